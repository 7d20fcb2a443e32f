"""Write the texture maps of three experiment materials (not shipped) for the map-informed model:

- ``bumps``: jittered round bumps of different sizes on a rough plane; albedo darker in the valleys,
  glossy bump tops (`bumps.toml`).
- ``grooves``: parallel V grooves along v with a slow sinusoidal wobble, striped albedo, metallic
  ridges (`grooves.toml`).
- ``basket``: a basket weave: blocks of three strips alternating in direction, each strip a rounded
  ridge, two colours (`basket.toml`).

Each is a periodic 128 x 128 tile: height (16-bit PNG), albedo (sRGB PNG), roughness (8-bit PNG),
and for grooves a metallic map. Deterministic. Run: .venv/bin/python docs/materials/make_map_materials.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

SIZE = 128
HERE = Path(__file__).parent


def grid() -> tuple[np.ndarray, np.ndarray]:
    t = (np.arange(SIZE) + 0.5) / SIZE
    return np.meshgrid(t, t, indexing="xy")  # x along u (columns), y along v (rows)


def wrapped(d: np.ndarray) -> np.ndarray:
    return d - np.round(d)


def bumps(rng: np.random.Generator) -> dict[str, np.ndarray]:
    x, y = grid()
    height = np.zeros((SIZE, SIZE))
    n = 5
    for i in range(n):
        for j in range(n):
            cx, cy = (i + 0.5 + 0.3 * rng.uniform(-1, 1)) / n, (j + 0.5 + 0.3 * rng.uniform(-1, 1)) / n
            r = rng.uniform(0.05, 0.09)
            d2 = (wrapped(x - cx) ** 2 + wrapped(y - cy) ** 2) / (r * r)
            height = np.maximum(height, np.sqrt(np.clip(1 - d2, 0, 1)) * r / 0.09)
    albedo = np.stack([0.25 + 0.45 * height, 0.3 + 0.35 * height, 0.2 + 0.2 * height], axis=2)
    roughness = np.where(height > 0.05, 0.2, 0.8)
    return {"height": height, "albedo": albedo, "roughness": roughness}


def grooves(rng: np.random.Generator) -> dict[str, np.ndarray]:
    x, y = grid()
    period = 1 / 8
    phase = x + 0.02 * np.sin(2 * np.pi * y) + 0.004 * rng.standard_normal()
    t = np.abs(wrapped(phase / period))  # 0 on the ridge line, 0.5 in the groove
    height = 1.0 - 2 * t
    stripe = (np.floor(phase / period) % 2).astype(float)
    albedo = np.where(stripe[..., None] > 0, [0.6, 0.45, 0.2], [0.35, 0.35, 0.4])
    metallic = (height > 0.8).astype(float)
    roughness = np.where(height > 0.8, 0.25, 0.6)
    return {"height": height, "albedo": albedo, "roughness": roughness, "metallic": metallic}


def basket(rng: np.random.Generator) -> dict[str, np.ndarray]:
    x, y = grid()
    blocks, strips = 4, 3
    bx, by = np.floor(x * blocks), np.floor(y * blocks)
    horizontal = (bx + by) % 2 == 0
    across = np.where(horizontal, y, x) * blocks * strips  # coordinate across the strips
    t = across - np.floor(across)  # 0..1 across one strip
    ridge = np.sqrt(np.clip(1 - (2 * t - 1) ** 2, 0, 1))
    along = np.where(horizontal, x, y) * blocks
    height = ridge * (0.8 + 0.2 * np.cos(np.pi * (along - np.floor(along) - 0.5)))
    albedo = np.where(horizontal[..., None], [0.7, 0.55, 0.3], [0.45, 0.3, 0.15]) * (0.7 + 0.3 * ridge[..., None])
    roughness = 0.45 + 0.1 * rng.random((SIZE, SIZE))
    return {"height": height, "albedo": albedo, "roughness": roughness}


def save(name: str, maps: dict[str, np.ndarray]) -> None:
    h = maps["height"]
    h = (h - h.min()) / max(h.max() - h.min(), 1e-9)
    Image.fromarray((h * 65535).round().astype(np.uint16)).save(HERE / f"{name}_height.png")
    a = np.clip(maps["albedo"], 0, 1)
    srgb = np.where(a <= 0.0031308, 12.92 * a, 1.055 * a ** (1 / 2.4) - 0.055)
    Image.fromarray((srgb * 255).round().astype(np.uint8)).save(HERE / f"{name}_albedo.png")
    for key in ("roughness", "metallic"):
        if key in maps:
            Image.fromarray((np.clip(maps[key], 0, 1) * 255).round().astype(np.uint8)).save(HERE / f"{name}_{key}.png")


def main() -> None:
    for seed, make in enumerate((bumps, grooves, basket)):
        save(make.__name__, make(np.random.default_rng(seed)))


if __name__ == "__main__":
    main()
