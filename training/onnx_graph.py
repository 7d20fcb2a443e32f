"""A small writer of ONNX graphs: names nodes and constants while the export builds a graph.

Only numpy and onnx; the material's stages (`export_lookup.py`, `export.py`) are written with it.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


class GraphWriter:
    """Collects nodes and initializers; every op returns the name of its (first) output."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self._n = 0

    def _name(self, hint: str) -> str:
        self._n += 1
        return f"{hint}_{self._n}"

    def const(self, value, dtype=np.float32, name: str | None = None) -> str:
        name = name or self._name("c")
        self.inits.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def scalar(self, value: float) -> str:
        """A float32 constant of shape (1, 1) for elementwise ops on 2-D tensors.

        ONNX Runtime 1.31 runs (N, 1) <op> () and (N, 1) <op> (1,) through a slow broadcasting path
        (tens of times slower than (N, 1) <op> (1, 1); benchmarks/bench_inference.py --sections ops).
        """
        return self.const(np.full((1, 1), value, np.float32))

    def op(self, op_type: str, *inputs: str, outputs: int = 1, **attrs):
        names = [self._name(op_type.lower()) for _ in range(outputs)]
        self.nodes.append(helper.make_node(op_type, list(inputs), names, **attrs))
        return names[0] if outputs == 1 else names

    def shape(self, x: str, dims) -> str:
        """Reshape `x` to `dims` (0 copies a dimension, -1 infers one)."""
        return self.op("Reshape", x, self.const(list(dims), np.int64))

    def pick(self, x: str, width: int, columns: list[int]) -> str:
        """Columns of (N, width) `x` -> (N, len(columns)), by a MatMul with a 0/1 matrix.

        Exact for finite values, and cheaper in ONNX Runtime than Split/Slice/Concat of narrow
        columns (those copy row by row).
        """
        select = np.zeros((width, len(columns)), np.float32)
        select[columns, np.arange(len(columns))] = 1.0
        return self.op("MatMul", x, self.const(select))

    def wrap(self, u: str) -> str:
        """Position -> position in [0, 1]: u - floor(u)."""
        return self.op("Sub", u, self.op("Floor", u))

    def linear(self, x: str, weights: dict, prefix: str, layer: int, relu: bool) -> str:
        """One Gemm (+ Relu) with weights[f"{prefix}.{layer}.weight"] (out, in) and its bias."""
        w = self.const(weights[f"{prefix}.{layer}.weight"], name=f"{prefix}.{layer}.weight")
        b = self.const(weights[f"{prefix}.{layer}.bias"], name=f"{prefix}.{layer}.bias")
        x = self.op("Gemm", x, w, b, transB=1)
        return self.op("Relu", x) if relu else x

    def mlp(self, x: str, weights: dict, prefix: str, layers: int, first: int = 0) -> str:
        """Gemm + Relu chain over layers first..layers-1; no Relu after the last layer."""
        for i in range(first, layers):
            x = self.linear(x, weights, prefix, i, relu=i < layers - 1)
        return x

    def model(self, input_name: str, input_dim: int, output_name: str, output_dim: int, opset: int,
              ir_version: int) -> onnx.ModelProto:
        """The finished model: one float32 (N, input_dim) input, one (N, output_dim) output."""
        graph = helper.make_graph(
            self.nodes,
            "neumip_material",
            [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, ["N", input_dim])],
            [helper.make_tensor_value_info(output_name, TensorProto.FLOAT, ["N", output_dim])],
            initializer=self.inits,
        )
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], producer_name="neumip")
        model.ir_version = ir_version
        return model
