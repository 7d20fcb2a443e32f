"""The kernel engine with its tables in 2 MB pages (transparent huge pages, madvise) against as loaded.

    .venv/bin/python experiments/server_overhead/huge_tables.py [MODEL ...]     # rock yarn (~30 s)

Loads each model twice: as shipped (`onnx_ops.aligned_zeros`: numpy's allocation) and with every table in an
anonymous mapping aligned to 2 MB and advised `MADV_HUGEPAGE`; prints the process's AnonHugePages after each load,
then both engines' time for 2^17 queries in interleaved rounds (8 rounds of 8 calls) and the ratio per round.
"""

from __future__ import annotations

import mmap
import statistics
import sys
import time
from pathlib import Path

import drjit as dr
import numpy as np

from neumip.core import contract as C
from neumip.engines import onnx_ops
from neumip.engines.kernel import KernelMaterial

ROOT = Path(__file__).resolve().parents[2]
HUGE = 1 << 21
_mappings: list[mmap.mmap] = []  # kept alive with the tables


def huge_zeros(shape: tuple, dtype) -> np.ndarray:
    """`onnx_ops.aligned_zeros` in huge pages."""
    size = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
    mapping = mmap.mmap(-1, (size + HUGE - 1) // HUGE * HUGE + HUGE)
    mapping.madvise(mmap.MADV_HUGEPAGE)
    _mappings.append(mapping)
    raw = np.frombuffer(mapping, np.uint8)
    start = -raw.ctypes.data % HUGE
    return raw[start:start + size].view(dtype).reshape(shape)


def anon_huge_kb() -> int:
    return int(next(line for line in open("/proc/self/smaps_rollup") if line.startswith("AnonHugePages")).split()[1])


def main() -> None:
    dr.set_thread_count(2)
    shipped_zeros = onnx_ops.aligned_zeros
    for name in sys.argv[1:] or ["rock", "yarn"]:
        path = ROOT / "models" / f"{name}.onnx"
        onnx_ops.aligned_zeros = shipped_zeros
        before = anon_huge_kb()
        shipped = KernelMaterial(path)
        middle = anon_huge_kb()
        onnx_ops.aligned_zeros = huge_zeros
        huge = KernelMaterial(path)
        print(f"{name}: AnonHugePages {before} kB -> {middle} kB (as shipped) -> {anon_huge_kb()} kB (huge tables)")
        n = 1 << 17
        pool = C.random_queries(4 * n, seed=1)
        batches = [pool[i * n:(i + 1) * n] for i in range(4)]
        assert np.array_equal(shipped.run(batches[0]), huge.run(batches[0]))
        times = {"shipped": [], "huge": []}
        for _ in range(8):
            for key, kernel in (("shipped", shipped), ("huge", huge)):
                began = time.perf_counter()
                for i in range(8):
                    kernel.run(batches[i % 4])
                times[key].append((time.perf_counter() - began) / 8)
        ratios = sorted(a / b for a, b in zip(times["shipped"], times["huge"]))
        print(f"{name}: 2^17 queries, shipped {statistics.median(times['shipped']) * 1e3:.2f} ms, huge tables "
              f"{statistics.median(times['huge']) * 1e3:.2f} ms; shipped / huge per round {ratios[0]:.3f}-{ratios[-1]:.3f}, "
              f"median {statistics.median(ratios):.3f}")
    onnx_ops.aligned_zeros = shipped_zeros


if __name__ == "__main__":
    main()
