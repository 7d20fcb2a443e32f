"""Triton python-backend model that serves a neumip material with ONNX Runtime.

`neumip export-repository --backend python` copies this file as ``NAME/1/model.py`` beside
``NAME/1/model.onnx``, for Triton builds that have the python backend but not the onnxruntime one
(PyPI's nvidia-pytriton). It runs inside Triton's python stub and needs only numpy and onnxruntime
there (not neumip). Dynamic batching hands `execute` several requests: their rows go into one ONNX
Runtime call and are split back, which gives every row the same bits as a call of its own (the
exported graph is batch-invariant); requests of different widths (query groups of K lights,
``5 + 2 K`` columns, answered ``3 K``) go into one call per width. The session options come from the
config's ``parameters``
(``intra_op_thread_count``, ``inter_op_thread_count``), as for Triton's onnxruntime backend.

Checked with the tritonserver 2.51 that nvidia-pytriton 0.7.0 bundles: its python stub needs numpy
1.x in the Python it runs. With numpy 2.0.2 or 2.4.6 every output tensor arrives empty and Triton
answers "output tensor shape does not match size of output"; `initialize` warns about it.
"""

import json
import os

import numpy as np

MAX_LIGHTS = 64
"""Most lights of a query group (`neumip.core.contract.MAX_LIGHTS`; this file runs without neumip)."""


class TritonPythonModel:
    """One material: (N, 7) FP32 ``queries`` -> (N, 3) FP32 ``rgb``, or query groups (N, 5 + 2 K) ->
    (N, 3 K)."""

    def initialize(self, args):
        import onnxruntime as ort
        import triton_python_backend_utils as pb_utils

        if int(np.__version__.split(".")[0]) >= 2:
            pb_utils.Logger.log_warn(
                f"numpy {np.__version__}: python-backend stubs built for numpy 1.x (Triton 2.51) send empty "
                "output tensors with numpy 2; if answers fail, install numpy<2 for this Python"
            )

        config = json.loads(args["model_config"])
        params = {k: v["string_value"] for k, v in config.get("parameters", {}).items()}
        self.input = config["input"][0]["name"]
        self.output = config["output"][0]["name"]
        options = ort.SessionOptions()
        options.intra_op_num_threads = int(params.get("intra_op_thread_count", "0"))
        options.inter_op_num_threads = int(params.get("inter_op_thread_count", "0"))
        path = os.path.join(args["model_repository"], args["model_version"], "model.onnx")
        self.session = ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])

    def _queries(self, request):
        """The request's (n, 5 + 2 K) float32 queries, or an error message."""
        import triton_python_backend_utils as pb_utils

        queries = pb_utils.get_input_tensor_by_name(request, self.input).as_numpy()
        if queries.ndim != 2 or queries.shape[1] not in range(7, 5 + 2 * MAX_LIGHTS + 1, 2):
            return (f"{self.input} must be (N, 7) or (N, 5 + 2 K) for query groups of K <= {MAX_LIGHTS} lights, "
                    f"got {queries.shape}")
        bad = np.flatnonzero(~np.isfinite(queries).all(axis=1))
        if bad.size:
            return f"{self.input} row {bad[0]} holds NaN or Inf"
        return np.ascontiguousarray(queries, dtype=np.float32)

    def execute(self, requests):
        import triton_python_backend_utils as pb_utils

        checked = [self._queries(r) for r in requests]
        answers = [None] * len(checked)
        for width in {q.shape[1] for q in checked if not isinstance(q, str)}:  # one call per width
            same = [i for i, q in enumerate(checked) if not isinstance(q, str) and q.shape[1] == width]
            rgb = self.session.run([self.output], {self.input: np.concatenate([checked[i] for i in same])})[0]
            lo = 0
            for i in same:
                answers[i] = rgb[lo : lo + checked[i].shape[0]]
                lo += checked[i].shape[0]
        responses = []
        for queries, rgb in zip(checked, answers):
            if isinstance(queries, str):
                responses.append(pb_utils.InferenceResponse(error=pb_utils.TritonError(queries)))
            else:
                responses.append(pb_utils.InferenceResponse([pb_utils.Tensor(self.output, rgb)]))
        return responses
