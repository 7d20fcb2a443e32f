"""An ONNX graph evaluated as drjit arithmetic, lane by lane: the in-kernel engine's interpreter.

`LaneGraph` reads a material's graph (any graph that maps ``queries`` (N, 5 + 2 K) or (N, 7) float32
to ``rgb`` (N, 3 K) or (N, 3) with the operators in `onnx_ops.OPERATORS`) and `LaneGraph.trace` writes
it as drjit operations on one lane per query row (`onnx_ops`: the tensors of a lane and the operators).

Initializers, and every node whose inputs are all constants, are computed once with numpy when the
graph loads (the export's quad tables, `training/export/lookup.py`, are such a subgraph). A constant
read by a ``Gather`` with computed indices (a texture) becomes a flat drjit array: `LaneGraph.tables`,
inputs of the frozen function.

A graph with a fixed input width of 7 (no query groups) is evaluated once per light of a group.
Needs numpy, onnx and drjit.
"""

from __future__ import annotations

import logging
from types import ModuleType

import drjit as dr
import numpy as np
import onnx
from onnx import TensorProto, numpy_helper

from neumip.core import contract as C

from neumip.engines.onnx_ops import OPERATORS, GraphError, Lanes, Ops, lift, objects, packed_table

log = logging.getLogger(__name__)


class LaneGraph:
    """A material's ONNX graph, read once: its constants folded, its textures as drjit arrays."""

    def __init__(self, model: onnx.ModelProto, backend: ModuleType) -> None:
        graph = model.graph
        self.backend = backend
        unsupported = sorted({n.op_type for n in graph.node
                              if n.op_type not in OPERATORS or n.domain not in ("", "ai.onnx")})
        if unsupported:
            raise GraphError(f"operator(s) {', '.join(unsupported)} not supported in the kernel "
                             f"(supported: {', '.join(sorted(OPERATORS))})")
        inits = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
        inputs = [i for i in graph.input if i.name not in inits]
        if [i.name for i in inputs] != [C.ONNX_INPUT] or [o.name for o in graph.output] != [C.ONNX_OUTPUT]:
            raise GraphError(f"graph must map '{C.ONNX_INPUT}' to '{C.ONNX_OUTPUT}'")
        if graph.output[0].type.tensor_type.elem_type != TensorProto.FLOAT:
            raise GraphError(f"'{C.ONNX_OUTPUT}' must be float32")
        dims = inputs[0].type.tensor_type.shape.dim
        if inputs[0].type.tensor_type.elem_type != TensorProto.FLOAT or len(dims) != 2:
            raise GraphError(f"'{C.ONNX_INPUT}' must be a 2-D float32 tensor")
        width = dims[1].dim_value if dims[1].HasField("dim_value") else None
        if width not in (None, C.QUERY_DIM):
            raise GraphError(f"'{C.ONNX_INPUT}' must be (N, {C.QUERY_DIM}) or query groups (N, 5 + 2 K), "
                             f"not (N, {width})")
        self.groups = width is None
        """Whether the graph takes query groups (otherwise each light is evaluated as a single query)."""
        constants, self.nodes = fold_constants(graph.node, inits)
        self.table_names = sorted({n.input[0] for n in self.nodes
                                   if n.op_type == "Gather" and n.input[0] in constants})
        for name in self.table_names:
            if constants[name].dtype not in (np.float32, np.float16):
                raise GraphError(f"computed indices read the table {name!r} of {constants[name].dtype} "
                                 "(only float32 and float16 tables)")
        self.tables = [packed_table(backend, constants[name]) for name in self.table_names]
        """The constants that computed indices read (textures), flat, their rows padded (`packed_table`): the frozen
        function's inputs."""
        self.table_shapes = [constants[name].shape for name in self.table_names]
        other = {name for n in self.nodes for i, name in enumerate(n.input) if i or n.op_type != "Gather"}
        self.constants = {name: constants[name] for name in other | {C.ONNX_OUTPUT} if name in constants}
        """The folded constants the traced nodes read (the tables only where they read more than rows)."""

    def trace(self, tables: list, columns: list) -> list:
        """drjit columns of query groups (5 + 2 K Floats, contract order) -> the lanes' answers, 3 K
        Floats; ``tables``: `tables` (passed, not captured, so that a frozen function takes them as
        inputs). A lane with a non-finite column answers 0."""
        lights = C.group_lights(len(columns))
        if self.groups:
            rgb = self._run(tables, columns)
        else:
            rgb = []
            more = range(C.QUERY_DIM, len(columns), 2)
            for wi in [columns[C.WI_X:C.WI_Y + 1]] + [columns[i:i + 2] for i in more]:
                rgb += self._run(tables, columns[:C.WI_X] + list(wi) + columns[C.WO_X:C.QUERY_DIM])
        if len(rgb) != C.RGB_DIM * lights:
            raise GraphError(f"'{C.ONNX_OUTPUT}' has {len(rgb)} columns for {lights} light(s), "
                             f"expected {C.RGB_DIM * lights}")
        # Tie every answer to its lane: an answer that does not depend on the query (a constant
        # material) is a literal, which a frozen function would replay at its first call's width.
        finite = dr.isfinite(columns[0])
        for column in columns[1:]:
            finite &= dr.isfinite(column)
        return [dr.select(finite, x, 0.0) for x in rgb]

    def _run(self, tables: list, columns: list) -> list:
        """The graph on one input tensor (N, len(columns)) -> the output's cells, one row."""
        env = {name: f"table {name}" for name in self.table_names}  # read by `Ops.Gather` from its tables
        env.update(self.constants)
        env[C.ONNX_INPUT] = Lanes(objects((1, 1, len(columns)), columns), 0)
        ops = Ops(self.backend, dict(zip(self.table_names, zip(tables, self.table_shapes))))
        for node in self.nodes:
            run_node(ops, node, env)
        out = env[C.ONNX_OUTPUT]
        if not isinstance(out, Lanes):  # a constant material: one row for every lane
            row = np.asarray(out, np.float32).reshape(-1, np.asarray(out).shape[-1])
            if len(row) != 1:
                raise GraphError(f"'{C.ONNX_OUTPUT}' is a constant of shape {np.shape(out)}, not one row")
            return [self.backend.Float(float(x)) for x in row[0]]
        if out.rank != 2 or out.axis != 0 or out.cells.shape[:2] != (1, 1):
            raise GraphError(f"'{C.ONNX_OUTPUT}' has shape {out.shape}, expected (N, 3 K)")
        return [lift(self.backend, x) for x in out.cells[0, 0]]


