"""The Triton python-backend model.py (`neumip.server.triton_python_model`) with a stand-in of Triton's
``triton_python_backend_utils``: a dynamic batch of plain queries, query groups and bad requests
answers each request on its own, with the bits of in-process evaluation. (A real Triton runs it in
the slow tests/server/test_triton.py.)"""

from __future__ import annotations

import json
import sys
import types
from dataclasses import dataclass

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core.contract import random_queries
from neumip.server.model_config import TritonOptions, model_config
from neumip.server.triton_python_model import TritonPythonModel


@dataclass
class _Tensor:
    name: str
    array: np.ndarray

    def as_numpy(self) -> np.ndarray:
        return self.array


@dataclass
class _Response:
    output_tensors: list | None = None
    error: str | None = None


@pytest.fixture
def pb_utils(monkeypatch):
    """The parts of ``triton_python_backend_utils`` that model.py calls."""
    module = types.SimpleNamespace(
        Tensor=_Tensor,
        InferenceResponse=_Response,
        TritonError=str,
        get_input_tensor_by_name=lambda request, name: _Tensor(name, request[name]),
        Logger=types.SimpleNamespace(log_warn=lambda message: None),
    )
    monkeypatch.setitem(sys.modules, "triton_python_backend_utils", module)
    return module


def model_for(tmp_path, model_dir) -> TritonPythonModel:
    (tmp_path / "1").mkdir()
    (tmp_path / "1" / "model.onnx").write_bytes((model_dir / "rand16.onnx").read_bytes())
    config = model_config("rand16", TritonOptions(1000, 100, 0, backend="python"))
    model = TritonPythonModel()
    model.initialize({"model_config": json.dumps(config), "model_repository": str(tmp_path), "model_version": "1"})
    return model


def test_a_batch_of_mixed_widths_answers_each_request(pb_utils, tmp_path, model_dir, reference):
    model = model_for(tmp_path, model_dir)
    plain, other = random_queries(30, seed=1), random_queries(5, seed=3)
    groups = np.hstack([random_queries(20, seed=2), random_queries(20, seed=4)[:, C.WI_X:C.WI_Y + 1]])
    requests = [{"queries": q} for q in (plain, groups, np.zeros((2, 8), np.float32), other)]
    responses = model.execute(requests)
    assert "(N, 5 + 2 K)" in responses[2].error
    for response, q in zip([responses[i] for i in (0, 1, 3)], (plain, groups, other)):
        [tensor] = response.output_tensors
        np.testing.assert_array_equal(tensor.array, reference.evaluate("rand16", q))


def test_its_copy_of_the_contract_agrees():
    """model.py runs inside Triton without neumip, so it repeats MAX_LIGHTS: the copies must agree."""
    from neumip.server import triton_python_model

    assert triton_python_model.MAX_LIGHTS == C.MAX_LIGHTS
