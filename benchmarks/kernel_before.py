"""Another checkout's in-kernel engine, for before/after runs in one process (``--kernel-before``).

    git show 906263c:engines/kernel.py > /tmp/kernel_before.py
    .venv/bin/python benchmarks/bench_inference.py --sections kernel --kernel-before /tmp/kernel_before.py
    .venv/bin/python benchmarks/bench_render.py --kernel-before /tmp/kernel_before.py

`load` imports that ``kernel.py`` under another module name (it imports the rest of neumip from this
checkout, so it must not need what this checkout removed); `Before` wraps its `KernelMaterials` in
this checkout's interface: ``answers(columns)`` (the hand-written kernel took ``u, v, sigma, wo,
lights``; the columns are only regrouped while tracing, so the compiled kernel is the same).
"""

from __future__ import annotations

import importlib.util
import inspect
import sys
from pathlib import Path

from neumip.core import contract as C


def load(path: str | Path):
    """The module of another checkout's ``engines/kernel.py``."""
    spec = importlib.util.spec_from_file_location("neumip_kernel_before", Path(path))
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


class Before:
    """A `KernelMaterials` of module `load(path)` over `folder`, with this checkout's interface."""

    def __init__(self, path: str | Path, folder: str | Path, backend=None) -> None:
        self.evaluator = load(path).KernelMaterials(folder, backend)

    def materials(self) -> list[str]:
        return self.evaluator.materials()

    def evaluate(self, material: str, queries):
        return self.evaluator.evaluate(material, queries)

    def kernel(self, material: str) -> "Before.Material":
        return Before.Material(self.evaluator.kernel(material))

    class Material:
        def __init__(self, material) -> None:
            self.material = material
            self.columns = len(inspect.signature(material.answers).parameters) == 1

        def answers(self, columns: list) -> list:
            if self.columns:
                return self.material.answers(columns)
            lights = [(columns[C.WI_X], columns[C.WI_Y])]
            lights += [(columns[i], columns[i + 1]) for i in range(C.QUERY_DIM, len(columns), 2)]
            return self.material.answers(columns[C.U], columns[C.V], columns[C.SIGMA],
                                         (columns[C.WO_X], columns[C.WO_Y]), lights)
