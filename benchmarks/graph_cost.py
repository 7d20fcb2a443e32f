"""What a model's graph asks of the machine a query, read from its shapes: the bytes its texture gathers read and its
arithmetic. The bounds of `bench_cuda.py` (a GPU) and `bench_engines.py` (the arithmetic of the MLP-only graph scaled
to the model's) come from it.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import helper, shape_inference


def _shapes(graph) -> tuple[dict[str, list], dict[str, int]]:
    """Every tensor's shape (ints, or a str where a dimension is symbolic: the batch) and its element's bytes."""
    shapes = {i.name: list(i.dims) for i in graph.initializer}
    types = {i.name: i.data_type for i in graph.initializer}
    for v in list(graph.value_info) + list(graph.input) + list(graph.output):
        dims = v.type.tensor_type.shape.dim
        shapes.setdefault(v.name, [d.dim_value if d.HasField("dim_value") else (d.dim_param or "?") for d in dims])
        types.setdefault(v.name, v.type.tensor_type.elem_type)
    sizes = {name: helper.tensor_dtype_to_np_dtype(t).itemsize for name, t in types.items() if t}
    return shapes, sizes


def graph_cost(model: onnx.ModelProto) -> dict:
    """Per single query, from the graph's shapes: bytes its texture gathers read (rows of tables read with per-query
    indices, in the tables' type), FLOPs of its matrix products with a per-query operand, and elements the other
    nodes write (one operation each; layout nodes - Reshape, Gather, Concat, Cast - count too, tap products over
    folded rows do not: an estimate, not a floor); and the node count. A symbolic first dimension is taken as the
    batch."""
    graph = shape_inference.infer_shapes(model).graph
    known, item = _shapes(graph)
    read = flops = elements = 0
    for node in graph.node:
        shapes = [known.get(name) for name in node.input[:2]]
        out = known.get(node.output[0])
        if node.op_type not in ("MatMul", "Gemm") and out and isinstance(out[0], str):
            elements += int(np.prod([d for d in out[1:] if isinstance(d, int)], dtype=np.int64))
        if None in shapes:
            continue
        if node.op_type == "Gather":
            data, indices = shapes
            if indices and isinstance(indices[0], str) and all(isinstance(d, int) for d in data):
                read += (int(np.prod(indices[1:], dtype=np.int64)) * int(np.prod(data[1:], dtype=np.int64))
                         * item.get(node.input[0], 4))
        elif node.op_type in ("MatMul", "Gemm"):
            fixed = [s for s in shapes if all(isinstance(d, int) for d in s)]
            if len(fixed) == 1 and len(fixed[0]) == 2:
                flops += 2 * fixed[0][0] * fixed[0][1]
    return {"bytes": read, "flops": flops, "elements": elements, "nodes": len(graph.node)}


def operations(cost: dict) -> int:
    """A query's operations: its products' FLOPs plus the other nodes' elements (one operation each)."""
    return cost["flops"] + cost["elements"]
