"""The answers' energy table (`MaterialConfig.energy_bins`): a gain per level of detail, half-vector angle and
light elevation, fitted after training. Pure torch.

A log loss (comb2) settles at a noisy target's geometric mean, below its mean. The coarse footprints of a glossy
material are where the targets are noisiest (a footprint of many texels holds a few glints that 16 samples hit or
miss), so its coarse levels answer darker than the data, most near the mirror direction and under grazing lights:
turtle's levels 3-7 answered 1.10-1.18x too dark where the half vector is 32-46 degrees from the normal, 1.21-1.50x
within 8 degrees of it and 1.26-1.67x under lights below 11.5 degrees (`experiments/energy`). An unbiased loss per
query removes that bias but lets each coarse texel chase its own targets' noise. The table instead takes the ratio
of the data's mean to the answers' mean over every query of a cell (thousands of queries each), so the energy comes
back without the noise.

A cell is a level and a pair of direction bins, B = `energy_bins` each: the half vector's angle, x = s (B - 1) /
sqrt 2 with s = 2 sin(theta_h / 2) = sqrt(2 - 2 h_z) in [0, sqrt 2], and the light's elevation, y = sqrt(wi_z)
(B - 1) (finer towards the horizon). A query's gain is trilinear in (level of detail, x, y): its 8 corner cells
(`corners`), whose weights sum to 1. `fit_energy` takes the same weights for the ratio of sums, with a prior of
`ENERGY_PRIOR` queries answering exactly right in every cell (a cell few queries reach keeps a gain near 1). The
table is a 3-D texture of RGB cells: its row ``(B l + b) B + e`` is level l, half-vector bin b, elevation bin e (the
graph Gathers a query's 8 rows as it reads a texture's taps). The graph writer's twin is `training.export.energy`.

With `energy_azimuths` A the table has a fourth, periodic axis: the half vector's azimuth in the tile's frame, as a
pseudo-angle that needs no trigonometry (`azimuth_coordinate`: piecewise linear in x / (|x| + |y|), 0 along +x, 1
along +y, 2 along -x, 3 along -y), A bins over its period of 4. A query then reads 16 corner cells, row
``((B l + b) B + e) A + a``, and the fit ties the cells of the first half-vector bin (the normal, where the azimuth is
undefined) to one gain for every azimuth.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from neumip.core import contract as C
from neumip.core.config import MaterialConfig
from neumip.core.weights import energy_channels, energy_rows
from neumip.training.model.base import half_direction, lift
from neumip.training.model.pyramid import level_of_detail

ENERGY_PRIOR = 256.0
"""Queries' worth of answers that are right (gain 1) added to every cell of the ratio (`fit_energy`)."""
FIT_CHUNK = 1 << 17
"""Queries a fit spreads over their cells at a time (`energy_sums`: up to 16 cells x 6 sums each, float64)."""
ENERGY_RANGE = (0.25, 4.0)
"""The gains a fit may give (a cell the data barely reach cannot swing an answer further)."""


def _pair(x: torch.Tensor, top: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) coordinates in [0, top] -> their lower and upper nodes (N, 2) (both at most `top`) and weights (N, 2)."""
    low = torch.floor(x)
    frac = x - low
    return torch.stack([low, torch.clamp(low + 1, max=top)], 1).long(), torch.stack([1 - frac, frac], 1)


def direction_coordinates(h: torch.Tensor, wi_z: torch.Tensor, bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3) half vectors h and (N,) the lights' wi_z -> (N,) x = sqrt(2 - 2 h_z) (bins - 1) / sqrt 2 and (N,)
    y = sqrt(wi_z) (bins - 1), both in [0, bins - 1]."""
    s = torch.sqrt(torch.clamp(2.0 - 2.0 * h[:, 2], min=0.0))
    x = torch.clamp(s * ((bins - 1) / math.sqrt(2.0)), 0.0, bins - 1.0)
    return x, torch.clamp(torch.sqrt(wi_z) * (bins - 1), 0.0, bins - 1.0)


def azimuth_coordinate(h: torch.Tensor, azimuths: int) -> torch.Tensor:
    """(N, 3) half vectors -> (N,) their azimuth as a pseudo-angle scaled to [0, azimuths]: with (x, y) the half
    vector's tangent part and d = |x| + |y|, 1 - x / d where y >= 0, else 3 + x / d, times azimuths / 4."""
    x, y = h[:, 0], h[:, 1]
    ratio = x / torch.clamp(torch.abs(x) + torch.abs(y), min=1e-30)
    return torch.where(y >= 0, 1.0 - ratio, 3.0 + ratio) * (azimuths / 4.0)


