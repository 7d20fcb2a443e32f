"""The distribution of training queries (u, sigma, wi, wo) over one tile, all levels and the hemisphere.

Defaults follow the NeuMIP authors' code:

- ``u, v`` uniform over the tile ``[0, 1)^2``;
- ``wi`` and ``wo`` independent, uniform on the projected disk up to ``max_zenith_deg``
  (``r = sin(theta_max) sqrt(U)``; the default 84.26 degrees is their ``r = sqrt(0.99 U)``), or
  (``directions="solid_angle"``) uniform in solid angle over the same cap, which gives the grazing
  directions 4x the queries (beyond 80 degrees: 8 % instead of 2 %);
- ``sigma`` a mixture over levels of detail, in finest texels ``t = 1 / resolution``:
  ``level_fraction`` log-uniform over all levels (``sigma = 2^L t``, ``L ~ U(0, log2 R)``; with
  ``levels_resolution`` R' over the levels of an R' pyramid instead, ``t' = 1 / R'``),
  ``heavy_fraction`` heavy-tailed ``sigma = t / sqrt(U)`` (most mass near the finest level),
  and the rest ``sigma = 0`` (the unfiltered BTF); with ``sub_texel_levels`` k both shares move k levels
  finer, from ``2^-k t`` (for a model whose finest level answers such footprints, `MaterialConfig.lod_bias`
  k: each of its levels gets the share the authors' sampling gives a level).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from neumip.core import contract as C


DIRECTIONS = ("disk", "solid_angle")


@dataclass
class QuerySampling:
    """Distribution of the generated queries."""

    max_zenith_deg: float = math.degrees(math.asin(math.sqrt(0.99)))
    """Largest zenith angle of wi and wo (degrees)."""
    directions: str = "disk"
    """'disk': uniform on the projected disk (the authors'); 'solid_angle': uniform in solid angle."""
    level_fraction: float = 0.3
    """Share of queries with sigma log-uniform over all levels of detail."""
    heavy_fraction: float = 0.6
    """Share of queries with heavy-tailed sigma = texel / sqrt(U); the rest get sigma = 0."""
    queries_per_texel: float = 256.0
    """Default number of queries per finest texel (the paper used 200-400)."""
    levels_resolution: int | None = None
    """The log-uniform share spans the levels of a pyramid of this many texels per side (a model
    coarser than the material's maps keeps its coarse levels' share); None: the sampling resolution's."""
    sub_texel_levels: int = 0
    """Levels below the finest texel that the footprints reach: both shares are scaled by ``2^-k`` (the
    heavy-tailed one is ``2^-k t / sqrt(U)``), for a model with `MaterialConfig.lod_bias` k, whose level L is
    the footprint 2^(L - k) t; 0: the authors' sampling."""

    def __post_init__(self) -> None:
        if not 0 < self.max_zenith_deg < 90:
            raise ValueError(f"max_zenith_deg must be in (0, 90), got {self.max_zenith_deg}")
        if self.directions not in DIRECTIONS:
            raise ValueError(f"directions must be one of {DIRECTIONS}, got {self.directions!r}")
        if self.level_fraction < 0 or self.heavy_fraction < 0 or self.level_fraction + self.heavy_fraction > 1:
            raise ValueError("level_fraction and heavy_fraction must be >= 0 and sum to at most 1")
        if self.queries_per_texel <= 0:
            raise ValueError("queries_per_texel must be positive")
        if self.levels_resolution is not None and self.levels_resolution < 1:
            raise ValueError(f"levels_resolution must be >= 1, got {self.levels_resolution}")
        if not (isinstance(self.sub_texel_levels, int) and 0 <= self.sub_texel_levels <= 8):
            raise ValueError(f"sub_texel_levels must be a whole number in [0, 8], got {self.sub_texel_levels!r}")


def sample_directions(
    n: int, rng: np.random.Generator, max_zenith_deg: float, kind: str = "disk"
) -> np.ndarray:
    """(n, 2) x, y of directions up to `max_zenith_deg`, uniform on the projected disk (`kind` 'disk')
    or in solid angle ('solid_angle': cos theta uniform)."""
    if kind == "disk":
        r = math.sin(math.radians(max_zenith_deg)) * np.sqrt(rng.random(n))
    else:
        cos = 1.0 - (1.0 - math.cos(math.radians(max_zenith_deg))) * rng.random(n)
        r = np.sqrt(1.0 - cos * cos)
    phi = 2 * math.pi * rng.random(n)
    return np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)


def sample_sigma(n: int, rng: np.random.Generator, resolution: int, config: QuerySampling) -> np.ndarray:
    """(n,) footprints in tile units drawn from the level mixture of `config`."""
    finer = 2.0 ** -config.sub_texel_levels
    texel = finer / resolution
    coarse = config.levels_resolution or resolution
    kind = rng.random(n)
    log_uniform = 2.0 ** (math.log2(coarse) * rng.random(n)) * finer / coarse
    heavy = texel / np.sqrt(1.0 - rng.random(n))  # 1 - U in (0, 1]: no division by zero
    sigma = np.where(kind < config.level_fraction, log_uniform, 0.0)
    heavy_kind = (kind >= config.level_fraction) & (kind < config.level_fraction + config.heavy_fraction)
    return np.where(heavy_kind, heavy, sigma)


def sample_queries(n: int, rng: np.random.Generator, resolution: int, config: QuerySampling) -> np.ndarray:
    """(n, 7) float32 queries in the contract's layout, drawn from `config` for a material of `resolution`."""
    uv = rng.random((n, 2), dtype=np.float32)  # float32 draws stay below 1
    sigma = sample_sigma(n, rng, resolution, config)
    wi = sample_directions(n, rng, config.max_zenith_deg, config.directions)
    wo = sample_directions(n, rng, config.max_zenith_deg, config.directions)
    return C.pack_queries(uv[:, 0], uv[:, 1], sigma, wi, wo)
