"""A small writer of ONNX graphs: names nodes and constants while the export builds a graph.

Only numpy and onnx; the material's stages (`lookup.py`, `graph.py`) are written with it.

A constant is stored once: an unnamed constant of more than one element that holds the same values as
an earlier one (dtype, shape, bytes) is that one's initializer (`shared_key`), e.g. the 0/1 matrices of
the lookups of pyramids of one width. Named constants (weights, ``lod.*``, ``quad.*``) and
single numbers (a level-of-detail Clip's bounds, which `neumip trim` swaps per pyramid; the (1, 1)
scalars) keep one initializer per use.
"""

from __future__ import annotations

import hashlib

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from neumip.core import weights as W


COLUMN_ALPHA = 2.0
"""The Gemm alpha of `GraphWriter.product` (its matrices are stored halved)."""

def shared_key(value: np.ndarray) -> tuple | None:
    """What makes two unnamed constants one initializer: (dtype, shape, digest of the bytes), None for a single
    number (kept per use: `neumip trim` swaps one pyramid's Clip bound, whatever the others hold)."""
    if value.size <= 1:
        return None
    return value.dtype.str, value.shape, hashlib.sha256(np.ascontiguousarray(value).tobytes()).digest()


class GraphWriter:
    """Collects nodes and initializers; every op returns the name of its (first) output."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self._n = 0
        self._shared: dict[tuple, str] = {}  # `shared_key` -> the initializer holding it

    def _name(self, hint: str) -> str:
        self._n += 1
        return f"{hint}_{self._n}"

    def const(self, value, dtype=np.float32, name: str | None = None) -> str:
        """An initializer holding `value` as `dtype`, named `name` or c_N; an unnamed one holding what an
        earlier one holds is that one (`shared_key`). Every unnamed constant advances the count N, stored or
        shared, so the other names do not depend on the values (a trimmed model's graph and an export at
        its level name their constants alike)."""
        value = np.asarray(value, dtype=dtype)
        if name is None:
            name = self._name("c")
            key = shared_key(value)
            if key is not None and self._shared.setdefault(key, name) != name:
                return self._shared[key]
        self.inits.append(numpy_helper.from_array(value, name))
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

    def product(self, w: np.ndarray, x: str, bias: str | None = None, rows: bool = False,
                name: str | None = None) -> str:
        """W (out, in) times the columns of `x` -> (out, N), column-major: `x` is (in, N), or (N, in)
        with ``rows`` (read transposed by the Gemm), `bias` (out, 1) is added.

        Activations one query per column keep ONNX Runtime's matrix kernels on full vectors (a layer
        of 25 outputs fills 16-lane vectors along N, not 25 of 32 lanes per row). The file stores
        W / 2 (named `name`) and the Gemm multiplies by alpha = 2, exact: with alpha 1 ONNX Runtime
        (MLAS) computes a 1-column product - a call of one query - with its GEMV kernel, which sums in
        another order than a wider call, and a query's answer would depend on its batch.
        """
        half = self.const(np.asarray(w, np.float32) * np.float32(0.5), name=name)
        inputs = [half, x] + ([bias] if bias is not None else [])
        return self.op("Gemm", *inputs, alpha=COLUMN_ALPHA, transB=1 if rows else 0)

    def mlp(self, x: str, weights: dict, prefix: str, layers: int, first: int = 0) -> str:
        """Column-major activations (in, N) -> (out, N) through layers first..layers-1 of MLP
        `prefix` (`weights.weight` (out, in) and `weights.bias` of each, `neumip.core.weights`): Gemm +
        Relu, no Relu after the last layer. Initializers `weights.half_weight` and `weights.bias`."""
        for i in range(first, layers):
            bias = self.const(weights[W.bias(prefix, i)][:, None], name=W.bias(prefix, i))
            x = self.product(weights[W.weight(prefix, i)], x, bias, name=W.half_weight(prefix, i))
            if i < layers - 1:
                x = self.op("Relu", x)
        return x

    def model(self, input_name: str, input_dim: int | str, output_name: str, output_dim: int | str,
              opset: int, ir_version: int) -> onnx.ModelProto:
        """The finished model: one float32 (N, input_dim) input, one (N, output_dim) output (a str
        dimension is a named dynamic one)."""
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
