"""Would half precision keep a model's answers within the contract's parity? Each texture (and the MLPs' weights)
of a model rounded to float16 and back, the rest as stored; ONNX Runtime's answers against the file's own.

    python experiments/half_precision/half_probe.py rock_maps rock     # models/NAME.onnx

Parity: |a - b| <= 1e-5 + 1e-4 |b| (the export's tolerance, tests' `assert_parity`).
"""

from __future__ import annotations

import sys

import numpy as np
import onnx
import onnxruntime as ort
from onnx import numpy_helper

from neumip.core import contract as C

PARTS = ("pyramid", "offset_texture", "base_maps", "relief_heights", "mlps")


def answers(model: onnx.ModelProto, q: np.ndarray) -> np.ndarray:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    return session.run(None, {C.ONNX_INPUT: q})[0]


def main() -> int:
    q = C.random_queries(65536, seed=3)
    for name in sys.argv[1:]:
        model = onnx.load(f"models/{name}.onnx")
        base = answers(model, q)
        for part in PARTS:
            rounded = onnx.ModelProto()
            rounded.CopyFrom(model)
            hit = False
            for init in rounded.graph.initializer:
                if init.name == part or (part == "mlps" and "half_weight" in init.name):
                    a = numpy_helper.to_array(init)
                    init.CopyFrom(numpy_helper.from_array(a.astype(np.float16).astype(np.float32), init.name))
                    hit = True
            if not hit:
                continue
            d = np.abs(answers(rounded, q) - base)
            outside = d > 1e-5 + 1e-4 * np.abs(base)
            print(f"{name} {part:15s} largest difference {d.max():.2e}, outside parity: {outside.mean() * 100:.2f} % "
                  f"of {base.size} answers")
    return 0


if __name__ == "__main__":
    sys.exit(main())
