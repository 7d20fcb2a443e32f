"""A material made without neumip: a Lambertian checkerboard written with onnx.helper alone.

It follows the query contract (`neumip.core.contract`: input ``queries`` (N, 7) float32, output
``rgb`` (N, 3)) and carries no neumip metadata; the in-kernel engine renders it as it renders an
exported material, from its graph (`neumip.engines.onnx_kernel`):

    .venv/bin/python scenes/checkerboard.py /tmp/foreign/checker.onnx
    .venv/bin/neumip render scenes/closeup.xml -D material=checker --models /tmp/foreign -o checker.png

Each tile holds ``CHECKS x CHECKS`` squares, of albedo `LIGHT` and `DARK` (answers albedo / pi).
"""

from __future__ import annotations

import sys

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

CHECKS = 4
LIGHT = (0.8, 0.75, 0.6)
DARK = (0.1, 0.12, 0.2)


def checkerboard(checks: int = CHECKS, light=LIGHT, dark=DARK) -> onnx.ModelProto:
    """The graph: square (i, j) of u, v is light where i and j have the same parity."""
    consts = {
        "starts": np.array([0], np.int64), "ends": np.array([2], np.int64), "axes": np.array([1], np.int64),
        "checks": np.full((1, 1), checks, np.float32), "half": np.full((1, 1), 0.5, np.float32),
        "two": np.full((1, 1), 2.0, np.float32), "one": np.array([1], np.int64),
        "light": (np.asarray([light], np.float32) / np.pi).astype(np.float32),
        "dark": (np.asarray([dark], np.float32) / np.pi).astype(np.float32),
    }
    nodes = [
        helper.make_node("Slice", ["queries", "starts", "ends", "axes"], ["uv"]),  # (N, 2)
        helper.make_node("Mul", ["uv", "checks"], ["scaled"]),
        helper.make_node("Floor", ["scaled"], ["square"]),
        helper.make_node("Mul", ["square", "half"], ["halved"]),
        helper.make_node("Floor", ["halved"], ["pairs"]),
        helper.make_node("Mul", ["pairs", "two"], ["even"]),
        helper.make_node("Sub", ["square", "even"], ["parity"]),  # (N, 2): 0 or 1
        helper.make_node("Greater", ["parity", "half"], ["odd"]),
        helper.make_node("Cast", ["odd"], ["odd_f"], to=TensorProto.FLOAT),
        helper.make_node("Slice", ["odd_f", "starts", "one", "axes"], ["odd_u"]),  # (N, 1)
        helper.make_node("Slice", ["odd_f", "one", "ends", "axes"], ["odd_v"]),
        helper.make_node("Equal", ["odd_u", "odd_v"], ["same"]),
        helper.make_node("Where", ["same", "light", "dark"], ["rgb"]),  # (N, 3)
    ]
    graph = helper.make_graph(
        nodes, "checkerboard",
        [helper.make_tensor_value_info("queries", TensorProto.FLOAT, ["N", 7])],
        [helper.make_tensor_value_info("rgb", TensorProto.FLOAT, ["N", 3])],
        initializer=[numpy_helper.from_array(v, k) for k, v in consts.items()],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], producer_name="onnx.helper")
    model.ir_version = 9
    onnx.checker.check_model(model, full_check=True)
    return model


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(f"usage: {sys.argv[0]} OUT.onnx")
    onnx.save(checkerboard(), sys.argv[1])
