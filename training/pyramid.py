"""Neural texture pyramid lookup: trilinear (bilinear in space, linear in log2 sigma), wrap-around.

Pure torch. Levels are stored stacked in one flat atlas of shape (texels, channels), finest level
first, so one lookup is a single gather of 8 rows per query (4 bilinear taps on each of the two
nearest levels). The ONNX export (`export.py`) builds the same arithmetic op for op.
"""

from __future__ import annotations

import math

import torch

from .config import MaterialConfig


def level_of_detail(sigma: torch.Tensor, resolution: int) -> torch.Tensor:
    """(N,) footprint sigma in tile units -> (N,) continuous level, clamp(log2(sigma * R), 0, log2 R).

    Same convention as `neumip.client.contract.level_of_detail`; sigma <= 0 reads the finest level.
    """
    tiny = torch.finfo(sigma.dtype).tiny
    lod = torch.log2(torch.clamp(sigma, min=tiny) * resolution)
    return torch.clamp(lod, 0.0, float(math.log2(resolution)))


def wrap(u: torch.Tensor) -> torch.Tensor:
    """(N,) position -> (N,) position in [0, 1] (period 1)."""
    return u - torch.floor(u)


def bilinear_taps(
    u: torch.Tensor, v: torch.Tensor, size: torch.Tensor, start: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Atlas rows and weights of the 4 bilinear taps of positions (u, v) in [0, 1].

    u, v: (N, 1) float; size, start: (N, L) int64 (texels per side and first atlas row of each of
    L levels). Returns rows (N, L, 4) int64 and weights (N, L, 4) float, taps ordered
    (x0 y0, x1 y0, x0 y1, x1 y1); texel centres sit at (i + 0.5) / size, wrapping around.
    """
    sizef = size.to(u.dtype)
    x = u * sizef - 0.5
    y = v * sizef - 0.5
    x0f, y0f = torch.floor(x), torch.floor(y)
    fx, fy = x - x0f, y - y0f
    x0 = torch.remainder(x0f.long(), size)
    y0 = torch.remainder(y0f.long(), size)
    x1 = torch.remainder(x0 + 1, size)
    y1 = torch.remainder(y0 + 1, size)
    row0, row1 = start + y0 * size, start + y1 * size
    rows = torch.stack([row0 + x0, row0 + x1, row1 + x0, row1 + x1], dim=-1)
    gx, gy = 1.0 - fx, 1.0 - fy
    weights = torch.stack([gx * gy, fx * gy, gx * fy, fx * fy], dim=-1)
    return rows, weights


def gather_blend(atlas: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(T, C) atlas, (N, K) rows, (N, K) weights -> (N, C) weighted sum of the gathered texels."""
    texels = atlas[rows]  # (N, K, C)
    return torch.einsum("nk,nkc->nc", weights, texels)


def pyramid_lookup(
    atlas: torch.Tensor, config: MaterialConfig, u: torch.Tensor, v: torch.Tensor, sigma: torch.Tensor
) -> torch.Tensor:
    """Trilinear feature lookup. atlas (T, C); u, v, sigma (N,) -> features (N, C)."""
    device = atlas.device
    sizes = torch.tensor(config.level_sizes(), dtype=torch.long, device=device)
    starts = torch.tensor(config.level_starts(), dtype=torch.long, device=device)
    lod = level_of_detail(sigma, config.resolution)
    lo = torch.floor(lod)
    t = (lod - lo).unsqueeze(1)  # (N, 1)
    lo_i = lo.long()
    hi_i = torch.clamp(lo_i + 1, max=config.levels)
    levels = torch.stack([lo_i, hi_i], dim=1)  # (N, 2)
    rows, weights = bilinear_taps(wrap(u).unsqueeze(1), wrap(v).unsqueeze(1), sizes[levels], starts[levels])
    weights = weights * torch.cat([1.0 - t, t], dim=1).unsqueeze(2)  # (N, 2, 4)
    return gather_blend(atlas, rows.flatten(1), weights.flatten(1))


def texture_lookup(texture: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear wrap-around lookup of one (S, S, C) texture at (N,) u, v -> (N, C)."""
    size = texture.shape[0]
    n = u.shape[0]
    full = torch.full((n, 1), size, dtype=torch.long, device=texture.device)
    zero = torch.zeros((n, 1), dtype=torch.long, device=texture.device)
    rows, weights = bilinear_taps(wrap(u).unsqueeze(1), wrap(v).unsqueeze(1), full, zero)
    return gather_blend(texture.reshape(size * size, -1), rows.flatten(1), weights.flatten(1))
