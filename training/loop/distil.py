"""Coarse targets distilled from the model's own finer footprints (`TrainConfig.distil`). Pure torch.

The data's target for a query at footprint sigma is a 16-sample estimate of the Gaussian-filtered BTF
(`groundtruth/tracer.py` jitters each sample's aim point by a Gaussian of std sigma). At a wide footprint of
a glossy material most of that noise is where on the footprint the samples land: a few land on glints. The
log loss settles below such a noisy target's mean, and an unbiased loss chases its noise
(experiments/level_share).

Gaussians compose: filtering by sigma is filtering by a finer sigma', then by sqrt(sigma^2 - sigma'^2). So a
coarse query's target can also be the mean of the model's own answers at the finer footprint sigma' (the
trainer's: about a finest texel), at K aim points jittered by the rest. The finest levels are fitted to most of
the data and their targets are quiet; averaged over the footprint they answer turtle's coarse queries 8-32x
closer (in MSE) to a 256-sample reference than its coarse levels do. The K points come in antithetic pairs
(z, -z), redrawn every step, so over the run the target's noise averages out instead of being fitted.

Measured (experiments/distil): trained coarse levels do not follow these targets (turtle stays 1.22-1.44x too
dark at 8-32 texels), so it is off by default.
"""

from __future__ import annotations

from typing import Callable

import torch

from neumip.core import contract as C

from neumip.training.model.pyramid import level_of_detail

Answer = Callable[[torch.Tensor], torch.Tensor]
"""(M, 7) queries (u, v where the relief has not yet moved them) -> (M, 3) the model's answers."""


def coarse_mask(queries: torch.Tensor, resolution: int, lod_bias: int, level: float) -> torch.Tensor:
    """(B, 7) queries -> (B,) bool: the queries whose level of detail is `level` or coarser."""
    return level_of_detail(queries[:, C.SIGMA], resolution, lod_bias) >= level


@torch.no_grad()
def distilled_targets(answer: Answer, queries: torch.Tensor, samples: int, generator: torch.Generator,
                      finer: float) -> torch.Tensor:
    """(B, 7) queries, K = `samples` (even) -> (B, 3) the mean of `answer` at K aim points jittered by
    sqrt(sigma^2 - sigma'^2), each read at sigma' = min(sigma, `finer`) (tile units)."""
    if samples < 2 or samples % 2:
        raise ValueError(f"distil samples must be an even number >= 2, got {samples}")
    n = queries.shape[0]
    half = torch.randn((n, samples // 2, 2), generator=generator).to(queries.device)
    z = torch.cat([half, -half], dim=1)  # (B, K, 2) antithetic pairs
    sigma = queries[:, C.SIGMA].clamp(min=0.0)
    fine = sigma.clamp(max=finer)
    spread = torch.sqrt(sigma * sigma - fine * fine)
    sub = queries[:, None, :].expand(n, samples, C.QUERY_DIM).clone()
    sub[:, :, C.U] += spread[:, None] * z[:, :, 0]
    sub[:, :, C.V] += spread[:, None] * z[:, :, 1]
    sub[:, :, C.U:C.V + 1] = torch.remainder(sub[:, :, C.U:C.V + 1], 1.0)  # the tile repeats
    sub[:, :, C.SIGMA] = fine[:, None]
    return answer(sub.reshape(n * samples, C.QUERY_DIM)).reshape(n, samples, -1).mean(dim=1)


def mix_targets(target: torch.Tensor, distilled: torch.Tensor, coarse: torch.Tensor, weight: float) -> torch.Tensor:
    """(B, 3) data targets with the `coarse` (B,) rows' replaced by weight * distilled + (1 - weight) * data."""
    out = target.clone()
    out[coarse] = weight * distilled + (1.0 - weight) * target[coarse]
    return out
