"""The kernel engine's rate by call size: does a large call run faster cut into cache-sized calls?

    .venv/bin/python experiments/server_overhead/kernel_chunks.py [MODEL ...]     # rock yarn (~1 min)

Per model (``models/NAME.onnx``), in interleaved rounds of 0.3-0.4 s each (medians of 5):
- ``repeated``: one array of 2^b queries evaluated again and again (`KernelMaterial.run`), b = 10 ... 18;
- ``cut``: 2^17 and 2^20 distinct queries evaluated whole, and in calls of 2^13 ... 2^16 rows one after another
  (the answers checked equal to the whole call's).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import drjit as dr
import numpy as np

from neumip.core import contract as C
from neumip.engines.kernel import KernelMaterial

ROOT = Path(__file__).resolve().parents[2]


def rate(fn, rows: int, seconds: float) -> float:
    """Queries a second of `fn()`, which answers `rows`, repeated for `seconds`."""
    calls, began = 0, time.perf_counter()
    while time.perf_counter() - began < seconds:
        fn()
        calls += 1
    return calls * rows / (time.perf_counter() - began)


def main() -> None:
    dr.set_thread_count(2)
    for name in sys.argv[1:] or ["rock", "yarn"]:
        kernel = KernelMaterial(ROOT / "models" / f"{name}.onnx")
        small = {b: C.random_queries(1 << b, seed=b) for b in (10, 12, 13, 14, 15, 16, 18)}
        rates = {b: [] for b in small}
        for _ in range(5):
            for b, q in small.items():
                rates[b].append(rate(lambda q=q: kernel.run(q), len(q), 0.3))
        print(name, "repeated:", {f"2^{b}": round(statistics.median(v) / 1e6, 2) for b, v in rates.items()}, "M q/s")
        for b in (17, 20):
            q = C.random_queries(1 << b, seed=b)

            def cut(rows: int, q=q) -> np.ndarray:
                out = np.empty((len(q), C.RGB_DIM), C.DTYPE)
                for lo in range(0, len(q), rows):
                    out[lo:lo + rows] = kernel.run(q[lo:lo + rows])
                return out

            ways = {"whole": lambda q=q: kernel.run(q), **{f"2^{c}": (lambda c=c: cut(1 << c)) for c in (13, 14, 15, 16)}}
            whole = kernel.run(q)
            assert all(np.array_equal(fn(), whole) for fn in ways.values())
            rates = {way: [] for way in ways}
            for _ in range(5):
                for way, fn in ways.items():
                    rates[way].append(rate(fn, len(q), 0.4))
            print(name, f"2^{b} cut:", {w: round(statistics.median(v) / 1e6, 2) for w, v in rates.items()}, "M q/s")


if __name__ == "__main__":
    main()
