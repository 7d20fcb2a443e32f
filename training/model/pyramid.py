"""Neural texture pyramid lookup: trilinear (bilinear in space, linear in log2 sigma), wrap-around.

Pure torch. Levels are stored stacked in one flat atlas of shape (texels, channels), finest level
first, so one lookup is a single gather of 8 rows per query (4 bilinear taps on each of the two
nearest levels). The ONNX export (`graph.py`) builds the same arithmetic op for op.
"""

from __future__ import annotations

import math

import torch

from neumip.core.config import MaterialConfig


def level_of_detail(sigma: torch.Tensor, resolution: int, bias: int = 0) -> torch.Tensor:
    """(N,) footprint sigma in tile units -> (N,) continuous level, clamp(log2(sigma * R) + bias, 0, log2 R).

    Same convention as `neumip.core.contract.level_of_detail`; sigma <= 0 reads the finest level.
    """
    tiny = torch.finfo(sigma.dtype).tiny
    lod = torch.log2(torch.clamp(sigma, min=tiny) * (resolution * 2**bias))
    return torch.clamp(lod, 0.0, float(math.log2(resolution)))


def wrap(u: torch.Tensor) -> torch.Tensor:
    """(N,) position -> (N,) position in [0, 1] (period 1).

    floor() has zero gradient: it is taken of the detached value so autograd does not build (and
    fill) zero gradients for it, which was a large share of a CPU training step.
    """
    return u - torch.floor(u.detach())


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
    x0f, y0f = torch.floor(x.detach()), torch.floor(y.detach())  # zero gradient: see wrap()
    fx, fy = x - x0f, y - y0f
    x0 = torch.remainder(x0f.long(), size)
    y0 = torch.remainder(y0f.long(), size)
    x1 = torch.remainder(x0 + 1, size)
    y1 = torch.remainder(y0 + 1, size)
    # taps as outer products (y0, y1) x (x0, x1): row-major order x0 y0, x1 y0, x0 y1, x1 y1
    row_y = (start.unsqueeze(-1) + torch.stack([y0, y1], dim=-1) * size.unsqueeze(-1)).unsqueeze(-1)  # (N, L, 2, 1)
    rows = (row_y + torch.stack([x0, x1], dim=-1).unsqueeze(-2)).flatten(-2)  # (N, L, 4)
    wy = torch.stack([1.0 - fy, fy], dim=-1).unsqueeze(-1)  # (N, L, 2, 1)
    weights = (wy * torch.stack([1.0 - fx, fx], dim=-1).unsqueeze(-2)).flatten(-2)  # (N, L, 4)
    return rows, weights


class _GatherBlend(torch.autograd.Function):
    """out[n] = sum_k weights[n, k] * atlas[rows[n, k]], with a scatter-add backward.

    Autograd's own backward of `atlas[rows]` goes through a sorting index_put; index_add_ of the
    (N*K, C) weighted output gradients is several times faster on CPU.
    """

    @staticmethod
    def forward(ctx, atlas: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        n, k = rows.shape
        flat = rows.reshape(-1)
        texels = atlas.index_select(0, flat).view(n, k, -1)  # (N, K, C)
        ctx.save_for_backward(flat, weights, texels)
        ctx.atlas_shape = atlas.shape
        return torch.bmm(weights.unsqueeze(1), texels).squeeze(1)  # (N, C)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        flat, weights, texels = ctx.saved_tensors
        grad_atlas = grad_weights = None
        if ctx.needs_input_grad[0]:
            contrib = (weights.unsqueeze(2) * grad.unsqueeze(1)).reshape(flat.shape[0], -1)  # (N*K, C)
            grad_atlas = torch.zeros(ctx.atlas_shape, dtype=grad.dtype, device=grad.device)
            grad_atlas.index_add_(0, flat, contrib)
        if ctx.needs_input_grad[2]:
            grad_weights = torch.bmm(texels, grad.unsqueeze(2)).squeeze(2)  # (N, K)
        return grad_atlas, None, grad_weights


def gather_blend(atlas: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """(T, C) atlas, (N, K) rows, (N, K) weights -> (N, C) weighted sum of the gathered texels."""
    return _GatherBlend.apply(atlas, rows, weights)


def as_stored(texture: torch.Tensor, config: MaterialConfig) -> torch.Tensor:
    """A texture as the model file stores it: rounded to float16 with `MaterialConfig.half_textures` (the
    gradient passes the rounding unchanged), else as it is."""
    if not config.half_textures:
        return texture
    return texture + (texture.half().float() - texture).detach()


def mip_levels(texture: torch.Tensor) -> list[torch.Tensor]:
    """(S, S, C) texture -> its mip pyramid, finest (the texture itself) first down to 1 x 1: each coarser texel is
    ((a + b) + (c + d)) / 4 of the 2 x 2 under it (rows y, y + 1: a, b; c, d), in that order on every device, so the
    levels training reads are the bits the export stores (it calls this function too)."""
    levels = [texture]
    while levels[-1].shape[0] > 1:
        t = levels[-1]
        levels.append(((t[0::2, 0::2] + t[0::2, 1::2]) + (t[1::2, 0::2] + t[1::2, 1::2])) * 0.25)
    return levels


def mip_atlas(texture: torch.Tensor) -> torch.Tensor:
    """(S, S, C) texture -> (T, C) its `mip_levels` flat, finest first (a pyramid atlas)."""
    return torch.cat([level.reshape(-1, texture.shape[-1]) for level in mip_levels(texture)])


def pyramid_lookup(
    atlas: torch.Tensor, config: MaterialConfig, u: torch.Tensor, v: torch.Tensor, sigma: torch.Tensor
) -> torch.Tensor:
    """Trilinear feature lookup. atlas (T, C); u, v, sigma (N,) -> features (N, C)."""
    device = atlas.device
    sizes = torch.tensor(config.level_sizes(), dtype=torch.long, device=device)
    starts = torch.tensor(config.level_starts(), dtype=torch.long, device=device)
    lod = level_of_detail(sigma, config.resolution, config.lod_bias)
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
