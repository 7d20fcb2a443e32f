"""Shared fixtures: small exported materials built from numpy weights (no training needed)."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.client import contract as C


@pytest.fixture(scope="session")
def model_dir(tmp_path_factory):
    """A folder with two small random materials (`rand16`, offset on; `flat16`, offset off) and a
    constant Lambertian `lambert` answering 0.5 / pi."""
    from neumip.training.config import MaterialConfig
    from neumip.training.export import build_onnx, constant_weights, random_weights, save_onnx

    folder = tmp_path_factory.mktemp("models")
    cfg = MaterialConfig(resolution=16)
    save_onnx(build_onnx(cfg, random_weights(cfg, seed=1), "random test material"), folder / "rand16.onnx")
    flat = MaterialConfig(resolution=16, offset=False)
    save_onnx(build_onnx(flat, random_weights(flat, seed=2)), folder / "flat16.onnx")
    save_onnx(
        build_onnx(cfg, constant_weights(cfg, [0.5 / np.pi] * 3), "Lambertian, albedo 0.5"),
        folder / "lambert.onnx",
    )
    return folder
