"""Write the texture maps of `stones.toml`: a periodic stones-and-mortar tile (experiment material).

Not a shipped material: it exists to test training changes on texture maps made outside the
procedural library (groundtruth/MATERIALS.md). Periodic Voronoi
cells (the stones) with domed, bevelled tops separated by recessed mortar; each stone has its own
albedo tint and a smoother (glossier) surface than the mortar.

Writes, next to this file: stones_height.png (16 bit), stones_albedo.png (sRGB), stones_roughness.png.
Deterministic (fixed seed). Run: .venv/bin/python docs/materials/make_stones.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

SIZE = 128
"""Map texels per side (the material's heightfield resolution)."""
STONES = 14
"""Voronoi sites (stones) per tile."""
SEED = 7


def voronoi(size: int, sites: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Periodic Voronoi of (n, 2) sites in [0, 1)^2 -> (nearest site index, border distance) per texel."""
    t = (np.arange(size) + 0.5) / size
    x, y = np.meshgrid(t, t, indexing="xy")
    d = np.empty((len(sites), size, size))
    for i, (sx, sy) in enumerate(sites):
        dx = np.abs(x - sx)
        dy = np.abs(y - sy)
        dx, dy = np.minimum(dx, 1 - dx), np.minimum(dy, 1 - dy)  # wrap-around distance
        d[i] = np.hypot(dx, dy)
    order = np.sort(d, axis=0)
    return np.argmin(d, axis=0), (order[1] - order[0]) / 2  # distance to the cell border (approx.)


def main() -> None:
    rng = np.random.default_rng(SEED)
    sites = rng.random((STONES, 2))
    cell, border = voronoi(SIZE, sites)
    mortar = 0.035
    bevel = np.clip((border - mortar) / 0.05, 0, 1)  # 0 in the mortar, 1 on the stone top
    dome = np.sqrt(bevel) * (0.75 + 0.25 * rng.random(STONES)[cell])  # stones of different heights
    noise = rng.standard_normal((SIZE // 8, SIZE // 8))
    grain = np.kron(noise, np.ones((8, 8)))
    grain = 0.25 * (grain + np.roll(grain, 4, 0) + np.roll(grain, 4, 1) + np.roll(grain, (4, 4), (0, 1)))
    height = np.clip(dome + 0.04 * grain * bevel, 0, 1)
    tint = 0.25 + 0.5 * rng.random((STONES, 3)) * np.array([1.0, 0.85, 0.7])
    albedo = np.where(bevel[..., None] > 0, tint[cell], np.array([0.55, 0.53, 0.5]))
    roughness = np.where(bevel > 0.5, 0.25 + 0.15 * rng.random(STONES)[cell], 0.85)
    here = Path(__file__).parent
    Image.fromarray((height * 65535).round().astype(np.uint16)).save(here / "stones_height.png")
    srgb = np.where(albedo <= 0.0031308, 12.92 * albedo, 1.055 * albedo ** (1 / 2.4) - 0.055)
    Image.fromarray((srgb * 255).round().astype(np.uint8)).save(here / "stones_albedo.png")
    Image.fromarray((roughness * 255).round().astype(np.uint8)).save(here / "stones_roughness.png")


if __name__ == "__main__":
    main()
