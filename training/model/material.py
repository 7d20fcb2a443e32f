"""The NeuMIP material: texture pyramid + neural offset + decoder MLP (paper Eq. 7), and the
map-informed variant whose textures an encoder computes from the material's prefiltered maps. Pure torch."""

from __future__ import annotations

import torch
from torch import nn

from neumip.core import contract as C

from neumip.core import head
from neumip.core import weights as W
from neumip.core.config import MaterialConfig
from neumip.training.model.base import base_answer, corrected, frame_inputs, half_direction, lift, light_visibility
from neumip.training.model.energy import energy_gain
from neumip.training.model.maps import MapConfig, level_feature
from neumip.training.model.offset import parallax_shift
from neumip.training.model.pyramid import as_stored, level_of_detail, mip_atlas, pyramid_lookup, texture_lookup
from neumip.training.model.relief import relief_shift


DECODER_INPUTS = {
    "half_vector": lambda maps, wi, wo: half_vector(wi, wo),
    "frame": lambda maps, wi, wo: frame_inputs(maps, wi, wo),
    "visibility": lambda maps, wi, wo: light_visibility(maps, wi),
}
"""How each row of `core.config.DECODER_INPUTS` is computed: (looked-up base maps (N, BASE_CHANNELS) or None,
wi (N, 2), wo (N, 2)) -> (N, width). The graph writer's twin is `training.export.graph.DECODER_INPUTS`."""


