"""What one kernel-engine call of N answers holds in memory: the process's RSS before, after the call, after its answer
array is dropped, and after drjit's cache of freed blocks is handed back (`drjit.flush_malloc_cache`), for single
queries and groups of three lights.

    .venv/bin/python experiments/server_overhead/call_memory.py [MODEL]     # rock (~40 s: a process per case)

Each case runs in a process of its own (this script again, with ``--case LOG2 LIGHTS``), so that no case inherits
another's freed blocks.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def rss_mib() -> float:
    return int(next(line for line in open("/proc/self/status") if line.startswith("VmRSS")).split()[1]) / 1024


def one_case(model: Path, log2: int, lights: int) -> None:
    """One call of 2^`log2` answers in groups of `lights` lights, in this process."""
    import drjit as dr
    import numpy as np

    from neumip.core import contract as C
    from neumip.engines.kernel import KernelMaterial

    dr.set_thread_count(2)
    material = KernelMaterial(model)
    q = C.random_queries((1 << log2) // lights, seed=1)
    rows = np.ascontiguousarray(np.hstack([q] + [q[:, C.WI_X:C.WI_Y + 1]] * (lights - 1)))  # (n, 5 + 2 K): wi repeated
    dr.flush_malloc_cache()
    before = rss_mib()
    out = material.run(rows)
    after = rss_mib()
    del out
    dropped = rss_mib()
    dr.flush_malloc_cache()
    flushed = rss_mib()
    print(f"2^{log2} answers, {lights} light(s) a row ({rows.nbytes / 2**20:.0f} MiB of rows): RSS {before:.0f} -> "
          f"{after:.0f} MiB after the call -> {dropped:.0f} MiB without its answer -> {flushed:.0f} MiB after drjit's cache "
          "is flushed", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", nargs="?", default="rock")
    parser.add_argument("--case", nargs=2, type=int, metavar=("LOG2", "LIGHTS"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    model = ROOT / "models" / f"{args.model}.onnx"
    if args.case:
        one_case(model, *args.case)
        return
    for log2 in (18, 20):
        for lights in (1, 3):
            subprocess.run([sys.executable, __file__, args.model, "--case", str(log2), str(lights)], check=True)


if __name__ == "__main__":
    main()
