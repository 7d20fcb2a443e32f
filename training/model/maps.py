"""Prefiltered material maps: what the map encoder of a map-informed material reads at each level.

A material traced by `neumip generate` is defined by maps (height, base colour, roughness,
metallic). `prefilter` turns them into one feature texture per pyramid level, at that level's
resolution, with the statistics a filtered lookup needs (LEAN mapping: the mean slopes and their
second moments keep the roughness that averaging the slopes away would lose):

====  ===================================================================================
 0    mean height, in units of ``HEIGHT_UNIT`` tile (the top of the relief is 0, below < 0)
 1-2  mean slopes dh/du, dh/dv (slopes of the finest height samples, box-averaged)
 3-5  the slopes' centred second moments: std of dh/du, std of dh/dv, their covariance
 6-8  linear base colour (box-averaged)
 9    roughness
 10   metallic
 11-  with `MapConfig.horizons` = K: the horizon's elevation (radians / (pi / 2), 0: open sky)
      towards K azimuths (0, 360 / K, ... degrees from +u towards +v), averaged over the texel
====  ===================================================================================

The level feature, log2 of the level's texels per side over 8, is added by the encoder (it is the
same for every texel of a level). Texel ``[row, col]`` of a level of ``S`` texels covers
``u in [col, col + 1) / S``, ``v in [row, row + 1) / S``: the pyramid's layout. Pure numpy.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass

import numpy as np

from neumip.core.config import dataclass_from_dict

from neumip.groundtruth.description import Microgeometry
from neumip.groundtruth.images import resample_periodic
from neumip.groundtruth.mesh import height_gradient

FEATURES = 11
"""Prefiltered features per texel without horizons (the table above)."""
HORIZON_REACH = 0.25
"""Horizons look this far (tiles) along each azimuth."""
HEIGHT_UNIT = 0.1
"""Heights enter the features in units of this many tiles (the shipped reliefs are 0.03-0.12 deep)."""
LEVEL_SCALE = 8.0
"""The level feature is log2(texels per side) / LEVEL_SCALE (0 at 1 x 1, 1 at 256 x 256)."""


def box_weights(n: int, size: int) -> np.ndarray:
    """(size, n) weights of an area average: output texel i is the mean of the input texels over
    [i n / size, (i + 1) n / size), each weighted by the length it overlaps (any n > size)."""
    edges = np.arange(size + 1) * (n / size)
    lo, hi = edges[:-1, None], edges[1:, None]
    cells = np.arange(n)[None, :]
    overlap = np.clip(np.minimum(hi, cells + 1) - np.maximum(lo, cells), 0, None)
    return overlap / (n / size)


def resize(arr: np.ndarray, size: int) -> np.ndarray:
    """A periodic (H, H[, C]) map -> (size, size[, C]): area-averaged when it is finer (each output
    texel the mean of the texels it covers, fractions of texels included), else bilinear at texel
    centres."""
    h = arr.shape[0]
    if arr.shape[1] != h:
        raise ValueError(f"maps must be square, got {arr.shape[:2]}")
    if h == size:
        return arr.astype(np.float32)
    if h == 1:
        return np.broadcast_to(arr, (size, size) + arr.shape[2:]).astype(np.float32)
    if h > size and h % size == 0:
        f = h // size
        return arr.reshape(size, f, size, f, *arr.shape[2:]).mean(axis=(1, 3)).astype(np.float32)
    if h > size:  # not a whole factor: exact area weights (point samples would alias)
        w = box_weights(h, size)
        rows = np.tensordot(w, arr.astype(np.float64), axes=(1, 0))  # (size, H[, C])
        return np.moveaxis(np.tensordot(w, rows, axes=(1, 1)), 0, 1).astype(np.float32)
    if arr.ndim == 2:
        return resample_periodic(arr, size)
    return np.stack([resample_periodic(arr[..., c], size) for c in range(arr.shape[2])], axis=2)


def finest_statistics(geo: Microgeometry) -> np.ndarray:
    """(R, R, 6) per height sample: height / HEIGHT_UNIT, slopes, and the slopes' raw products
    (sx^2, sy^2, sx sy) that box filtering averages into second moments."""
    height = geo.height.astype(np.float64)
    if height.shape[0] == 1:
        return np.zeros((1, 1, 6))
    slope = height_gradient(height)  # (R, R, 2), dimensionless
    sx, sy = slope[..., 0], slope[..., 1]
    return np.stack([height / HEIGHT_UNIT, sx, sy, sx * sx, sy * sy, sx * sy], axis=2)


def horizon_angles(height: np.ndarray, azimuths: int) -> np.ndarray:
    """(R, R) periodic heights (tile units) -> (R, R, azimuths): the elevation of the horizon seen
    from each sample towards each azimuth, within HORIZON_REACH tiles, in units of pi / 2.

    Azimuths are marched in steps of one sample along (cos a, sin a) (rounded to whole samples)."""
    res = height.shape[0]
    out = np.zeros(height.shape + (azimuths,))
    if res == 1:
        return out
    steps = max(1, int(HORIZON_REACH * res))
    for j in range(azimuths):
        a = 2 * np.pi * j / azimuths
        best = np.zeros(height.shape)
        for k in range(1, steps + 1):
            dx, dy = int(round(k * np.cos(a))), int(round(k * np.sin(a)))
            if dx == 0 and dy == 0:
                continue
            ahead = np.roll(height, (-dy, -dx), axis=(0, 1))  # height at (row + dy, col + dx)
            best = np.maximum(best, (ahead - height) / (np.hypot(dx, dy) / res))
        out[..., j] = np.arctan(best) / (np.pi / 2)
    return out


def level_features(stats: np.ndarray, geo: Microgeometry, size: int) -> np.ndarray:
    """(size, size, FEATURES) float32: the table of the module docstring at one level."""
    m = resize(stats, size).astype(np.float64)  # first and second moments, averaged over each texel
    mean_x, mean_y = m[..., 1], m[..., 2]
    var_x = np.maximum(m[..., 3] - mean_x * mean_x, 0.0)
    var_y = np.maximum(m[..., 4] - mean_y * mean_y, 0.0)
    cov = m[..., 5] - mean_x * mean_y
    albedo = resize(geo.base_color, size)
    rough, metal = resize(geo.roughness, size), resize(geo.metallic, size)
    columns = [m[..., 0], mean_x, mean_y, np.sqrt(var_x), np.sqrt(var_y), cov,
               albedo[..., 0], albedo[..., 1], albedo[..., 2], rough, metal]
    columns += [m[..., 6 + j] for j in range(stats.shape[2] - 6)]  # horizons, if any
    return np.stack(columns, axis=2).astype(np.float32)


def prefilter(geo: Microgeometry, sizes: list[int], horizons: int = 0) -> list[np.ndarray]:
    """The material's maps prefiltered to each of `sizes` (texels per side, finest first):
    a list of (S, S, FEATURES + horizons) float32 arrays."""
    stats = finest_statistics(geo)
    if horizons:
        stats = np.concatenate([stats, horizon_angles(geo.height.astype(np.float64), horizons)], axis=2)
    return [level_features(stats, geo, size) for size in sizes]


def level_feature(size: int) -> float:
    """The level feature of a level of `size` texels per side."""
    return math.log2(size) / LEVEL_SCALE


@dataclass(frozen=True)
class MapConfig:
    """Architecture of the map encoder of a map-informed material (`material.MapMaterial`)."""

    neighbourhood: int = 3
    """Texels per side of the neighbourhood of prefiltered features the encoder reads (1 or 3)."""
    hidden: int = 32
    """Width of the encoder's hidden layers."""
    layers: int = 3
    """Linear layers of the encoder MLP."""
    residual: int = 0
    """Also train a free texture, added to the encoded one, on every level of at most this many texels per side
    (0: none): the paper's latents as a correction where the data hold many queries per texel. On the finest
    levels it relearns the targets' noise (training/TRAINING.md)."""
    horizons: int = 0
    """Horizon elevations per texel, towards this many azimuths (0: none), among the features."""

    def __post_init__(self) -> None:
        if self.neighbourhood not in (1, 3):
            raise ValueError(f"neighbourhood must be 1 or 3, got {self.neighbourhood}")
        if self.horizons < 0:
            raise ValueError(f"horizons must be >= 0, got {self.horizons}")
        if isinstance(self.residual, bool) or self.residual < 0:
            raise ValueError(f"residual is a level size (texels per side, 0: none), got {self.residual!r}")
        if self.hidden < 1 or self.layers < 1:
            raise ValueError(f"hidden and layers must be >= 1, got {self.hidden}, {self.layers}")

    @property
    def features(self) -> int:
        """Prefiltered features per texel."""
        return FEATURES + self.horizons

    @property
    def inputs(self) -> int:
        """Encoder inputs: the features of every texel of the neighbourhood, plus the level feature."""
        return self.features * self.neighbourhood**2 + 1

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "MapConfig":
        data = json.loads(text)
        if isinstance(data.get("residual"), bool):  # before it was a size: a free texture on every level, or none
            data["residual"] = RESIDUAL_EVERY_LEVEL if data["residual"] else 0
        return dataclass_from_dict(cls, data)


RESIDUAL_EVERY_LEVEL = 1 << 16
"""`MapConfig.residual` of a free texture on every level (larger than any pyramid)."""
