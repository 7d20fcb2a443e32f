"""The relief stage of a material with `MaterialConfig.relief` (issue 25, lever 3): parallax and occlusion
from the material's own height field, in place of (or before) the learned offset.

A query's (u, v) is where its view ray crosses the reference plane, the top of the relief (`contract`).
The ray goes on along -wo into the relief; the stage finds where it first meets the height field and
moves the query's lookups there. The heights are a pyramid of the height map (each level the area
average of the finest), read at the query's footprint like every other texture: a close-up marches the
full relief, a far view its smooth mean (whose parallax is a plain shift).

The march (parallax occlusion mapping): D is the relief's depth (-min height, tile units), d = wo_xy /
max(wo_z, RELIEF_MIN_COS), and for k = 0..n (n = `MaterialConfig.relief_steps`) the ray is at depth
t_k = D k / n above p_k = uv - t_k d, where the surface is at depth -H(p_k). s_k = t_k + H(p_k) turns
from < 0 (above the surface) to >= 0 (below it); s_0 = H(uv) <= 0 and s_n = D + H >= 0. At the first
k with s_k >= 0 the crossing is refined by one secant step:

    t = t_{k-1} + (D / n) clamp(-s_{k-1} / max(s_k - s_{k-1}, RELIEF_DIVISION_FLOOR), 0, 1)

(t = 0 if s_0 >= 0; t = D if no step crossed, which only rounding can cause), and the shift is -t d.
The secant keeps t continuous where a step's sign flips by rounding. The heights are the material's,
not learned: the stage has no gradient and training computes it without one. `relief_heights` is
numpy, `relief_shift` torch; `export._relief` writes the same arithmetic into the graph.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from neumip.core.config import RELIEF_DIVISION_FLOOR, RELIEF_MIN_COS, MaterialConfig

from neumip.training.model.maps import resize
from neumip.groundtruth.description import Microgeometry
from neumip.training.model.pyramid import as_stored, pyramid_lookup


def relief_resolution(geo: Microgeometry) -> int:
    """The height pyramid's finest resolution for `geo`: its height map's side, up to a power of two; 0 for a
    flat material (a 1 x 1 height map: nothing to march)."""
    side = geo.height.shape[0]
    return 1 << math.ceil(math.log2(side)) if side > 1 else 0


def relief_heights(geo: Microgeometry, resolution: int) -> list[np.ndarray]:
    """The relief's height pyramid for `geo`, finest level `resolution` texels per side: one (S, S, 1)
    float32 array per level, finest first, in tile units (the top of the relief 0, below < 0)."""
    finest = resize(geo.height.astype(np.float64), resolution).astype(np.float64)
    return [resize(finest, size).astype(np.float32)[..., None]
            for size in MaterialConfig(resolution=resolution).level_sizes()]


def march_direction(wo: torch.Tensor) -> torch.Tensor:
    """(N, 2) x, y of unit view directions -> (N, 2) d = wo_xy / max(wo_z, RELIEF_MIN_COS), with the max
    taken under the root (sqrt(max(1 - |wo_xy|^2, RELIEF_MIN_COS^2)): the same for a correctly rounded sqrt,
    and what the graph computes)."""
    floor = RELIEF_MIN_COS * RELIEF_MIN_COS
    return wo / torch.sqrt(torch.clamp(1.0 - (wo * wo).sum(1, keepdim=True), min=floor))


@torch.no_grad()
def relief_depth(heights: torch.Tensor, pyramid: MaterialConfig, u: torch.Tensor, v: torch.Tensor,
                 sigma: torch.Tensor, wo: torch.Tensor, steps: int) -> torch.Tensor:
    """heights (T, 1) atlas, (N,) u, v, sigma, (N, 2) wo -> (N,) t, the ray's depth where it meets the
    relief (module docstring); the shift of the lookups is -t d (`march_direction`)."""
    return _march(heights, pyramid, u, v, sigma, march_direction(wo), steps)


@torch.no_grad()
def _march(heights: torch.Tensor, pyramid: MaterialConfig, u: torch.Tensor, v: torch.Tensor,
           sigma: torch.Tensor, d: torch.Tensor, steps: int) -> torch.Tensor:
    """`relief_depth` along a march direction d (N, 2) already computed."""
    depth = torch.clamp(-heights.min(), min=0.0)
    fractions = [k / steps for k in range(steps + 1)]  # t_n = D exactly
    s_prev = t_prev = None
    found = torch.zeros_like(u)
    missed = torch.ones_like(u)
    for f in fractions:
        t = depth * f
        h = pyramid_lookup(heights, pyramid, u - t * d[:, 0], v - t * d[:, 1], sigma)[:, 0]
        s = t + h
        below = (s >= 0).to(u.dtype)
        if s_prev is None:
            here = torch.zeros_like(u)
        else:
            ratio = torch.clamp(-s_prev / torch.clamp(s - s_prev, min=RELIEF_DIVISION_FLOOR), 0.0, 1.0)
            here = t_prev + (depth / steps) * ratio
        found = found + missed * below * here
        missed = missed * (1.0 - below)
        s_prev, t_prev = s, t
    return found + missed * depth


def relief_shift(heights: torch.Tensor, config: MaterialConfig, u: torch.Tensor, v: torch.Tensor,
                 sigma: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The relief stage of `config` (with `relief`): (N,) u, v, sigma, (N, 2) wo -> (N,) du, dv."""
    d = march_direction(wo)
    t = _march(heights, config.relief_pyramid(), u, v, sigma, d, config.relief_steps)
    return -t * d[:, 0], -t * d[:, 1]


@torch.no_grad()
def landed_positions(levels: list[np.ndarray], config: MaterialConfig, queries: np.ndarray,
                     chunk: int = 1 << 16) -> np.ndarray:
    """The relief stage of `config` for (N, 7) `queries` (`relief_heights` `levels`) -> (N, 2) float32 u, v where
    each lands, in chunks; what `NeuMIPMaterial.forward` computes first, answer for answer."""
    heights = as_stored(torch.cat([torch.as_tensor(lvl, dtype=torch.float32).reshape(-1, 1) for lvl in levels]), config)
    out = np.empty((len(queries), 2), np.float32)
    for start in range(0, len(queries), chunk):
        q = torch.from_numpy(np.array(queries[start:start + chunk], dtype=np.float32))
        u, v = q[:, 0], q[:, 1]
        du, dv = relief_shift(heights, config, u, v, q[:, 2], q[:, 5:7])
        out[start:start + chunk] = torch.stack([u + du, v + dv], dim=1).numpy()
    return out
