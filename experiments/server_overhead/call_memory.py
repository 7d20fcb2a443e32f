"""What one kernel-engine call of N answers holds in memory: the process's RSS before, after the call, after its answer
array is dropped, and after drjit's cache of freed blocks is handed back (`drjit.flush_malloc_cache`), for single
queries and groups of three lights.

    .venv/bin/python experiments/server_overhead/call_memory.py [MODEL]     # rock (~40 s: a process per case)

Each case runs in a process of its own, so that no case inherits another's freed blocks.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

CASE = r"""
import sys, numpy as np, drjit as dr
from neumip.core import contract as C
from neumip.engines.kernel import KernelMaterial
def rss():
    return int(next(l for l in open('/proc/self/status') if l.startswith('VmRSS')).split()[1]) / 1024
dr.set_thread_count(2)
material = KernelMaterial(sys.argv[1])
answers, lights = 1 << int(sys.argv[2]), int(sys.argv[3])
q = C.random_queries(answers // lights, seed=1)
rows = np.ascontiguousarray(np.hstack([q] + [q[:, C.WI_X:C.WI_Y + 1]] * (lights - 1)))  # (n, 5 + 2 K): wi repeated
dr.flush_malloc_cache()
before = rss(); out = material.run(rows); after = rss(); del out; dropped = rss(); dr.flush_malloc_cache(); flushed = rss()
print(f"2^{sys.argv[2]} answers, {lights} light(s) a row ({rows.nbytes / 2**20:.0f} MiB of rows): RSS {before:.0f} -> "
      f"{after:.0f} MiB after the call -> {dropped:.0f} MiB without its answer -> {flushed:.0f} MiB after drjit's cache "
      "is flushed")
"""


def main() -> None:
    model = ROOT / "models" / f"{sys.argv[1] if len(sys.argv) > 1 else 'rock'}.onnx"
    for log2 in (18, 20):
        for lights in (1, 3):
            subprocess.run([sys.executable, "-c", CASE, str(model), str(log2), str(lights)], check=True)


if __name__ == "__main__":
    main()
