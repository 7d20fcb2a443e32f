"""What the kernel engine's own code asks of a lane: the LLVM IR drjit compiles for a model's arithmetic, counted.

    python benchmarks/kernel_ops.py models/rock.onnx models/yarn.onnx models/flat.onnx

For single queries and for query groups of three lights (the renderer's), one line each: drjit's operation count of
the kernel, its arithmetic a lane (each vector instruction one operation, an fma two, as `graph_cost.py` counts a
product's FLOPs; register moves, addressing, loads and packet gathers not counted), its 16-wide fmas, its packet
loads and its per-value gathers (a table read one value at a time: 0 is what the kernel engine is built for,
`engines/onnx_ops.py`'s `aligned_zeros`). `graph_cost.py` estimates from the graph's shapes, counting layout nodes
that cost the kernel nothing; this is the count of what runs. Needs drjit (the LLVM backend) and onnx.

``--peak`` also measures what this machine's drjit kernels can do (the bound of the arithmetic): kernels of
nothing but fmas, 2^20 lanes, best of five. Four interleaved chains of 25 fmas on a few weights (what the
CPU's pipelines sustain), one chain of 2,400 fmas (each waiting for the one before: the floor), and four chains
of 600 on 97 distinct weights, which LLVM compiles one chain after another once the weights no longer fit in
registers, as in a model's kernel. Then, per model, the kernel engine's rate on 2^17 random single queries
and groups of three lights, and its arithmetic a second (the count above times the rate) against the peak, in
operations (an fma two) and in vector instructions (an fma one; the peak's fmas are instructions at half its
operations). The peak is of fmas alone: adds, compares and selects may issue beside them, so it bounds a kernel's
rate of fmas, not of every instruction.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

FREE = {"shufflevector", "insertelement", "extractelement", "bitcast", "getelementptr", "extractvalue", "load",
        "trunc", "zext", "sext", "phi", "br", "ret", "alloca", "store"}
"""Instructions not counted as arithmetic: register moves, addressing, memory."""


def kernel_ir(path: Path, lights: int) -> tuple[dict, str]:
    """The largest kernel drjit compiles for the model at `path` on 2^16 random queries (single, or groups of
    `lights`): (its kernel-history entry, its LLVM IR)."""
    import drjit as dr

    from neumip.core import contract as C
    from neumip.engines.kernel import KernelMaterial

    material = KernelMaterial(path)
    jit = material.backend
    q = C.random_queries(1 << 16, seed=1)
    if lights > 1:
        more = np.random.default_rng(2).uniform(-0.6, 0.6, (len(q), 2 * (lights - 1))).astype(np.float32)
        q = np.concatenate([q, more], 1)
    columns = [jit.Float(np.ascontiguousarray(q[:, i])) for i in range(q.shape[1])]
    dr.eval(columns)
    dr.kernel_history()  # clear it
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True), dr.scoped_set_flag(dr.JitFlag.KernelFreezing, False):
        dr.eval(material.graph.trace(material.graph.tables, columns))
        dr.sync_thread()
        history = dr.kernel_history()
    entry = max(history, key=lambda k: k.get("operation_count", 0))
    ir = entry["ir"]
    return entry, ir.getvalue() if hasattr(ir, "getvalue") else str(ir)


def count(ir: str) -> dict:
    """Arithmetic a lane (an fma two), fmas, packet loads and per-value gathers in the kernel's body."""
    ops = Counter()
    for line in ir.splitlines():
        match = re.match(r"\s*%\S+ = (\w+)", line)
        if not match:
            continue
        op = match.group(1)
        if op == "call":
            callee = re.search(r"@([\w.]+)\(", line)
            op = callee.group(1) if callee else "call"
        ops[op] += 1
    packets = sum(n for op, n in ops.items() if op.startswith("gather_"))
    gathers = sum(n for op, n in ops.items() if op.startswith("llvm.masked.gather"))
    fmas = sum(n for op, n in ops.items() if op.startswith("llvm.fma"))
    arithmetic = sum(n * (2 if op.startswith("llvm.fma") else 1) for op, n in ops.items()
                     if op not in FREE and not op.startswith(("gather_", "llvm.masked.gather")))
    return {"arithmetic": arithmetic, "fma": fmas, "packet loads": packets, "per-value gathers": gathers}


