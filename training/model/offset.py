"""Neural offset (paper Sec. 3.3): a learned ray depth turned into a parallax shift of u.

Pure torch: offset = r * (wo_x, wo_y) / max(wo_z, min_cos), r = scale * MLP(offset features, wo).
"""

from __future__ import annotations

import torch


def direction_z(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(N,) x, y of unit vectors -> (N,) z = sqrt(max(1 - x^2 - y^2, 0))."""
    return torch.sqrt(torch.clamp(1.0 - x * x - y * y, min=0.0))


def parallax_shift(
    depth: torch.Tensor, wo_x: torch.Tensor, wo_y: torch.Tensor, min_cos: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Fixed function stage: (N,) ray depth r and view direction -> (N,) du, dv = r * wo_xy / wo_z."""
    scale = depth / torch.clamp(direction_z(wo_x, wo_y), min=min_cos)
    return scale * wo_x, scale * wo_y
