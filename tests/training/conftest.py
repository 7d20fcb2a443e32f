"""Fixtures of the training tests: a material of one's own from PNG maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="module")
def material(tmp_path_factory) -> Path:
    """my.toml with 8 x 8 height, albedo and roughness PNGs beside it (a raised square on a floor)."""
    Image = pytest.importorskip("PIL.Image")
    folder = tmp_path_factory.mktemp("my_material")
    height = np.zeros((8, 8), np.uint16)
    height[2:6, 2:6] = 65535
    Image.fromarray(height).save(folder / "height.png")
    albedo = np.full((8, 8, 3), 180, np.uint8)
    albedo[2:6, 2:6] = (200, 60, 40)
    Image.fromarray(albedo).save(folder / "albedo.png")
    Image.fromarray(np.where(height > 0, 80, 230).astype(np.uint8)).save(folder / "roughness.png")
    (folder / "my.toml").write_text(
        'summary = "a raised square"\nresolution = 8\nheight_scale = 0.05\n'
        '[maps]\nheight = "height.png"\nbase_color = "albedo.png"\nroughness = "roughness.png"\n'
    )
    return folder / "my.toml"
