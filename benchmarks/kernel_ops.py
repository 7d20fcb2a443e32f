"""What the kernel engine's own code asks of a lane: the LLVM IR drjit compiles for a model's arithmetic, counted.

    python benchmarks/kernel_ops.py models/rock.onnx models/yarn.onnx models/flat.onnx

For single queries and for query groups of three lights (the renderer's), one line each: drjit's operation count of
the kernel, its arithmetic a lane (each vector instruction one operation, an fma two, as `graph_cost.py` counts a
product's FLOPs; register moves, addressing, loads and packet gathers not counted), its 16-wide fmas, its packet
loads and its per-value gathers (a table read one value at a time: 0 is what the kernel engine is built for,
`engines/onnx_ops.py`'s `aligned_zeros`). `graph_cost.py` estimates from the graph's shapes, counting layout nodes
that cost the kernel nothing; this is the count of what runs. Needs drjit (the LLVM backend) and onnx.
"""

from __future__ import annotations

import argparse
import re
import sys
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", type=Path, nargs="+")
    args = parser.parse_args()
    for path in args.models:
        for lights in (1, 3):
            entry, ir = kernel_ir(path, lights)
            figures = count(ir)
            print(f"{path.stem} {'single queries' if lights == 1 else 'groups of 3 lights'}: drjit operations "
                  f"{entry['operation_count']}, arithmetic {figures['arithmetic']} a lane ({figures['fma']} fmas), "
                  f"packet loads {figures['packet loads']}, per-value gathers {figures['per-value gathers']}",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
