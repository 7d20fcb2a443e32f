"""The kernel engine's dot products as one fma chain (the product's `onnx_ops.Ops._rows`) against two chains, the
even terms from the bias and the odd ones, added last (`split_rows` here, for products of at least 4 terms):
queries a second in interleaved rounds, and each variant's distance from ONNX Runtime in units of the export's
parity tolerance (1e-5 + 1e-4 relative; 1 is the limit), and on 2^20 more single queries the answers outside
that tolerance (strays: the relief march is discontinuous, so a last bit can move where a ray lands).

    .venv/bin/python experiments/kernel_limits/fma_chains.py models --names rock,yarn,turtle,foam,flat --rounds 5

Each variant is traced at its first call with its `_rows` in place (the kernel freezes its trace), so both live in
one process and are timed alternately.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np


def split_rows(self, x, w, start):
    """`onnx_ops.Ops._rows` with each dot product of at least 4 terms as two fma chains added last."""
    from neumip.engines.onnx_ops import Lanes, _fma, lift, objects

    rows = x.cells.reshape(-1, w.shape[0])
    out_shape = x.cells.shape[:-1] + (w.shape[1],)
    if start is not None:
        start = self.align(Lanes(np.empty(out_shape, object), x.axis), start)[0][1]
        start = np.broadcast_to(start, out_shape).reshape(-1, w.shape[1])
    cells = []
    for r, row in enumerate(rows):
        for j in range(w.shape[1]):
            terms = [(row[k], float(w[k, j])) for k in np.flatnonzero(w[:, j])]
            even, odd = (None if start is None else start[r, j]), None
            if len(terms) < 4:
                for x_k, w_k in terms:
                    even = _fma(x_k, w_k, even)
                acc = even
            else:
                for x_k, w_k in terms[0::2]:
                    even = _fma(x_k, w_k, even)
                for x_k, w_k in terms[1::2]:
                    odd = _fma(x_k, w_k, odd)
                acc = even + odd
            cells.append(lift(self.jit, 0.0 if acc is None else acc))
    return Lanes(objects(out_shape, cells), x.axis)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", type=Path)
    parser.add_argument("--names", default="rock,yarn")
    parser.add_argument("--queries", type=int, default=1 << 17)
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    from neumip.core import contract as C
    from neumip.engines import onnx_ops
    from neumip.engines.kernel import KernelMaterials
    from neumip.engines.local import LocalMaterials

    variants = {"chain": onnx_ops.Ops._rows, "split": split_rows}
    rng = np.random.default_rng(3)
    single = C.random_queries(args.queries, seed=9)
    groups = np.ascontiguousarray(np.concatenate(
        [C.random_queries(args.queries // 3, seed=10),
         rng.uniform(-0.7, 0.7, (args.queries // 3, 4)).astype(np.float32)], 1))
    sets = {"single": single, "groups of 3": groups}
    reference = LocalMaterials(args.models)
    print(f"# {args.queries} single queries or {args.queries // 3} groups of 3 lights a call, best of "
          f"{args.rounds} interleaved rounds; load {os.getloadavg()[0]:.2f}", flush=True)
    for name in args.names.split(","):
        engines = {}
        for variant, rows in variants.items():
            onnx_ops.Ops._rows = rows
            engines[variant] = KernelMaterials(args.models)
            for q in sets.values():
                engines[variant].evaluate(name, q)  # traces and freezes this variant
        onnx_ops.Ops._rows = variants["chain"]
        for kind, q in sets.items():
            truth = reference.evaluate(name, q)
            times = {v: [] for v in variants}
            margin = {}
            for _ in range(args.rounds):
                for variant, engine in engines.items():
                    time.sleep(0.05)  # past drjit's worker spin
                    start = time.perf_counter()
                    rgb = engine.evaluate(name, q)
                    times[variant].append(time.perf_counter() - start)
                    margin[variant] = float(np.max(np.abs(rgb - truth) / (1e-5 + 1e-4 * np.abs(truth))))
            rate = {v: len(q) / min(t) / 1e6 for v, t in times.items()}
            ratios = sorted(a / b for a, b in zip(times["chain"], times["split"]))
            print(f"{name} {kind}: chain {rate['chain']:.2f} M/s, split {rate['split']:.2f} M/s "
                  f"(split / chain {rate['split'] / rate['chain']:.3f}, per round {ratios[0]:.2f}-{ratios[-1]:.2f}); "
                  f"distance from ONNX Runtime / tolerance: chain {margin['chain']:.3f}, split {margin['split']:.3f}  "
                  f"load {os.getloadavg()[0]:.2f}", flush=True)
        many = C.random_queries(1 << 20, seed=21)
        truth = reference.evaluate(name, many)
        strays = {v: int((np.abs(e.evaluate(name, many) - truth) > 1e-5 + 1e-4 * np.abs(truth)).any(axis=1).sum())
                  for v, e in engines.items()}
        print(f"{name}: answers outside the parity tolerance of 2^20 single queries: chain {strays['chain']}, "
              f"split {strays['split']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
