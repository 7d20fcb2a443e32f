"""A kernel call right after the last one against one after drjit's pool has idled, and what resizing the pool costs.

    .venv/bin/python experiments/server_overhead/idle_pool.py [MODEL ...]     # rock (~10 s)

For each gap (0, 5 and 30 ms of sleep after a call of 2^17 queries): the pool shrunk to the calling thread
(`drjit.set_thread_count(1)`), 3 ms of sleep, the pool grown back to 2, then the next call, 10 times; prints the
medians of the shrink, the grow and the call. The process idles for the gap plus those 3 ms before the call. The gaps
bracket the pool's spin: its workers spin for about 20 ms
after a call before they sleep.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import drjit as dr

from neumip.core import contract as C
from neumip.engines.kernel import KernelMaterial

ROOT = Path(__file__).resolve().parents[2]


def main() -> None:
    for name in sys.argv[1:] or ["rock"]:
        dr.set_thread_count(2)
        material = KernelMaterial(ROOT / "models" / f"{name}.onnx")
        queries = C.random_queries(1 << 17, seed=1)
        material.run(queries)
        for gap in (0.0, 0.005, 0.03):
            shrink, grow, call = [], [], []
            for _ in range(10):
                dr.set_thread_count(2)
                material.run(queries)
                time.sleep(gap)
                t0 = time.perf_counter()
                dr.set_thread_count(1)
                t1 = time.perf_counter()
                time.sleep(0.003)
                t2 = time.perf_counter()
                dr.set_thread_count(2)
                t3 = time.perf_counter()
                material.run(queries)
                t4 = time.perf_counter()
                shrink.append(t1 - t0)
                grow.append(t3 - t2)
                call.append(t4 - t3)
            print(f"{name}: gap {gap * 1e3:4.0f} ms  shrink {statistics.median(shrink) * 1e3:.3f} ms  grow "
                  f"{statistics.median(grow) * 1e3:.3f} ms  call {statistics.median(call) * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
