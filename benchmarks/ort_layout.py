"""What ONNX Runtime's column shuffles cost against its arithmetic, and how many a model's graph runs a query.

    .venv/bin/python benchmarks/ort_layout.py                    # the shipped rock and yarn
    .venv/bin/python benchmarks/ort_layout.py --models rock --rows 16384

The export keeps the lookups' tensors row-major, (N, k) with k of 1-56, and moves columns with 0/1 MatMuls, Gemms,
Concat, Slice, Tile and Split (`training/export/lookup.py`). ONNX Runtime runs each of those per row. This script
times each kind as an intermediate node of one graph (ONNX Runtime's profiler, 1 thread, `--rows` rows a call, the
median of 30 calls), beside an elementwise Sub on the same rows; then, per model, counts the nodes of its optimised
graph that only move columns (a MatMul or Gemm whose constant operand is all 0 and 1 - without the Gemm's bias - a
Concat, Slice, Split, Tile or Transpose on a per-query tensor) and prices them at the measured per-row cost of their
kind: an estimate of the time a query spends moving columns, beside its whole kernel time (`bench_engines.py
--profile`).
"""

from __future__ import annotations

import argparse
import collections
import json
import tempfile
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

from neumip.core import contract as C
from neumip.engines.local import run_call

SHUFFLES = ("MatMul", "Gemm", "Concat", "Slice", "Split", "Tile", "Transpose")


def _session(model: onnx.ModelProto, folder: str | None = None, optimise: bool = True) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads, opts.log_severity_level = 1, 3
    if not optimise:
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    if folder:
        opts.enable_profiling, opts.profile_file_prefix = True, f"{folder}/profile"
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
              "taps": np.tile(np.asarray([[-1.0, 1.0]], np.float32), (4, 4)), "bias": np.ones(8, np.float32),
              "reps": np.asarray([1, 2], np.int64), "one": np.ones((1, 1), np.float32),
              "start": np.asarray([0], np.int64), "end": np.asarray([2], np.int64), "axis": np.asarray([1], np.int64)}
    kinds = {  # kind -> (op, inputs, attributes); each reads x (rows, 4) or w (rows, 8)
        "MatMul (4 -> 4 columns, 0/1)": ("MatMul", ["x", "pair"], {}),
        "MatMul (4 -> 2 columns, 0/1)": ("MatMul", ["x", "pick"], {}),
        "MatMul (8 -> 1 column, a sum)": ("MatMul", ["w", "sum"], {}),
        "Gemm (4 -> 8 columns, + bias)": ("Gemm", ["x", "taps", "bias"], {}),
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


def _is_shuffle(node: onnx.NodeProto, consts: dict[str, np.ndarray]) -> bool:
    """Whether `node` only moves a per-query tensor's columns (a 0/1 product without a bias, or a layout op)."""
    if node.op_type in ("MatMul", "Gemm"):
        if node.op_type == "Gemm" and len(node.input) > 2 and node.input[2]:
            return False
        operands = [consts.get(name) for name in node.input[:2]]
        return any(v is not None and v.ndim == 2 and np.isin(v, (0.0, 1.0)).all() for v in operands) and \
            any(v is None for v in operands)
    return node.op_type in SHUFFLES[2:] and any(name not in consts for name in node.input[:1])


def model_shuffles(path: Path, rows: int) -> tuple[collections.Counter, float]:
    """Column-moving nodes of the model's graph as ONNX Runtime optimises it, by op; and its kernel time a query (ns,
    1 thread, calls of `rows`)."""
    with tempfile.TemporaryDirectory() as folder:
        opts = ort.SessionOptions()
        opts.intra_op_num_threads, opts.log_severity_level = 1, 3
        opts.optimized_model_filepath = f"{folder}/optimised.onnx"
        opts.enable_profiling, opts.profile_file_prefix = True, f"{folder}/profile"
        sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        queries = C.random_queries(8 * rows, seed=20)
        for lo in range(0, len(queries), rows):
            run_call(sess, queries[lo:lo + rows])
        total = sum(_node_times(sess).values())  # the median call's nodes
        optimised = onnx.load(f"{folder}/optimised.onnx")
    consts = {i.name: numpy_helper.to_array(i) for i in optimised.graph.initializer}
    return collections.Counter(n.op_type for n in optimised.graph.node if _is_shuffle(n, consts)), total / rows * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, default=Path("models"))
    parser.add_argument("--models", type=lambda t: t.split(","), default=["rock", "yarn"])
    parser.add_argument("--rows", type=int, default=16384, help="queries a call")
    args = parser.parse_args()
    print(f"# onnxruntime {ort.__version__}, 1 thread, calls of {args.rows} rows (ns a row: the node's kernel time "
          f"/ rows, median of 30 calls)")
    costs = op_costs(args.rows)
    for kind, ns in costs.items():
        print(f"  {kind:32s} {ns:6.2f} ns a row")
    per_op = {op: float(np.median([ns for kind, ns in costs.items() if kind.startswith(op)])) for op in SHUFFLES}
    for name in args.models:
        counts, total = model_shuffles(args.folder / f"{name}.onnx", args.rows)
        moving = sum(per_op[op] * n for op, n in counts.items())
        print(f"\n## {name}: {sum(counts.values())} nodes only move columns ("
              + ", ".join(f"{op} {n}" for op, n in counts.most_common()) + f"); at the costs above about {moving:.0f} "
              f"ns a query, of {total:.0f} ns of kernel time a query ({100 * moving / total:.0f} %)")


if __name__ == "__main__":
    main()
