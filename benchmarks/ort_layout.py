"""Where ONNX Runtime's time goes in a model's graph: moving columns, summing them, reading tables, arithmetic.

    .venv/bin/python benchmarks/ort_layout.py                    # the shipped rock and yarn
    .venv/bin/python benchmarks/ort_layout.py --models rock --rows 16384

The export keeps the lookups' tensors row-major, (N, k) with k of 1-56, and moves columns with 0/1 MatMuls, Concat,
Slice and Tile (`training/export/lookup.py`); ONNX Runtime runs each of those row by row. First, each kind of node
timed alone as an intermediate of one graph on (rows, 4) float32 (4-8 columns out; ONNX Runtime's profiler, 1
thread, `--rows` rows a call, the median of 30 calls, no graph optimisation), beside an elementwise Sub. Then, per
model, its kernel time a query (the same profiler, the median call of each node) split by the kind of each node of
the graph ONNX Runtime optimises that runs on the queries' rows (`kind`): "move" (a product with a constant 0/1
matrix of at most one 1 per output column, alpha 1, no bias; a Concat, Slice, Split, Tile or Transpose of computed
tensors), "sum" (a 0/1 matrix that adds columns), "read" (a Gather of a table) and "arithmetic" (the rest, the MLPs
among it).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import tempfile
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

from neumip.core import contract as C
from neumip.engines.local import run_call

SHUFFLES = ("MatMul", "Gemm", "Concat", "Slice", "Split", "Tile", "Transpose")


def _session(model: onnx.ModelProto, folder: str, optimise: bool = True) -> ort.InferenceSession:
    """A profiled one-thread session of `model` (its profile and, optimised, its graph as ``folder/optimised.onnx``)."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads, opts.log_severity_level = 1, 3
    opts.enable_profiling, opts.profile_file_prefix = True, f"{folder}/profile"
    if optimise:
        opts.optimized_model_filepath = f"{folder}/optimised.onnx"
    else:
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])


def _node_times(sess: ort.InferenceSession) -> dict[str, float]:
    """Median kernel time (us) of each node of a profiled session's calls."""
    per = collections.defaultdict(list)
    for e in json.loads(Path(sess.end_profiling()).read_text()):
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            per[e["name"][:-len("_kernel_time")]].append(e["dur"])
    return {name: float(np.median(v)) for name, v in per.items()}


def op_costs(rows: int) -> dict[str, float]:
    """ns a row of each kind of node on (rows, 4) float32 (8 columns out where it widens), as intermediates."""
    consts = {"pair": np.asarray([[1, 0, 1, 0], [0, 1, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]], np.float32),
              "pick": np.eye(4, 2, dtype=np.float32), "sum": np.ones((8, 1), np.float32),
              "taps": np.tile(np.eye(4, dtype=np.float32), (1, 2)),
              "reps": np.asarray([1, 2], np.int64), "one": np.ones((1, 1), np.float32),
              "start": np.asarray([0], np.int64), "end": np.asarray([2], np.int64), "axis": np.asarray([1], np.int64)}
    kinds = {  # kind -> (op, inputs, attributes); each reads x (rows, 4) or w (rows, 8)
        "MatMul (4 -> 4 columns, 0/1)": ("MatMul", ["x", "pair"], {}),
        "MatMul (4 -> 2 columns, 0/1)": ("MatMul", ["x", "pick"], {}),
        "MatMul (8 -> 1 column, a sum)": ("MatMul", ["w", "sum"], {}),
        "Gemm (4 -> 8 columns, 0/1)": ("Gemm", ["x", "taps"], {}),
        "Concat (4 + 4 columns)": ("Concat", ["x", "x"], {"axis": 1}),
        "Slice (2 of 4 columns)": ("Slice", ["x", "start", "end", "axis"], {}),
        "Split (4 into 2 + 2)": ("Split", ["x"], {"axis": 1, "num_outputs": 2}),
        "Tile (4 -> 8 columns)": ("Tile", ["x", "reps"], {}),
        "Transpose (4 columns)": ("Transpose", ["x"], {}),
        "Sub (8 columns, elementwise)": ("Sub", ["one", "w"], {}),
    }
    nodes, outs = [helper.make_node("Tile", ["x", "reps"], ["w"], name="widen")], []
    for i, (kind, (op, inputs, attrs)) in enumerate(kinds.items()):
        names = [f"n{i}"] if op != "Split" else [f"n{i}", f"n{i}b"]
        nodes.append(helper.make_node(op, inputs, names, name=f"k{i}", **attrs))
        outs.append(names[0])
    nodes.append(helper.make_node("Concat", [o for o in outs if o != "n8"], ["y"], axis=1, name="sink"))
    graph = helper.make_graph(nodes, "kinds", [helper.make_tensor_value_info("x", TensorProto.FLOAT, None)],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, None),
                               helper.make_tensor_value_info("n8", TensorProto.FLOAT, None)],
                              [numpy_helper.from_array(v, k) for k, v in consts.items()])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)
    x = np.random.default_rng(0).random((rows, 4), np.float32)
    with tempfile.TemporaryDirectory() as folder:
        sess = _session(model, folder, optimise=False)
        for _ in range(30):
            sess.run(None, {"x": x})
        times = _node_times(sess)
    return {kind: times[f"k{i}"] / rows * 1e3 for i, kind in enumerate(kinds)}


