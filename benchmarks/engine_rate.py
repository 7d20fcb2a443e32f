"""Queries a second of each in-process engine on a few models: the figure to compare across a change of the
engines' code (run it at both commits, alternately, on one machine: `answer_digest.py` checks the bits).

    python benchmarks/engine_rate.py models --names yarn,flat --queries 131072 --rounds 3

Each line: model, engine, the best of `--rounds` timed calls (after one untimed), queries/s, and the 1-minute
load average. Works with the layout before the engines moved to `neumip.engines` too (`answer_digest.engines`).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from answer_digest import engines  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", type=Path)
    parser.add_argument("--names", default="yarn,flat")
    parser.add_argument("--queries", type=int, default=1 << 17)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    from neumip.core import contract as C

    q = C.random_queries(args.queries, seed=9)
    for engine, cls in engines():
        materials = cls(args.models)
        for name in args.names.split(","):
            materials.evaluate(name, q)  # untimed: loads, compiles, warms up
            best = min(_timed(materials, name, q) for _ in range(args.rounds))
            print(f"{name} {engine} {args.queries / best / 1e6:.3f} Mq/s (load {os.getloadavg()[0]:.1f})", flush=True)
    return 0


def _timed(materials, name, q) -> float:
    start = time.perf_counter()
    materials.evaluate(name, q)
    return time.perf_counter() - start


if __name__ == "__main__":
    sys.exit(main())