def fma_rate(chains: int, length: int, weights: int, lanes: int = 1 << 20) -> float:
    """Arithmetic a second (an fma two) of a drjit kernel of `chains` independent fma chains of `length`, over
    `lanes` lanes, its coefficients `weights` distinct literals: the best of five timed runs."""
    import drjit as dr
    from drjit.llvm import Float

    x = dr.arange(Float, lanes) * 1e-7
    dr.eval(x)

    def kernel():
        accs = [x + i for i in range(chains)]
        for k in range(length):
            accs = [dr.fma(a, 0.999 + 1e-6 * ((k * chains + i) % weights), 1e-3 * (i + 1)) for i, a in enumerate(accs)]
        return sum(accs[1:], accs[0])

    dr.eval(kernel())  # compiles
    best = float("inf")
    for _ in range(5):
        time.sleep(0.05)  # past drjit's worker spin
        out = kernel()
        start = time.perf_counter()
        dr.eval(out)
        dr.sync_thread()
        best = min(best, time.perf_counter() - start)
    return lanes * chains * length * 2 / best


def engine_rate(path: Path, lights: int, rows: int = 1 << 17) -> float:
    """The kernel engine's answers a second (query groups of `lights` a second where more than one) on random
    queries: the best of five calls after one untimed."""
    from neumip.core import contract as C
    from neumip.engines.kernel import KernelMaterial

    material = KernelMaterial(path)
    q = C.random_queries(rows, seed=9)
    if lights > 1:
        more = np.random.default_rng(2).uniform(-0.6, 0.6, (rows, 2 * (lights - 1))).astype(np.float32)
        q = np.ascontiguousarray(np.concatenate([q, more], 1))
    material.evaluate(q)
    best = float("inf")
    for _ in range(5):
        time.sleep(0.05)
        start = time.perf_counter()
        material.evaluate(q)
        best = min(best, time.perf_counter() - start)
    return rows / best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", type=Path, nargs="+")
    parser.add_argument("--peak", action="store_true", help="also the machine's fma rate and each model's share")
    args = parser.parse_args()
    peak = None
    if args.peak:
        rates = {"4 chains x 25, 4 weights": fma_rate(4, 25, 4), "1 chain x 2400, 97 weights": fma_rate(1, 2400, 97),
                 "4 chains x 600, 97 weights": fma_rate(4, 600, 97)}
        peak = rates["4 chains x 25, 4 weights"]
        print("fma kernels, G operations a second (an fma two): "
              + ", ".join(f"{k} {v / 1e9:.0f}" for k, v in rates.items()) + f"  [load {os.getloadavg()[0]:.2f}]",
              flush=True)
    for path in args.models:
        for lights in (1, 3):
            entry, ir = kernel_ir(path, lights)
            figures = count(ir)
            kind = "single queries" if lights == 1 else "groups of 3 lights"
            line = (f"{path.stem} {kind}: drjit operations {entry['operation_count']}, arithmetic "
                    f"{figures['arithmetic']} a lane ({figures['fma']} fmas), packet loads {figures['packet loads']}, "
                    f"per-value gathers {figures['per-value gathers']}")
            if peak:
                rate = engine_rate(path, lights)
                ops = rate * figures["arithmetic"]
                instructions = rate * (figures["arithmetic"] - figures["fma"])  # an fma one
                line += (f"; {rate / 1e6:.2f} M a second, {ops / 1e9:.0f} G operations a second, {ops / peak:.2f}x "
                         f"the peak (at the peak: {peak / figures['arithmetic'] / 1e6:.1f} M a second); in "
                         f"instructions (an fma one) {instructions / 1e9:.0f} G a second, {2 * instructions / peak:.2f}x "
                         f"the peak's {peak / 2e9:.0f}")
            print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
