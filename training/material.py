"""The NeuMIP material: texture pyramid + neural offset + decoder MLP (paper Eq. 7). Pure torch."""

from __future__ import annotations

import torch
from torch import nn

from neumip.core import contract as C

from neumip.core import head
from neumip.core.config import MaterialConfig
from .offset import parallax_shift
from .pyramid import pyramid_lookup, texture_lookup


def mlp(inputs: int, hidden: int, outputs: int, layers: int) -> nn.Sequential:
    """`layers` linear layers with ReLU between them (none after the last)."""
    widths = [inputs] + [hidden] * (layers - 1) + [outputs]
    mods: list[nn.Module] = []
    for i in range(layers):
        mods.append(nn.Linear(widths[i], widths[i + 1]))
        if i < layers - 1:
            mods.append(nn.ReLU())
    return nn.Sequential(*mods)


class NeuMIPMaterial(nn.Module):
    """M(u, sigma, wi, wo) -> RGB for (N, 7) queries in the contract's layout."""

    def __init__(self, config: MaterialConfig, init_std: float = 0.1) -> None:
        super().__init__()
        self.config = config
        self.pyramid = nn.ParameterList(
            nn.Parameter(torch.randn(s, s, config.channels) * init_std) for s in config.level_sizes()
        )
        self.decoder = mlp(config.channels + 4, config.hidden, head.outputs(config.head), config.layers)
        if config.head == "yuv":
            self.register_buffer("yuv_to_rgb", torch.tensor(head.YUV_TO_RGB.T, dtype=torch.float32), persistent=False)
        if config.offset:
            r = config.resolution
            self.offset_texture = nn.Parameter(torch.randn(r, r, config.offset_channels) * init_std)
            self.offset_mlp = mlp(config.offset_channels + 2, config.hidden, 1, config.layers)

    def textures(self) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The raw neural textures: pyramid levels (finest first, each (S, S, C)) and the offset texture."""
        return list(self.pyramid), (self.offset_texture if self.config.offset else None)

    def forward(
        self,
        queries: torch.Tensor,
        pyramid: list[torch.Tensor] | None = None,
        offset_texture: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """(N, 7) queries -> (N, 3) RGB >= 0.

        `pyramid` / `offset_texture` replace the stored textures (training evaluates blurred copies).
        """
        levels, otex = self.textures()
        levels = levels if pyramid is None else pyramid
        otex = otex if offset_texture is None else offset_texture
        u, v, sigma = queries[:, C.U], queries[:, C.V], queries[:, C.SIGMA]
        wo = queries[:, C.WO_X : C.WO_Y + 1]
        if self.config.offset:
            feat = texture_lookup(otex, u, v)
            depth = self.config.offset_scale * self.offset_mlp(torch.cat([feat, wo], dim=1))[:, 0]
            du, dv = parallax_shift(depth, wo[:, 0], wo[:, 1], self.config.offset_min_cos)
            u, v = u + du, v + dv
        atlas = torch.cat([lvl.reshape(-1, self.config.channels) for lvl in levels], dim=0)
        features = pyramid_lookup(atlas, self.config, u, v, sigma)
        out = self.decoder(torch.cat([features, queries[:, C.WI_X : C.WO_Y + 1]], dim=1))
        if self.config.head == "yuv":  # exp(YUV) - 1 times the shadow mask (core/head.py)
            shadow = head.SHADOW_FLOOR + torch.sigmoid(out[:, 3:])
            out = torch.expm1(out[:, :3] @ self.yuv_to_rgb) * shadow
        return torch.relu(out)
