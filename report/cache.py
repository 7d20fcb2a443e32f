"""Renders cached on disk, keyed by everything that determines them, written atomically.

A render is stored as ``<key>.npz`` (the image and what it cost) through a temporary file and an
atomic rename, so an interrupted report resumes from its finished renders and never reads a
half-written one. A file that cannot be read is rendered again.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neumip.core.files import atomic_write

log = logging.getLogger(__name__)


def cache_key(params: dict) -> str:
    """A stable hash of JSON-ready render parameters."""
    text = json.dumps(params, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


@dataclass
class Cached:
    image: np.ndarray
    """(H, W, 3) float32 linear RGB."""
    seconds: float
    """Wall time of the render when it was made."""
    load: float = float("nan")
    """1-minute load average of the machine when the render finished (nan: not recorded)."""


class RenderCache:
    """A folder of finished renders."""

    def __init__(self, folder: str | os.PathLike) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.hits = 0
        self.seconds = 0.0
        """Wall time of every render handed out (fresh or cached), summed."""

    def path(self, params: dict) -> Path:
        return self.folder / f"{cache_key(params)}.npz"

    def get(self, params: dict) -> Cached | None:
        path = self.path(params)
        if not path.exists():
            return None
        try:
            with np.load(path) as data:
                load = float(data["load"]) if "load" in data.files else float("nan")
                cached = Cached(data["image"].astype(np.float32), float(data["seconds"]), load)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
            log.warning("cached render %s unreadable (%s): rendering again", path.name, exc)
            return None
        self.hits += 1
        self.seconds += cached.seconds
        return cached

    def forget(self, params: dict) -> None:
        """Remove a render from the cache (none there: nothing to do)."""
        self.path(params).unlink(missing_ok=True)

    def put(self, params: dict, image: np.ndarray, seconds: float, load: float = float("nan")) -> None:
        path = self.path(params)

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as f:  # a file object: np.savez adds no suffix
                np.savez(f, image=image.astype(np.float32), seconds=np.float64(seconds), load=np.float64(load),
                         params=json.dumps(params, sort_keys=True, default=str))

        atomic_write(path, write)
        self.seconds += seconds