def mlp(inputs: int, outputs: int, layers: int, hidden: int) -> nn.Sequential:
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
        self.decoder = mlp(*W.mlps(config)[W.DECODER], config.layers, hidden=config.hidden)
        if config.coarse_decoder:  # the coarse levels' (`MaterialConfig.coarse_decoder`)
            self.coarse_decoder = mlp(*W.mlps(config)[W.COARSE_DECODER], config.layers, hidden=config.hidden)
        if config.base:  # the answer starts as the base's: zero correction, zero additive term
            for decoder in self.decoders():
                nn.init.zeros_(decoder[-1].weight)
                nn.init.zeros_(decoder[-1].bias)
            self.register_buffer(W.BASE, torch.zeros(W.weight_shapes(config)[W.BASE]))
        if config.relief:
            self.register_buffer(W.RELIEF, torch.zeros(W.weight_shapes(config)[W.RELIEF]))
        if config.energy_bins:  # every gain 1 until a fit after training (`energy.fit_energy`)
            self.register_buffer(W.ENERGY, torch.ones(W.weight_shapes(config)[W.ENERGY]))
        if config.head == "yuv":
            self.register_buffer("yuv_to_rgb", torch.tensor(head.YUV_TO_RGB.T, dtype=torch.float32), persistent=False)
        if config.offset:
            r = config.resolution
            self.offset_texture = nn.Parameter(torch.randn(r, r, config.offset_channels) * init_std)
            self.offset_mlp = mlp(*W.mlps(config)[W.OFFSET_MLP], config.layers, hidden=config.hidden)

    def decoders(self) -> list[nn.Sequential]:
        """The decoder, and the coarse levels' with `MaterialConfig.coarse_decoder`."""
        return [self.decoder] + ([self.coarse_decoder] if self.config.coarse_decoder else [])

    def decode(self, inputs: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        """The decoder's output for its (N, inputs) inputs; with a coarse decoder, blended into that one's by
        w = clamp(lod - K, 0, 1) at the queries' footprints sigma (N,)."""
        out = self.decoder(inputs)
        if not self.config.coarse_decoder:
            return out
        lod = level_of_detail(sigma, self.config.resolution, self.config.lod_bias)
        w = torch.clamp(lod - self.config.coarse_decoder, 0.0, 1.0)[:, None]
        return out + w * (self.coarse_decoder(inputs) - out)

    @torch.no_grad()
    def set_maps(self, name: str, levels: list) -> None:
        """Store a pyramid made from the material's maps, (S, S, C) per level, finest first: the base's
        (`W.BASE`, `base.base_maps`) or the relief's heights (`W.RELIEF`, `relief.relief_heights`)."""
        buffer = getattr(self, name)
        atlas = torch.cat([torch.as_tensor(lvl, dtype=torch.float32).reshape(-1, buffer.shape[1]) for lvl in levels])
        if atlas.shape != buffer.shape:
            raise ValueError(f"{name} of {atlas.shape[0]} texels, the config's pyramid has {buffer.shape[0]}")
        buffer.copy_(atlas)

    def textures(self) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The raw neural textures: pyramid levels (finest first, each (S, S, C)) and the offset texture."""
        return list(self.pyramid), (self.offset_texture if self.config.offset else None)

    @torch.no_grad()
    def store_textures(self, levels: list[torch.Tensor] | None, offset_texture: torch.Tensor | None) -> None:
        """Make `textures()` return these (e.g. blurred copies, so an export computes what training
        did); None keeps that texture as it is."""
        for param, value in zip(self.pyramid, levels or []):
            if value is not param:
                param.copy_(value)
        if offset_texture is not None and offset_texture is not self.offset_texture:
            self.offset_texture.copy_(offset_texture)

    def freeze_offset(self) -> None:
        """Stop training what makes the offset texture (`Trainer`, at the end of the blur schedule)."""
        self.offset_texture.requires_grad_(False)
        self.offset_texture.grad = None

    def forward(
        self,
        queries: torch.Tensor,
        pyramid: list[torch.Tensor] | None = None,
        offset_texture: torch.Tensor | None = None,
        landed: bool = False,
        ceiling: bool = True,
    ) -> torch.Tensor:
        """(N, 7) queries -> (N, 3) RGB >= 0 (and at most `MaterialConfig.ceiling`, unless `ceiling` is False:
        the training loss reads the answers unclamped, so that a query above the ceiling still learns).

        `pyramid` / `offset_texture` replace the stored textures (training evaluates blurred copies).
        `landed`: the queries' u, v are already where the relief stage lands (`relief.landed_positions`:
        training marches each data row once, its heights being fixed).
        """
        levels, otex = pyramid, offset_texture
        if levels is None or (self.config.offset and otex is None):  # (an encoder's textures cost a pass)
            stored_levels, stored_otex = self.textures()
            levels = stored_levels if levels is None else levels
            otex = stored_otex if otex is None else otex
        u, v, sigma = queries[:, C.U], queries[:, C.V], queries[:, C.SIGMA]
        wo = queries[:, C.WO_X : C.WO_Y + 1]
        if self.config.relief and not landed:
            du, dv = relief_shift(as_stored(self.relief_heights, self.config), self.config, u, v, sigma, wo)
            u, v = u + du, v + dv
        if self.config.offset:
            otex = as_stored(otex, self.config)
            if self.config.offset_mip:  # its mip pyramid at the footprint, the coarser levels stored rounded too
                mips = as_stored(mip_atlas(otex), self.config)
                feat = pyramid_lookup(mips, self.config.offset_pyramid(), u, v, sigma)
            else:
                feat = texture_lookup(otex, u, v)
            depth = self.config.offset_scale * self.offset_mlp(torch.cat([feat, wo], dim=1))[:, 0]
            du, dv = parallax_shift(depth, wo[:, 0], wo[:, 1], self.config.offset_min_cos)
            u, v = u + du, v + dv
        atlas = torch.cat([lvl.reshape(-1, self.config.channels) for lvl in levels], dim=0)
        features = pyramid_lookup(as_stored(atlas, self.config), self.config, u, v, sigma)
        directions = queries[:, C.WI_X : C.WO_Y + 1]
        wi, wo = directions[:, :2], directions[:, 2:]
        maps = (pyramid_lookup(as_stored(self.base_maps, self.config), self.config.base_pyramid(), u, v, sigma)
                if self.config.base else None)
        inputs = {row.name: DECODER_INPUTS[row.name](maps, wi, wo) for row in self.config.decoder_inputs()}
        if inputs:
            features = torch.cat([features, *inputs.values()], dim=1)
        lit = inputs.get("visibility")  # the base's visibility of the light: the base's answer reads it too
        out = self.decode(torch.cat([features, directions], dim=1), sigma)
        if self.config.base:
            out = corrected(base_answer(maps, wi, wo, self.config.terminator, lit), out)
        if self.config.energy_bins:
            out = out * energy_gain(getattr(self, W.ENERGY), self.config, sigma, wi, wo)
        if self.config.head == "yuv":  # exp(YUV) - 1 times the shadow mask (core/head.py)
            shadow = head.SHADOW_FLOOR + torch.sigmoid(out[:, 3:])
            out = torch.expm1(out[:, :3] @ self.yuv_to_rgb) * shadow
        out = torch.relu(out)
        return torch.clamp(out, max=self.config.ceiling) if ceiling and self.config.ceiling else out


def half_vector(wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """(N, 2) wi, wo (x, y of unit vectors, z >= 0) -> (N, 4): h = normalize(wi + wo) and cos(theta_d) = h . wi
    (`MaterialConfig.half_vector`; the graph computes the same in `export._half_vector`)."""
    wi3, wo3 = lift(wi), lift(wo)
    h = half_direction(wi3, wo3)
    return torch.cat([h, (h * wi3).sum(1, keepdim=True)], dim=1)


def neighbourhood(features: torch.Tensor, size: int) -> torch.Tensor:
    """(S, S, F) features -> (S, S, size^2 F): each texel's wrapped size x size neighbourhood,
    row by row (the texel itself in the middle)."""
    r = size // 2
    shifted = [torch.roll(features, (-dy, -dx), (0, 1)) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    return torch.cat(shifted, dim=2)


class MapMaterial(NeuMIPMaterial):
    """A NeuMIP material whose textures start from the material's maps (issue 25, lever 1).

    One MLP shared by every texel of every level (`encoder`) maps a neighbourhood of the level's
    prefiltered map features (`maps.prefilter`, buffers ``map_features_{i}``) and the level feature
    to the level's latent texture; a second one (`offset_encoder`) maps the finest level's to the
    offset texture. `pyramid` and `offset_texture` hold a free part added to them: zero, and trained
    only on the levels `MapConfig.residual` names (or set by `store_textures`).

    The decoder, the offset MLP and the lookups are the paper model's, so its export is the paper's
    graph with these textures baked in: `state_dict()` holds the textures the material answers with
    under the paper model's names (``pyramid.{i}``, ``offset_texture``: what `graph.py` reads) and
    the free parts under ``free.``; `load_state_dict` reads the free parts back.
    """

    def __init__(self, config: MaterialConfig, maps: MapConfig, features: list | None = None,
                 init_std: float = 0.1) -> None:
        super().__init__(config, init_std)
        self.maps = maps
        sizes = config.level_sizes()
        if features is not None and [tuple(f.shape) for f in features] != [(s, s, maps.features) for s in sizes]:
            raise ValueError(f"map features of shapes {[tuple(f.shape) for f in features]} do not match "
                             f"the pyramid's levels {sizes}")
        with torch.no_grad():
            for param, size in zip(self.free_parameters(), sizes + sizes[:1]):  # the offset texture: the finest size
                param.zero_()
                param.requires_grad_(size <= maps.residual)
        for i, size in enumerate(sizes):
            value = torch.zeros(size, size, maps.features) if features is None else torch.as_tensor(features[i])
            self.register_buffer(f"map_features_{i}", value.to(torch.float32).clone())
        self.encoder = mlp(maps.inputs, config.channels, maps.layers, hidden=maps.hidden)
        if config.offset:
            self.offset_encoder = mlp(maps.inputs, config.offset_channels, maps.layers, hidden=maps.hidden)
        self.register_state_dict_post_hook(_state_with_textures)
        self.register_load_state_dict_pre_hook(_free_parts_from_state)

    def free_parameters(self) -> list[nn.Parameter]:
        """The free textures added to the encoded ones (pyramid levels, then the offset texture)."""
        return list(self.pyramid) + ([self.offset_texture] if self.config.offset else [])

    def encoder_inputs(self, level: int) -> torch.Tensor:
        """(S * S, maps.inputs) encoder inputs of one level's texels, row-major."""
        features = getattr(self, f"map_features_{level}")
        size = features.shape[0]
        near = neighbourhood(features, self.maps.neighbourhood).reshape(size * size, -1)
        return torch.cat([near, near.new_full((size * size, 1), level_feature(size))], dim=1)

    def textures(self) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The encoded textures plus their free parts: levels (finest first, (S, S, C)) and the offset texture."""
        sizes = self.config.level_sizes()
        inputs = [self.encoder_inputs(i) for i in range(len(sizes))]
        encoded = self.encoder(torch.cat(inputs, dim=0)).split([s * s for s in sizes])  # one MLP call
        levels = [e.view(s, s, -1) + free for e, s, free in zip(encoded, sizes, self.pyramid)]
        if not self.config.offset:
            return levels, None
        size = sizes[0]
        return levels, self.offset_encoder(inputs[0]).view(size, size, -1) + self.offset_texture

    @torch.no_grad()
    def store_textures(self, levels: list[torch.Tensor] | None, offset_texture: torch.Tensor | None) -> None:
        """Make `textures()` return these: their difference from the encoded textures goes to the free parts."""
        now_levels, now_offset = self.textures()
        for param, value, now in zip(self.pyramid, levels or [], now_levels):
            param.add_(value - now)
        if offset_texture is not None:
            self.offset_texture.add_(offset_texture - now_offset)

    def freeze_offset(self) -> None:
        """Stop training the offset texture and the encoder that makes it."""
        super().freeze_offset()
        for param in self.offset_encoder.parameters():
            param.requires_grad_(False)
            param.grad = None


FREE = "free."
"""State-dict prefix of a `MapMaterial`'s free texture parts."""


def _texture_names(material: MapMaterial) -> list[str]:
    return [f"pyramid.{i}" for i in range(len(material.pyramid))] + (["offset_texture"] if material.config.offset else [])


def _state_with_textures(material: MapMaterial, state: dict, prefix: str, _meta) -> None:
    """state_dict post-hook: the textures the material answers with under the paper model's names."""
    with torch.no_grad():
        levels, offset_texture = material.textures()
    for name, texture in zip(_texture_names(material), levels + [offset_texture]):
        state[prefix + FREE + name] = state[prefix + name]
        state[prefix + name] = texture.detach()


def _free_parts_from_state(material: MapMaterial, state: dict, prefix: str, *_args) -> None:
    """load_state_dict pre-hook: the free parts back under their parameters' names."""
    for name in _texture_names(material):
        if prefix + FREE + name in state:
            state[prefix + name] = state.pop(prefix + FREE + name)
