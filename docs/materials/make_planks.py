"""Write the texture maps of `planks.toml`: a periodic tile of varnished wooden planks (the report's
own texture-map material, made outside the procedural library).

Four boards per tile, staggered, separated by dark recessed gaps; each board has its own tint, a
wood grain along its length (albedo stripes and shallow ridges), slightly rounded edges, and a
glossy varnish that is worn (rougher) near the gaps.

Writes, next to this file: planks_height.png (16 bit), planks_albedo.png (sRGB), planks_roughness.png.
Deterministic (fixed seed). Run: .venv/bin/python docs/materials/make_planks.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

SIZE = 128
"""Map texels per side (the material's heightfield resolution)."""
BOARDS = 4
"""Boards across one tile (each runs along u)."""
SEED = 11


def periodic_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth periodic noise in [-1, 1]: random values on a ``cells`` grid, bilinear, wrapped."""
    grid = rng.uniform(-1, 1, (cells, cells))
    t = np.arange(size) * cells / size
    i0 = np.floor(t).astype(int)
    f = t - i0
    i1 = (i0 + 1) % cells
    rows = grid[i0] * (1 - f)[:, None] + grid[i1] * f[:, None]  # (size, cells)
    return rows[:, i0] * (1 - f)[None] + rows[:, i1] * f[None]


def main() -> None:
    rng = np.random.default_rng(SEED)
    t = (np.arange(SIZE) + 0.5) / SIZE
    u, v = np.meshgrid(t, t, indexing="xy")  # u along the boards, v across them
    board = np.floor(v * BOARDS).astype(int) % BOARDS
    across = v * BOARDS - np.floor(v * BOARDS)  # position across a board, [0, 1)
    offsets = rng.uniform(0, 1, BOARDS)  # staggered butt joints, one per board
    along = (u + offsets[board]) % 1.0
    gap_w, bevel_w = 0.06, 0.12
    edge = np.minimum(np.minimum(across, 1 - across) / BOARDS, np.minimum(along, 1 - along))  # tile units
    top = np.clip((edge - gap_w / BOARDS) / (bevel_w / BOARDS), 0, 1)  # 0 in the gap, 1 on the board
    grain = np.sin(2 * np.pi * (across * 6 + 0.8 * periodic_noise(rng, SIZE, 8)))  # stripes along the board
    height = np.clip(np.sqrt(top) * (0.9 + 0.05 * grain) + 0.05 * rng.uniform(0, 1, BOARDS)[board] * top, 0, 1)
    tint = np.array([0.45, 0.26, 0.12]) * (0.7 + 0.6 * rng.uniform(0, 1, (BOARDS, 1)))
    albedo = tint[board] * (0.85 + 0.15 * grain[..., None])
    albedo = np.where(top[..., None] > 0, albedo, np.array([0.06, 0.05, 0.04]))
    roughness = np.where(top > 0.5, 0.18 + 0.1 * (1 - top) + 0.05 * (grain + 1), 0.8)
    here = Path(__file__).parent
    Image.fromarray((height * 65535).round().astype(np.uint16)).save(here / "planks_height.png")
    srgb = np.where(albedo <= 0.0031308, 12.92 * albedo, 1.055 * np.clip(albedo, 0, 1) ** (1 / 2.4) - 0.055)
    Image.fromarray((srgb * 255).round().astype(np.uint8)).save(here / "planks_albedo.png")
    Image.fromarray((np.clip(roughness, 0, 1) * 255).round().astype(np.uint8)).save(here / "planks_roughness.png")


if __name__ == "__main__":
    main()
