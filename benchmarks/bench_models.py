"""Evaluation speed of the model files in one folder, side by side: each file's queries per second in the
render's own kernel (`KernelMaterials`) and in ONNX Runtime on one thread (`LocalMaterials`), the median
of interleaved rounds on the same random queries (compare ratios within one run: the machine is shared).

    .venv/bin/python benchmarks/bench_models.py DIR [--queries 18] [--rounds 3] [--backends llvm,cuda]

`--backends` names the drjit backends the kernel runs on (cuda: an NVIDIA GPU, as the renderer's
cuda_ad_rgb variant runs it; its figure includes copying the queries to the GPU and the answers back).

Put the variants to compare in DIR (e.g. a model with and without a stage, `experiments/relief/relief.txt`).
"""

from __future__ import annotations

import argparse
import importlib
import os
import time

import numpy as np

from neumip.engines.kernel import KernelMaterials
from neumip.engines.local import LocalMaterials
from neumip.core.contract import random_queries


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder")
    parser.add_argument("--queries", type=int, default=18, help="log2 of the queries per call")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--backends", default="llvm", help="comma-separated drjit backends of the kernel: llvm, cuda")
    args = parser.parse_args()
    engines = {"kernel" if b == "llvm" else f"kernel {b}": KernelMaterials(args.folder, importlib.import_module(f"drjit.{b}.ad"))
               for b in args.backends.split(",")}
    engines["onnxruntime"] = LocalMaterials(args.folder, threads=1)
    q = random_queries(1 << args.queries, seed=1)
    names = sorted(engines["onnxruntime"].materials())  # (the kernel's may run on CUDA alone)
    for engine in engines.values():  # warm up: kernels compiled, sessions opened
        for name in names:
            engine.evaluate(name, q)
    seconds = {(e, n): [] for e in engines for n in names}
    for _ in range(args.rounds):
        for name in names:
            for e, engine in engines.items():
                start = time.perf_counter()
                engine.evaluate(name, q)
                seconds[e, name].append(time.perf_counter() - start)
    print(f"{len(q)} random queries per call, median of {args.rounds} rounds, load {os.getloadavg()[0]:.1f}")
    print(f"{'model':24s} " + " ".join(f"{e + ' M q/s':>18s}" for e in engines))
    for name in names:
        print(f"{name:24s} " + " ".join(f"{len(q) / np.median(seconds[e, name]) / 1e6:18.2f}" for e in engines))


if __name__ == "__main__":
    main()