def _periodic_pair(a: torch.Tensor, period: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(N,) coordinates in [0, period] -> their lower and upper nodes (N, 2) in [0, period) (the upper wraps to 0)
    and weights (N, 2)."""
    low = torch.clamp(torch.floor(a), max=period - 1.0)
    frac = a - low
    high = torch.where(low + 1 >= period, torch.zeros_like(low), low + 1)
    return torch.stack([low, high], 1).long(), torch.stack([1 - frac, frac], 1)


def corners(config: MaterialConfig, sigma: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor,
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Queries' sigma (N,), wi, wo (N, 2) -> the table rows (N, K) of their K corner cells and their weights (N, K),
    which sum to 1 (corners in the order of `training.export.energy.corner_list`): K = 8, rows (B l + b) B + e,
    trilinear; with `energy_azimuths` A, K = 16, rows ((B l + b) B + e) A + a."""
    bins = config.energy_bins
    wi3 = lift(wi)
    h = half_direction(wi3, lift(wo))
    x, y = direction_coordinates(h, wi3[:, 2], bins)
    pairs = [_pair(level_of_detail(sigma, config.resolution, config.lod_bias), config.levels),
             _pair(x, bins - 1), _pair(y, bins - 1)]
    strides = [bins, bins]
    if config.energy_azimuths:
        pairs.append(_periodic_pair(azimuth_coordinate(h, config.energy_azimuths), config.energy_azimuths))
        strides.append(config.energy_azimuths)
    index, weight = pairs[0]
    for (nodes, weights), stride in zip(pairs[1:], strides):  # corner-major: the first axis varies slowest
        index = (index[:, :, None] * stride + nodes[:, None, :]).reshape(len(x), -1)
        weight = (weight[:, :, None] * weights[:, None, :]).reshape(len(x), -1)
    return index, weight


def energy_gain(table: torch.Tensor, config: MaterialConfig, sigma: torch.Tensor, wi: torch.Tensor,
                wo: torch.Tensor) -> torch.Tensor:
    """The table (`weights.energy_rows`, K) at the queries (sigma (N,), wi, wo (N, 2)) -> (N, K) gains (K = 1: one for
    the three channels, `MaterialConfig.energy_luminance`)."""
    index, weight = corners(config, sigma, wi, wo)
    return (table[index] * weight[:, :, None]).sum(1)


@torch.no_grad()
def fit_energy(config: MaterialConfig, queries: torch.Tensor, answers: torch.Tensor, targets: torch.Tensor,
               prior: float = ENERGY_PRIOR) -> torch.Tensor:
    """(N, 7) single queries, the model's answers without a table (N, 3) and the data's targets (N, 3) -> the table
    (`weights.energy_rows`, `weights.energy_channels`) whose cell holds, per channel (or for the luminances, with
    `energy_luminance`), (sum w t + prior m) / (sum w a + prior m): w a query's
    weight in the cell (`corners`), m the answers' mean (float64 sums, `energy_sums`); with the azimuth axis, the
    sums of the first half-vector bin's cells are pooled over the azimuths. Rows with a non-finite value are left
    out."""
    keep = torch.isfinite(targets).all(1) & torch.isfinite(answers).all(1)
    queries, answers, targets = queries[keep], answers[keep].double(), targets[keep].double()
    if config.energy_luminance:  # one gain a cell: the luminances' ratio
        lum = torch.tensor(C.LUMINANCE, dtype=torch.float64)
        answers, targets = (answers @ lum)[:, None], (targets @ lum)[:, None]
    n = energy_channels(config)
    sums = energy_sums(config, queries, answers, targets)
    sums[:, 0] = sums[:, 0].sum(2, keepdim=True)  # the normal's bin: one sum for every azimuth
    mean = answers.mean(0) if len(answers) else torch.ones(n, dtype=torch.float64)
    table = (sums[..., :n] + prior * mean) / (sums[..., n:] + prior * mean)
    return torch.nan_to_num(table.reshape(-1, n), nan=1.0).clamp(*ENERGY_RANGE).float()


def energy_sums(config: MaterialConfig, queries: torch.Tensor, answers: torch.Tensor, targets: torch.Tensor,
                ) -> torch.Tensor:
    """Each cell's sums over the (N, 7) queries, float64 (L + 1, B, B, A, 2 K) (A = 1 without the azimuth axis): sum w t
    and sum w a per channel of the (N, K) targets and answers, w a query's weight in the cell (`corners`). In chunks
    of `FIT_CHUNK` queries (a query spreads over up to 16 cells)."""
    width = 2 * targets.shape[1]
    sums = torch.zeros(energy_rows(config), width, dtype=torch.float64)
    for lo in range(0, len(queries), FIT_CHUNK):
        part = queries[lo:lo + FIT_CHUNK]
        index, weight = corners(config, part[:, C.SIGMA], part[:, C.WI_X : C.WI_Y + 1], part[:, C.WO_X : C.WO_Y + 1])
        values = torch.cat([targets[lo:lo + FIT_CHUNK], answers[lo:lo + FIT_CHUNK]], 1).double()
        sums.index_add_(0, index.reshape(-1), (weight.double()[:, :, None] * values[:, None, :]).reshape(-1, width))
    return sums.reshape(config.levels + 1, config.energy_bins, config.energy_bins, max(config.energy_azimuths, 1), width)


def ones_table(config: MaterialConfig) -> np.ndarray:
    """The table of a model that needs no gain (`weights.energy_rows`, `weights.energy_channels`): every gain 1."""
    return np.ones((energy_rows(config), energy_channels(config)), np.float32)
