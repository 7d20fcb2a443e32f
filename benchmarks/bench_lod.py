"""Benchmark: the export's exact level of detail (`training/export_lod.py`) against the former Log one.

Builds the default graph of a 256^2 material with random weights twice - as exported, and with the
former level of detail (``Log`` of sigma * R, then Floor) swapped in - and prints, for each:

- rows whose answer changes bits when the same queries are evaluated in chunks of 17 rows instead of
  one call (the batch dependence the exact level of detail removes);
- queries per second on one thread for calls of 4096 rows (the in-process evaluator's chunk), both
  variants interleaved round by round, median of the rounds, and their ratio.

    .venv/bin/python benchmarks/bench_lod.py [--rows 65536] [--rounds 5]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from unittest import mock

import numpy as np
import onnxruntime as ort
from onnx import TensorProto

from neumip.client import contract as C
from neumip.client.contract import random_queries
from neumip.training import export_lookup
from neumip.training.config import MaterialConfig
from neumip.training.export import build_onnx, random_weights
from neumip.training.onnx_graph import GraphWriter


def log_level_of_detail(g: GraphWriter, sigma: str, config: MaterialConfig, finest_level: int = 0,
                        tables: dict | None = None) -> tuple[dict, str]:
    """The former stage: sigma (N, 1) -> lo = floor of a Log (batch-dependent bits), row lo of each
    per-level table (Gather), t (N, 1)."""
    tiny = np.finfo(np.float32).tiny
    scaled = g.op("Mul", g.op("Max", sigma, g.scalar(tiny)), g.scalar(config.resolution))
    lod = g.op("Div", g.op("Log", scaled), g.scalar(math.log(2.0)))
    lod = g.op("Clip", lod, g.const(float(finest_level)), g.const(float(config.levels)))
    lo = g.op("Floor", lod)
    index = g.shape(g.op("Cast", lo, to=TensorProto.INT64), [-1])
    rows = {name: g.op("Gather", g.const(table), index, axis=0) for name, table in (tables or {}).items()}
    return rows, g.op("Sub", lod, lo)


def session(model) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])


def rows_changed_by_chunking(sess, q: np.ndarray, chunk: int = 17) -> int:
    whole = sess.run(None, {C.ONNX_INPUT: q})[0]
    parts = np.concatenate([sess.run(None, {C.ONNX_INPUT: q[i : i + chunk]})[0] for i in range(0, len(q), chunk)])
    return int((whole.view(np.uint32) != parts.view(np.uint32)).any(axis=1).sum())


def queries_per_second(sess, q: np.ndarray, batch: int, seconds: float) -> float:
    done, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        lo = (done * batch) % (len(q) - batch)
        sess.run(None, {C.ONNX_INPUT: q[lo : lo + batch]})
        done += 1
    return done * batch / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=65536, help="queries checked for chunking changes")
    parser.add_argument("--batch", type=int, default=4096, help="rows per call in the speed rounds")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=0.5, help="time per variant per round")
    args = parser.parse_args()

    cfg = MaterialConfig()
    weights = random_weights(cfg, seed=0)
    with mock.patch.object(export_lookup, "level_of_detail", log_level_of_detail):
        former = session(build_onnx(cfg, weights))
    sessions = {"exact (export_lod)": session(build_onnx(cfg, weights)), "former (Log)": former}
    q = random_queries(max(args.rows, 4 * args.batch), seed=1)
    a, b = (s.run(None, {C.ONNX_INPUT: q[:args.rows]})[0] for s in sessions.values())
    print(f"256^2 material, random weights; {args.rows} random queries; exact vs former answers differ by "
          f"at most {np.abs(a - b).max():.2e}")
    speeds: dict[str, list[float]] = {name: [] for name in sessions}
    for _ in range(args.rounds):
        for name, sess in sessions.items():
            speeds[name].append(queries_per_second(sess, q, args.batch, args.seconds))
    print(f"{'level of detail':20s} {'rows changed by 17-row chunks':>30s} {'M queries/s (1 thread)':>24s}")
    for name, sess in sessions.items():
        changed = rows_changed_by_chunking(sess, q[: args.rows])
        print(f"{name:20s} {changed:>30d} {statistics.median(speeds[name]) / 1e6:>24.3f}")
    ratio = statistics.median(speeds["exact (export_lod)"]) / statistics.median(speeds["former (Log)"])
    print(f"exact / former speed: {ratio:.3f} (calls of {args.batch} rows, median of {args.rounds} rounds)")


if __name__ == "__main__":
    main()
