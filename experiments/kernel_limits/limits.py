"""What holds the kernel engine below the machine's arithmetic rate, four probes in one process (interleaved rounds,
the best of five calls of 2^17 random single queries each, after one untimed):

    .venv/bin/python experiments/kernel_limits/limits.py models/rock.onnx

- **stages**: the model's graph without each of its stages (`benchmarks/bench_render.py`'s `stage_variants`: the
  same weights, the graph of the config without the stage; its answers are wrong, its cost is the rest's).
- **tables**: the same queries with u, v in a square of 1 % of the tile's area (0.1 x 0.1), sorted by u, and all at
  the coarsest footprint (sigma 1): how much of a call is waiting for table rows.
- **vector width**: drjit's LLVM backend compiling the same kernel for 32 or 8 lanes a packet instead of its default
  (16 with AVX-512), through libdrjit-core's `jit_llvm_set_target`, which the Python API does not expose.
- **mlp**: a multilayer perceptron of the paper's shapes (7, 25, 25, 25, 3; ReLU) written as the kernel writes a
  product (an fma chain per output, literal weights) and through drjit's cooperative vectors (`drjit.nn.matvec`),
  2^20 lanes: the arithmetic rate the kernel's own style of code reaches where nothing else is in the way.
"""

from __future__ import annotations

import argparse
import ctypes
import glob
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from kernel_ops import fma_rate  # noqa: E402


def best_of(fns: dict, rounds: int = 5) -> dict:
    """{label: seconds}: the best of `rounds` interleaved calls of each fn (after one untimed)."""
    for fn in fns.values():
        fn()
    times = {k: [] for k in fns}
    for _ in range(rounds):
        for k, fn in fns.items():
            time.sleep(0.05)  # past drjit's worker spin
            start = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - start)
    return {k: min(v) for k, v in times.items()}


def report(title: str, rows: int, seconds: dict) -> None:
    first = next(iter(seconds.values()))
    print(f"## {title}  [load {os.getloadavg()[0]:.2f}]")
    for k, s in seconds.items():
        print(f"  {k:36s} {rows / s / 1e6:7.2f} M a second   time / first {s / first:.2f}", flush=True)


def stages(path: Path, q: np.ndarray) -> None:
    from bench_render import stage_variants

    from neumip.engines.kernel import KernelMaterial

    with tempfile.TemporaryDirectory() as tmp:
        folders = stage_variants(path, Path(tmp))
        materials = {k: KernelMaterial(v / path.name) for k, v in folders.items()}
        report("stages (the model without each)", len(q), best_of({k: (lambda m=m: m.evaluate(q)) for k, m in materials.items()}))


def tables(path: Path, q: np.ndarray) -> None:
    from neumip.engines.kernel import KernelMaterial

    material = KernelMaterial(path)
    sets = {"random": q}
    near = q.copy()
    near[:, :2] = np.random.default_rng(3).uniform(0.0, 0.1, (len(q), 2))
    sets["u, v in 1 % of the tile's area"] = near
    sets["sorted by u, then v"] = np.ascontiguousarray(q[np.lexsort((q[:, 1], q[:, 0]))])
    coarse = q.copy()
    coarse[:, 2] = 1.0
    sets["sigma 1 (the coarsest level)"] = coarse
    report("table reads (the same model, other queries)", len(q),
           best_of({k: (lambda v=v: material.evaluate(v)) for k, v in sets.items()}))


