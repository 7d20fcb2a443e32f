"""A digest of every model's answers in every engine: run it before and after a change that must not change
answers, and compare the lines (`diff`). Each line: model, engine, query kind, SHA-256 of the answers' bytes.

    python benchmarks/answer_digest.py models > before.txt   # (at the old commit)
    python benchmarks/answer_digest.py models > after.txt
    diff before.txt after.txt && echo "bit-identical"

Queries: 65,536 random single queries and 16,384 query groups of 3 lights (fixed seeds). Engines: ONNX Runtime (`LocalMaterials`) and the in-kernel engine (`KernelMaterials`, drjit LLVM).
Works with the layout before the engines moved to `neumip.engines` too (it falls back to `neumip.client`).
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

import numpy as np


def engines():
    """(name, class) of each engine, from either layout."""
    try:
        from neumip.engines.kernel import KernelMaterials
        from neumip.engines.local import LocalMaterials
    except ImportError:  # the layout before the engines package
        from neumip.client.kernel import KernelMaterials
        from neumip.client.local import LocalMaterials
    return [("onnxruntime", LocalMaterials), ("kernel", KernelMaterials)]


def queries() -> dict[str, np.ndarray]:
    from neumip.core import contract as C

    rng = np.random.default_rng(5)
    groups = C.random_queries(16384, seed=6)
    extra = rng.uniform(-0.7, 0.7, (16384, 4)).astype(np.float32)  # two more lights, inside the disc
    return {"single": C.random_queries(65536, seed=4), "groups3": np.ascontiguousarray(np.concatenate([groups, extra], 1))}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", type=Path, help="folder of .onnx models")
    args = parser.parse_args()
    sets = queries()
    for engine, cls in engines():
        materials = cls(args.models)
        for path in sorted(args.models.glob("*.onnx")):
            for kind, q in sets.items():
                rgb = np.ascontiguousarray(materials.evaluate(path.stem, q), np.float32)
                print(f"{path.stem} {engine} {kind} {hashlib.sha256(rgb.tobytes()).hexdigest()[:16]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