def fold_constants(nodes, inits: dict) -> tuple[dict, list]:
    """Compute every node whose inputs are all constants (numpy) -> (constants by name, the other nodes)."""
    constants, rest = dict(inits), []
    ops = Ops(None, {})
    for node in nodes:
        if all(not name or name in constants for name in node.input):
            run_node(ops, node, constants)
        else:
            rest.append(node)
    return constants, rest


def run_node(ops: Ops, node, env: dict) -> None:
    """Evaluate `node` on its inputs in `env` (by name), writing its outputs there; any failure is a
    GraphError naming the node."""
    missing = [name for name in node.input if name and name not in env]
    if missing:  # a name no earlier node, input or initializer gives: a graph written wrong, or damaged on disk
        raise GraphError(f"{node.op_type} node {node.name or node.output[0]!r} reads {missing[0]!r}, which nothing "
                         "before it produces (a damaged file?)")
    try:
        out = ops.run(node, [env[name] if name else None for name in node.input])
    except (GraphError, ValueError, IndexError, TypeError, KeyError, ArithmeticError, RuntimeError) as exc:
        raise GraphError(f"{node.op_type} node {node.name or node.output[0]!r}: {exc}") from None
    for name, value in zip(node.output, out if isinstance(out, tuple) else (out,)):
        env[name] = value