def _pick_matrix(node: onnx.NodeProto, consts: dict[str, np.ndarray]) -> np.ndarray | None:
    """A product's constant operand as (in, out) where the other operand is computed and the product adds nothing
    else (no bias, alpha 1); None otherwise."""
    attrs = {a.name: helper.get_attribute_value(a) for a in node.attribute}
    if node.op_type not in ("MatMul", "Gemm", "FusedMatMul") or attrs.get("alpha", 1.0) != 1.0:
        return None
    if node.op_type == "Gemm" and len(node.input) > 2 and node.input[2]:
        return None
    a, b = (consts.get(name) for name in node.input[:2])
    if (a is None) == (b is None) or (b if a is None else a).ndim != 2:
        return None
    if b is not None:  # x @ B: B's columns are the outputs
        return b.T if attrs.get("transB") else b
    return a if attrs.get("transA") else a.T  # A @ x, x column-major: A's rows are the outputs


def kind(node: onnx.NodeProto, consts: dict[str, np.ndarray]) -> str:
    """'move' where `node` only copies a tensor's columns (a product with a 0/1 matrix of at most one 1 per output,
    or a layout op with a computed input), 'sum' where a 0/1 matrix adds columns, 'read' for a Gather of a
    table, else 'arithmetic'."""
    matrix = _pick_matrix(node, consts)
    if matrix is not None and np.isin(matrix, (0.0, 1.0)).all():
        return "move" if (matrix.sum(axis=0) <= 1).all() else "sum"
    if node.op_type in SHUFFLES[2:] and any(name and name not in consts for name in node.input):
        return "move"
    if node.op_type == "Gather" and node.input[0] in consts:
        return "read"
    return "arithmetic"


def model_time(path: Path, rows: int) -> tuple[dict[str, float], collections.Counter, float]:
    """The model's kernel time a query (ns, 1 thread, calls of `rows`: the median call of each node) by `kind` of
    node in the graph ONNX Runtime optimises, the nodes of each kind that run on the queries' rows, and the total.
    Nodes are named before loading so that the profile and the optimised graph name them alike."""
    model = onnx.load(str(path))
    for i, node in enumerate(model.graph.node):
        node.name = f"node{i}"
    with tempfile.TemporaryDirectory() as folder:
        sess = _session(model, folder)
        queries = C.random_queries(8 * rows, seed=20)
        for lo in range(0, len(queries), rows):
            run_call(sess, queries[lo:lo + rows])
        events = json.loads(Path(sess.end_profiling()).read_text())
        optimised = onnx.load(f"{folder}/optimised.onnx")
    times, per_query = collections.defaultdict(list), set()
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            name = e["name"][:-len("_kernel_time")]
            times[name].append(e["dur"])
            if any(rows in next(iter(t.values())) for t in e["args"].get("output_type_shape", [])):
                per_query.add(name)
    consts = {i.name: numpy_helper.to_array(i) for i in optimised.graph.initializer}
    by_kind, counts = collections.Counter(), collections.Counter()
    for node in optimised.graph.node:
        if node.name in times and node.name in per_query:
            by_kind[kind(node, consts)] += float(np.median(times[node.name])) / rows * 1e3
            counts[kind(node, consts), node.op_type] += 1
    total = sum(float(np.median(v)) for v in times.values()) / rows * 1e3
    return dict(by_kind), counts, total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, default=Path("models"))
    parser.add_argument("--models", type=lambda t: t.split(","), default=["rock", "yarn"])
    parser.add_argument("--rows", type=int, default=16384, help="queries a call")
    args = parser.parse_args()
    print(f"# onnxruntime {ort.__version__}, 1 thread, calls of {args.rows} rows (ns a row: the node's kernel time "
          f"/ rows, median of 30 calls); load average %.2f (1 min), %.2f (5 min)" % os.getloadavg()[:2])
    for what, ns in op_costs(args.rows).items():
        print(f"  {what:32s} {ns:6.2f} ns a row")
    for name in args.models:
        by_kind, counts, total = model_time(args.folder / f"{name}.onnx", args.rows)
        print(f"\n## {name}: {total:.0f} ns of kernel time a query; by kind of node on the queries' rows:")
        for k in ("move", "sum", "read", "arithmetic"):
            ops = ", ".join(f"{op} {n}" for (kk, op), n in counts.most_common() if kk == k)
            print(f"  {k:10s} {by_kind.get(k, 0.0):6.0f} ns ({100 * by_kind.get(k, 0.0) / total:4.1f} %): {ops}")


if __name__ == "__main__":
    main()
