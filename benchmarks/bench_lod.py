"""Benchmark: the export's level of detail (`training/export/lod.py`) against two former ones.

Builds the default graph of a 256^2 material with random weights three times - as exported (the
per-level tables read by one exact Gemm of level steps), with the former exact stage (floor(log2) and
2^-lo read from tables indexed by floor(sigma R), then the level pair's parameters by lo: three
Gathers), and with the first one (``Log`` of sigma * R, then Floor, then the Gathers) - and prints,
for each:

- rows whose answer changes bits when the same queries are evaluated in chunks of 17 rows instead of
  one call (the batch dependence the exact stages remove), and rows whose bits differ from the
  export's;
- queries per CPU-second of this process on one thread for calls of 4096 rows (the in-process
  evaluator's chunk), and the ratio to the export's measured in the same round (the variants
  alternate, order reversed every other round; median and quartiles over the rounds).

    .venv/bin/python benchmarks/bench_lod.py [--rows 65536] [--rounds 30]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from unittest import mock

import numpy as np
import onnxruntime as ort
from onnx import TensorProto

from neumip.core import contract as C
from neumip.core.contract import random_queries
from neumip.training.export import lookup as export_lookup
from neumip.core.config import MaterialConfig
from neumip.training.export.graph import build_onnx, random_weights
from neumip.training.export.lod import clip_min, log2_mantissa
from neumip.training.export.onnx_graph import GraphWriter


def _table_rows(g: GraphWriter, lo: str, tables: dict | None) -> dict:
    """Row lo (N,) of each per-level table: one Gather of the tables side by side, then 0/1 picks."""
    tables = tables or {}
    if not tables:
        return {}
    table = np.concatenate(list(tables.values()), axis=1)
    rows = g.op("Gather", g.const(table), lo, axis=0)
    out, start = {}, 0
    for name, value in tables.items():
        out[name] = g.pick(rows, table.shape[1], list(range(start, start + value.shape[1])))
        start += value.shape[1]
    return out


def gather_level_of_detail(g: GraphWriter, sigma: str, config: MaterialConfig, finest_level: int = 0,
                           tables: dict | None = None) -> tuple[dict, str]:
    """The former exact stage: lo and 2^-lo Gathered from tables indexed by floor(x), x = clip(sigma
    R, 2^K, 2^L), then the per-level tables by lo (the same bits as the export's)."""
    x = g.op("Clip", g.op("Mul", sigma, g.scalar(config.resolution)), g.const(clip_min(finest_level)),
             g.const(2.0**config.levels))
    index = g.shape(g.op("Cast", g.op("Floor", x), to=TensorProto.INT64), [-1])  # (N,) in [1, 2^L]
    k = np.maximum(np.arange(2**config.levels + 1), 1)
    floor_log2 = np.asarray([int(i).bit_length() - 1 for i in k], np.int64)  # row k: floor(log2 k)
    lo = g.op("Gather", g.const(floor_log2, np.int64), index, axis=0)  # (N,)
    scale = g.op("Gather", g.const(2.0 ** -floor_log2[:, None].astype(np.float64)), index, axis=0)  # (N, 1)
    return _table_rows(g, lo, tables), log2_mantissa(g, g.op("Mul", x, scale))


def log_level_of_detail(g: GraphWriter, sigma: str, config: MaterialConfig, finest_level: int = 0,
                        tables: dict | None = None) -> tuple[dict, str]:
    """The first stage: lo = floor of a Log (batch-dependent bits), the tables Gathered by lo."""
    tiny = np.finfo(np.float32).tiny
    scaled = g.op("Mul", g.op("Max", sigma, g.scalar(tiny)), g.scalar(config.resolution))
    lod = g.op("Div", g.op("Log", scaled), g.scalar(math.log(2.0)))
    lod = g.op("Clip", lod, g.const(float(finest_level)), g.const(float(config.levels)))
    lo = g.op("Floor", lod)
    index = g.shape(g.op("Cast", lo, to=TensorProto.INT64), [-1])
    return _table_rows(g, index, tables), g.op("Sub", lod, lo)


def session(model) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])


def rows_changed_by_chunking(sess, q: np.ndarray, chunk: int = 17) -> int:
    whole = sess.run(None, {C.ONNX_INPUT: q})[0]
    parts = np.concatenate([sess.run(None, {C.ONNX_INPUT: q[i : i + chunk]})[0] for i in range(0, len(q), chunk)])
    return int((whole.view(np.uint32) != parts.view(np.uint32)).any(axis=1).sum())


def cpu_rate(sess, q: np.ndarray, batch: int, seconds: float, start: int) -> float:
    """Queries per CPU-second of this process, calls of `batch` consecutive rows of `q` from `start`."""
    done, wall, cpu = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - wall < seconds:
        lo = (start + done * batch) % (len(q) - batch)
        sess.run(None, {C.ONNX_INPUT: q[lo : lo + batch]})
        done += 1
    return done * batch / max(time.process_time() - cpu, 1e-9)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=65536, help="queries checked for chunking changes")
    parser.add_argument("--batch", type=int, default=4096, help="rows per call in the speed rounds")
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--seconds", type=float, default=0.15, help="time per variant per round")
    args = parser.parse_args()

    cfg = MaterialConfig()
    weights = random_weights(cfg, seed=0)
    sessions = {"export (Gemm of steps)": session(build_onnx(cfg, weights))}
    for name, stage in (("former exact (Gathers)", gather_level_of_detail), ("first (Log, Gathers)", log_level_of_detail)):
        with mock.patch.object(export_lookup, "level_of_detail", stage):
            sessions[name] = session(build_onnx(cfg, weights))
    q = random_queries(max(args.rows, 64 * args.batch), seed=1)
    answers = {name: s.run(None, {C.ONNX_INPUT: q[: args.rows]})[0] for name, s in sessions.items()}
    export = next(iter(answers.values()))
    print(f"256^2 material, random weights; {args.rows} random queries; {load_text()}")
    rates: dict[str, list[float]] = {name: [] for name in sessions}
    ratios: dict[str, list[float]] = {name: [] for name in sessions}
    for r in range(args.rounds):
        names = list(sessions) if r % 2 == 0 else list(sessions)[::-1]
        got = {name: cpu_rate(sessions[name], q, args.batch, args.seconds, r * args.batch) for name in names}
        for name in sessions:
            rates[name].append(got[name])
            ratios[name].append(got[name] / got["export (Gemm of steps)"])
    print(f"{'level of detail':24s} {'rows changed by':>16s} {'rows differing':>15s} {'M queries / CPU s':>18s} "
          f"{'/ export, same round (quartiles)':>34s}")
    print(f"{'':24s} {'17-row chunks':>16s} {'from export':>15s} {'(1 thread)':>18s}")
    for name, sess in sessions.items():
        changed = rows_changed_by_chunking(sess, q[: args.rows])
        differ = int((answers[name].view(np.uint32) != export.view(np.uint32)).any(axis=1).sum())
        lo, mid, hi = np.percentile(ratios[name], [25, 50, 75])
        print(f"{name:24s} {changed:>16d} {differ:>15d} {statistics.median(rates[name]) / 1e6:>18.3f} "
              f"{mid:>16.3f} ({lo:.3f}-{hi:.3f})")
    print(f"calls of {args.batch} rows, {args.rounds} rounds of {args.seconds} s per variant; {load_text()}")


def load_text() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {os.cpu_count()} cores"


if __name__ == "__main__":
    main()
