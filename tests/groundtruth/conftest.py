"""Fixtures of the ground-truth tests: small descriptions built from numpy height maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from neumip.groundtruth.description import MaterialDescription


def diffuse(albedo: float) -> dict:
    """A homogeneous Lambertian Mitsuba BSDF dictionary."""
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [albedo] * 3}}


def height_description(folder: Path, height: np.ndarray, **fields) -> MaterialDescription:
    """A description whose height map is `height` (saved as .npy in `folder`)."""
    path = folder / f"height_{len(list(folder.glob('height_*.npy')))}.npy"
    np.save(path, height.astype(np.float32))
    data = {"name": "test", "resolution": height.shape[0], "maps": {"height": path.name}, **fields}
    return MaterialDescription.from_dict(data, base_dir=folder)


def wall_height(resolution: int, lo: int, hi: int) -> np.ndarray:
    """(R, R) height map: floor 0, a wall of height 1 over columns [lo, hi) (invariant along v)."""
    height = np.zeros((resolution, resolution), np.float32)
    height[:, lo:hi] = 1.0
    return height


@pytest.fixture(scope="module")
def mi():
    from neumip.client.mitsuba.runtime import import_mitsuba

    return import_mitsuba()
