"""The model registry: every ``*.onnx`` material of the model folder, loaded, checked and warmed up.

A file that fails to load (corrupt, another contract version, wrong graph) is logged and kept in
:attr:`Registry.failed` with its reason, so its ready endpoint can say no; the others still serve.
Material names from requests are only ever looked up in a dict, never joined into a path.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from neumip.client import contract as C
from neumip.client.local import NAME_PATTERN, Material, UnknownMaterial, load_folder, run_chunked

from .errors import ApiError

log = logging.getLogger(__name__)

MODEL_VERSION = "1"
"""The one version of each material the server exposes (Open Inference Protocol model version)."""


def warmup_queries(rows: int) -> np.ndarray:
    """(rows, 7) float32 valid queries spread over the tile, all levels and a cone of directions."""
    t = np.linspace(0.0, 1.0, rows, dtype=np.float32)
    queries = np.zeros((rows, C.QUERY_DIM), dtype=C.DTYPE)
    queries[:, C.U] = t
    queries[:, C.V] = t[::-1]
    queries[:, C.SIGMA] = 2.0 ** (-12.0 * t)
    queries[:, C.WI_X] = 0.7 * np.cos(7 * t)
    queries[:, C.WI_Y] = 0.7 * np.sin(7 * t)
    queries[:, C.WO_X] = 0.5 * np.sin(3 * t)
    queries[:, C.WO_Y] = 0.5 * np.cos(3 * t)
    return queries


def without_folder(message: str, folder: Path) -> str:
    """`message` with the model folder's path taken out of the file paths in it (ONNX Runtime's errors
    name the file in full): clients learn the file name, not where the server keeps its files."""
    for prefix in {str(folder.resolve()), str(folder.absolute()), str(folder)}:
        message = message.replace(prefix + os.sep, "")
    return message


def check_name(name: str) -> str:
    """Raise a 400 ApiError unless `name` looks like a material name (no paths, no dots first)."""
    if not NAME_PATTERN.match(name):
        raise ApiError(
            400,
            f"invalid material name {name[:80]!r}: use letters, digits, '_', '.', '-'"
            " (starting with a letter or digit, at most 128 characters)",
        )
    return name


@dataclass
class Registry:
    """Loaded materials by name, plus the files that failed to load and why."""

    folder: Path
    """The model folder the materials came from."""
    materials: dict[str, Material] = field(default_factory=dict)
    """Materials that loaded and warmed up, by name (file stem)."""
    failed: dict[str, str] = field(default_factory=dict)
    """Files that could not be served: name -> reason."""

    @classmethod
    def load(cls, folder: Path, threads: int, warmup_rows: int) -> "Registry":
        """Load and warm up every ``*.onnx`` in `folder` (raises FileNotFoundError if it is missing)."""
        folder = Path(folder)
        if not folder.is_dir():
            raise FileNotFoundError(f"model folder {folder} does not exist")
        loaded, failed = load_folder(folder, threads)
        registry = cls(folder, failed={name: without_folder(reason, folder) for name, reason in failed.items()})
        for material in loaded.values():
            registry._warm_up(material, warmup_rows)
        log.info(
            "serving %d material(s) from %s: %s%s",
            len(registry.materials),
            folder,
            ", ".join(registry.materials) or "none",
            f"; {len(registry.failed)} failed" if registry.failed else "",
        )
        return registry

    def _warm_up(self, material: Material, warmup_rows: int) -> None:
        """Evaluate a few queries once (first-call costs, and a graph that loads but cannot run)."""
        try:
            if warmup_rows:
                C.as_rgb(run_chunked(material.session, warmup_queries(warmup_rows)), warmup_rows)
        except Exception as exc:  # a model that loads but fails to run (bad graph, wrong shapes)
            log.error("cannot serve %s: warm-up failed: %s", material.path.name, exc)
            reason = f"{material.path.name}: warm-up evaluation failed: {exc}"
            self.failed[material.name] = without_folder(reason, self.folder)
            return
        self.materials[material.name] = material

    def get(self, name: str) -> Material:
        """The loaded material `name`; 400 for a malformed or failed one (as Triton does), 404 if unknown."""
        check_name(name)
        material = self.materials.get(name)
        if material is not None:
            return material
        if name in self.failed:
            raise ApiError(400, f"material {name!r} is not ready (failed to load): {self.failed[name]}")
        known = ", ".join(sorted(self.materials)) or "none"
        raise UnknownMaterial(f"unknown material {name!r} (served: {known})")

    def names(self) -> list[str]:
        return sorted(self.materials)

    def listing(self) -> dict:
        """What ``GET /v1/materials`` answers: metadata of each material and the failures."""
        return {
            "materials": [self.materials[name].info() for name in self.names()],
            "failed": [{"name": n, "error": e} for n, e in sorted(self.failed.items())],
        }