def vector_width(path: Path, q: np.ndarray) -> None:
    import drjit as dr

    from neumip.engines.kernel import KernelMaterial

    lib = ctypes.CDLL(glob.glob(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))[0])
    lib._Z19jit_llvm_target_cpuv.restype = ctypes.c_char_p
    lib._Z24jit_llvm_target_featuresv.restype = ctypes.c_char_p
    lib._Z21jit_llvm_vector_widthv.restype = ctypes.c_uint32
    materials, answers = {}, {}
    default = None
    for width in (None, 32, 8):
        material = KernelMaterial(path)  # compiled at its first call, for the target set then
        cpu, features = lib._Z19jit_llvm_target_cpuv(), lib._Z24jit_llvm_target_featuresv()
        default = default or lib._Z21jit_llvm_vector_widthv()
        lib._Z19jit_llvm_set_targetPKcS0_j(cpu, features, ctypes.c_uint32(width or default))
        label = f"{width or default} lanes a packet"
        answers[label] = material.evaluate(q)
        materials[label] = material
    lib._Z19jit_llvm_set_targetPKcS0_j(cpu, features, ctypes.c_uint32(default))
    report("vector width", len(q), best_of({k: (lambda m=m: m.evaluate(q)) for k, m in materials.items()}))
    first = next(iter(answers.values()))
    print("  the same bits in every width:", all(np.array_equal(first, a) for a in answers.values()))


def mlp(lanes: int = 1 << 20) -> None:
    import drjit as dr
    import drjit.nn as nn
    from drjit.llvm.ad import Float, TensorXf

    rng = np.random.default_rng(0)
    sizes = [7, 25, 25, 25, 3]
    ws = [rng.normal(size=(o, i)).astype(np.float32) * 0.3 for i, o in zip(sizes[:-1], sizes[1:])]
    bs = [rng.normal(size=(o,)).astype(np.float32) * 0.1 for o in sizes[1:]]
    xs = [dr.arange(Float, lanes) * (1e-6 * (i + 1)) for i in range(sizes[0])]
    dr.eval(xs)

    def literal():
        h = xs
        for layer, (w, b) in enumerate(zip(ws, bs)):
            out = []
            for j in range(w.shape[0]):
                acc = h[0] * float(w[j, 0]) + float(b[j])
                for k in range(1, w.shape[1]):
                    acc = dr.fma(h[k], float(w[j, k]), acc)
                out.append(dr.maximum(acc, 0.0) if layer < len(ws) - 1 else acc)
            h = out
        return h

    views = nn.pack(*[t for w, b in zip(ws, bs) for t in (TensorXf(w), TensorXf(b))], layout="inference")

    def coop():
        h = nn.CoopVec(*xs)
        for layer in range(len(ws)):
            h = nn.matvec(views[2 * layer], h, views[2 * layer + 1])
            if layer < len(ws) - 1:
                h = dr.maximum(h, 0.0)
        return list(h)

    def run(fn):
        out = fn()
        dr.eval(out)
        dr.sync_thread()

    seconds = best_of({"fma chains, literal weights": lambda: run(literal),
                       "cooperative vectors (drjit.nn.matvec)": lambda: run(coop)})
    report(f"an MLP of {sizes}, {lanes} lanes", lanes, seconds)
    macs = sum(w.size for w in ws)
    # the chains' instructions a lane: an output's product and bias add, its other fmas, its ReLU but the last layer's
    instructions = sum(w.shape[0] * (w.shape[1] + 1) for w in ws) + sum(w.shape[0] for w in ws[:-1])
    peak = fma_rate(4, 25, 4)  # operations a second (an fma two): kernel_ops.py's peak, measured now
    chains = seconds["fma chains, literal weights"]
    print("  G operations a second (an fma two): "
          + ", ".join(f"{k} {lanes * macs * 2 / s / 1e9:.0f}" for k, s in seconds.items())
          + f"; the peak {peak / 1e9:.0f}: the chains {lanes * macs * 2 / chains / peak:.2f}x; in instructions (an fma "
          f"one, {instructions} a lane) {lanes * instructions / chains / 1e9:.0f} G a second, "
          f"{2 * lanes * instructions / chains / peak:.2f}x the peak's {peak / 2e9:.0f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--sections", default="stages,tables,width,mlp")
    args = parser.parse_args()
    from neumip.core import contract as C

    q = C.random_queries(1 << 17, seed=9)
    sections = args.sections.split(",")
    print(f"# {args.model}: 2^17 random single queries a call unless said")
    if "stages" in sections:
        stages(args.model, q)
    if "tables" in sections:
        tables(args.model, q)
    if "width" in sections:
        vector_width(args.model, q)
    if "mlp" in sections:
        mlp()
    return 0


if __name__ == "__main__":
    sys.exit(main())
