"""Write the texture maps of `bricks.toml`, the worked example of groundtruth/MATERIALS.md.

A periodic tile of glazed bricks in running bond: four courses of two bricks each, every other course
shifted by half a brick, set in recessed mortar. Each brick has a bevelled top, its own tint and a
smoother (glossier) surface than the mortar. This stands for "your own texture maps": any tool that
writes a height, a colour and a roughness PNG of one periodic tile does the same job.

Writes, next to this file: bricks_height.png (16 bit grey), bricks_albedo.png (8 bit sRGB),
bricks_roughness.png (8 bit grey). Deterministic (fixed seed).
Run: .venv/bin/python docs/example/make_bricks.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

SIZE = 64
"""Map texels per side (the material's heightfield resolution)."""
COURSES, PER_COURSE = 4, 2
"""Brick rows per tile, and bricks per row."""
MORTAR = 0.035
"""Half the mortar joint's width, in tile units."""
BEVEL = 0.03
"""Width of a brick's rounded edge, in tile units."""
SEED = 3


def bricks(size: int) -> tuple[np.ndarray, np.ndarray]:
    """(brick index, distance to the brick's edge in tile units) of each texel; mortar has distance < 0."""
    t = (np.arange(size) + 0.5) / size
    x, y = np.meshgrid(t, t, indexing="xy")  # x along +u (columns), y along +v (rows)
    course = np.floor(y * COURSES).astype(int)
    shifted = (x + 0.5 / PER_COURSE * (course % 2)) % 1.0  # running bond: odd courses shift half a brick
    column = np.floor(shifted * PER_COURSE).astype(int)
    dx = np.minimum(shifted * PER_COURSE % 1.0, 1 - shifted * PER_COURSE % 1.0) / PER_COURSE
    dy = np.minimum(y * COURSES % 1.0, 1 - y * COURSES % 1.0) / COURSES
    return course * PER_COURSE + column, np.minimum(dx, dy) - MORTAR


def main() -> None:
    rng = np.random.default_rng(SEED)
    index, edge = bricks(SIZE)
    brick = edge > 0
    bevel = np.clip(edge / BEVEL, 0, 1)
    grain = rng.normal(0, 0.03, (SIZE, SIZE))  # a little surface roughness in the relief
    height = np.where(brick, 0.55 + 0.45 * np.sqrt(bevel), 0.2) + grain
    height = (height - height.min()) / (height.max() - height.min())
    tints = rng.uniform([0.45, 0.12, 0.06], [0.70, 0.25, 0.12], (COURSES * PER_COURSE, 3))  # linear RGB
    mortar = np.array([0.55, 0.53, 0.50])
    albedo = np.where(brick[..., None], tints[index], mortar) * (1 + rng.normal(0, 0.04, (SIZE, SIZE, 1)))
    roughness = np.where(brick, 0.3, 0.9) + rng.normal(0, 0.03, (SIZE, SIZE))

    folder = Path(__file__).parent
    Image.fromarray(np.round(height * 65535).astype(np.uint16)).save(folder / "bricks_height.png")
    srgb = np.where(albedo <= 0.0031308, 12.92 * albedo, 1.055 * np.clip(albedo, 0, 1) ** (1 / 2.4) - 0.055)
    Image.fromarray(np.round(np.clip(srgb, 0, 1) * 255).astype(np.uint8)).save(folder / "bricks_albedo.png")
    Image.fromarray(np.round(np.clip(roughness, 0, 1) * 255).astype(np.uint8)).save(folder / "bricks_roughness.png")


if __name__ == "__main__":
    main()
