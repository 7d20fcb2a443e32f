"""Progressive Gaussian blur of the neural textures (paper Sec. 4: training in a coarse-to-fine way).

Pure torch. The blur is separable and wraps around (the textures tile), with a kernel of radius
ceil(3 sigma) normalised to sum 1. Each of the two 1-D passes is a product with the S x S circulant
matrix of the kernel folded onto the circle (levels up to 256 texels, or kernels wider than the
level) or a circular 1-D convolution (larger levels); both compute the same wrapped blur.

`effective_textures` gives the blurred textures a run evaluates the material with at a step, and
`bake` stores them as the material's own, so an export computes what training computed.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from neumip.training.model.material import NeuMIPMaterial
from neumip.training.loop.config import TrainConfig


def blur_sigma(step: int, config: TrainConfig) -> float:
    """Blur sigma (finest-level texels) at `step`: blur_start halving every blur_half_life; 0 once
    it is below blur_min (the schedule has ended)."""
    sigma = config.blur_start * 0.5 ** (step / config.blur_half_life)
    return sigma if sigma >= config.blur_min else 0.0


def schedule_end(config: TrainConfig) -> int:
    """First step at which `blur_sigma` is 0."""
    if config.blur_start < config.blur_min:
        return 0
    step = math.ceil(config.blur_half_life * math.log2(config.blur_start / config.blur_min))
    while blur_sigma(step, config) > 0:  # guard the float rounding of the closed form
        step += 1
    while step > 0 and blur_sigma(step - 1, config) == 0:
        step -= 1
    return step


def gaussian_kernel(sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(2r + 1,) normalised Gaussian weights, r = ceil(3 sigma)."""
    radius = max(1, math.ceil(3.0 * sigma))
    x = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def circulant(size: int, kernel: torch.Tensor) -> torch.Tensor:
    """(S, S) matrix B with (B @ x)[i] = sum_d kernel[d] x[(i + d - r) mod S]: the wrapped blur."""
    radius = (kernel.shape[0] - 1) // 2
    offsets = torch.arange(-radius, radius + 1, device=kernel.device)
    cols = (torch.arange(size, device=kernel.device)[:, None] + offsets[None, :]) % size  # (S, 2r+1)
    matrix = torch.zeros(size, size, dtype=kernel.dtype, device=kernel.device)
    return matrix.scatter_add_(1, cols, kernel.expand(size, -1).contiguous())


MATRIX_MAX_SIZE = 256
"""Levels up to this size blur by two circulant matrix products (fastest on CPU, measured);
larger ones by circular 1-D convolutions (cost grows with the kernel, not the size squared)."""


def _blur_rows(x: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Wrapped 1-D blur along the last axis of (B, S) rows by circular convolution (radius < S)."""
    radius = (kernel.shape[0] - 1) // 2
    padded = F.pad(x.unsqueeze(1), (radius, radius), mode="circular")  # (B, 1, S + 2r)
    return F.conv1d(padded, kernel.view(1, 1, -1)).squeeze(1)


def blur_texture(texture: torch.Tensor, sigma: float) -> torch.Tensor:
    """(S, S, C) texture -> (S, S, C) texture blurred by a wrapped Gaussian of std `sigma` texels."""
    size, _, channels = texture.shape
    kernel = gaussian_kernel(sigma, texture.dtype, texture.device)
    radius = (kernel.shape[0] - 1) // 2
    if size <= MATRIX_MAX_SIZE or radius >= size:
        m = circulant(size, kernel)  # (S, S), symmetric
        along_y = (m @ texture.reshape(size, size * channels)).view(size, size, channels)
        # along x as one plain matrix product too: a (S, S) @ (S_y, S_x, C) broadcast runs as S small
        # batched products, measured ~8x slower than the same multiply-adds in one (S, S*C) product
        by_x = along_y.transpose(0, 1).reshape(size, size * channels)  # (S_x, S_y * C)
        return (m @ by_x).view(size, size, channels).transpose(0, 1)
    # pass along x: rows are (y, c) pairs
    x = texture.permute(0, 2, 1).reshape(size * channels, size)
    x = _blur_rows(x, kernel).reshape(size, channels, size)  # (y, c, x)
    # pass along y: rows are (c, x) pairs
    y = x.permute(1, 2, 0).reshape(channels * size, size)
    y = _blur_rows(y, kernel).reshape(channels, size, size)  # (c, x, y)
    return y.permute(2, 1, 0)


def blur_pyramid(levels: list[torch.Tensor], sigma: float, sigma_min: float) -> list[torch.Tensor]:
    """Blur level l of a pyramid (finest first, each (S, S, C)) by sigma / 2^l; levels whose sigma
    falls below `sigma_min` are returned unchanged."""
    out = []
    for level, texture in enumerate(levels):
        s = sigma / 2.0**level
        out.append(blur_texture(texture, s) if s >= sigma_min and texture.shape[0] > 1 else texture)
    return out


# --- the blur a run applies, baked into the material ----------------------------------------------


def effective_textures(
    material: NeuMIPMaterial, sigma: float, config: TrainConfig, offset_frozen: bool
) -> tuple[list[torch.Tensor], torch.Tensor | None]:
    """The (blurred) textures the material is evaluated with at blur `sigma`."""
    levels, otex = material.textures()
    if sigma > 0:
        levels = blur_pyramid(levels, sigma, config.blur_min)
    if otex is not None and not offset_frozen:
        otex = blur_texture(otex, max(sigma, config.offset_blur_floor))
    return levels, otex


@torch.no_grad()
def bake(material: NeuMIPMaterial, levels: list[torch.Tensor], otex: torch.Tensor | None) -> None:
    """Store the given effective textures as the material's own (export then matches training)."""
    material.store_textures(levels, otex)


def bake_checkpoint_textures(material: NeuMIPMaterial, extra: dict) -> bool:
    """Bake the blur a training run applied at the checkpoint's step into `material` (in place).

    A checkpoint written inside the blur schedule stores raw textures, while training evaluated
    blurred copies; baking makes an export of it compute what training computed. Returns whether
    anything was baked (False for finished or baked runs and for checkpoints without a run state).
    """
    state, saved = extra.get("state"), extra.get("train_config")
    if not state or not saved or state.get("baked"):
        return False
    config = TrainConfig.from_dict(saved)
    sigma = blur_sigma(state["step"], config)
    frozen = state.get("offset_frozen", False)
    if sigma <= 0 and (not material.config.offset or frozen):
        return False
    bake(material, *effective_textures(material, sigma, config, frozen))
    return True
