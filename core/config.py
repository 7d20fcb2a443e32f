"""Model configuration: the architecture of one neural material, shared by training and export.

Kept free of torch so that export, the server and tests can read it anywhere.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields

from neumip.core.head import HEADS


def dataclass_from_dict(cls, data: dict):
    """Build dataclass `cls` from `data`, refusing keys that are not its fields (typos in files)."""
    unknown = set(data) - {f.name for f in fields(cls)}
    if unknown:
        raise ValueError(f"unknown {cls.__name__} fields: {sorted(unknown)}")
    return cls(**data)


HALF_FLOOR = 1e-12
"""|wi + wo|^2 is clamped to at least this before the half vector is normalised (`MaterialConfig.half_vector`)."""

BASE_HORIZONS = 8
"""Azimuths of the base's horizons (0, 45, ... degrees from +u towards +v)."""
BASE_CHANNELS = 9 + BASE_HORIZONS
"""Channels of the base maps' pyramid (`MaterialConfig.base`): diffuse colour (3), specular F0 (3), the
mean slopes dh/du, dh/dv (2), the GGX alpha^2 with the slopes' variance added (1), and the sine of the
horizon's elevation towards each of `BASE_HORIZONS` azimuths."""
BASE_AZIMUTHS = tuple((math.cos(2 * math.pi * j / BASE_HORIZONS), math.sin(2 * math.pi * j / BASE_HORIZONS))
                      for j in range(BASE_HORIZONS))
"""Unit vectors (x, y) of the base's horizon azimuths."""
BASE_AZIMUTH_KERNEL = math.cos(2 * math.pi / BASE_HORIZONS)
"""An azimuth's weight towards wi is max(cos(phi - phi_j) - this, 0): non-zero for the two nearest only."""
BASE_AZIMUTH_FLOOR = 1e-6
"""|wi_xy| and the azimuth weights' sum are clamped to at least this (a light at the zenith clears every horizon)."""
BASE_SHADOW_SOFTNESS = 0.1
"""The base's shadow from its horizons: visibility clamp((wi_z - sin(horizon)) / softness + 1/2, 0, 1)."""
TERMINATORS = ("all", "specular", "none")
"""`MaterialConfig.terminator`'s values: the base's terms that S(g) multiplies."""
BASE_OUTPUTS = 6
"""Decoder outputs with a base: a log-scale correction per RGB channel, then an additive term per channel."""
BASE_ALPHA2_FLOOR = 1e-4
"""alpha^2 of the base's GGX lobe is clamped to at least this (roughness 0.1)."""
BASE_COS_FLOOR = 1e-4
"""The base's cos(n, wo) is clamped to at least this in the specular term's denominator."""
BASE_WI_FLOOR = 0.05
"""The reference plane's wi_z is clamped to at least this where the base divides by it."""
BASE_LOG_CEILING = 8.0
"""The decoder's log-scale correction is clamped to at most this (exp(8) ~ 3000x) before exp."""
RELIEF_MIN_COS = 0.25
"""The relief stage marches along wo_xy / max(wo_z, this): a grazing view's ray is followed at most ~3.9x
its depth sideways (`MaterialConfig.relief`)."""
def same_footprint_level(levels: int, pyramid_levels: int, finest_level: int) -> int:
    """The level of a pyramid of ``pyramid_levels`` + 1 levels that holds the footprint of level K = ``finest_level``
    of the latents' ``levels`` + 1: every pyramid's level of detail is log2(sigma R) + lod_bias at its own
    resolution R, so the same footprint is log2(R_pyramid / R_latents) levels further down it (coarser maps: up),
    clamped at 0. K = 0 is every query, the finest footprints too: 0."""
    return max(0, finest_level + pyramid_levels - levels) if finest_level else 0


@dataclass(frozen=True)
class DecoderInput:
    """One of the decoder's optional inputs: a row of `DECODER_INPUTS`."""

    name: str
    """Its part of the decoder's stored first layer (``decoder.0.half_weight.NAME``) and its key in the torch
    model's and the graph writer's tables of how it is computed."""
    width: int
    """Inputs it adds to the decoder's first layer, per light."""
    switch: str
    """The `MaterialConfig` field (a bool) that turns it on."""
    reads_base: bool
    """It reads the base maps' pyramid, so it needs a base (`MaterialConfig.base`)."""


DECODER_INPUTS = (
    DecoderInput("half_vector", 4, "half_vector", reads_base=False),  # h_x, h_y, h_z, cos(theta_d)
    DecoderInput("frame", 6, "local_frame", reads_base=True),  # wi, wo (x, y, z) in the base normal's frame
    DecoderInput("visibility", 1, "visibility_input", reads_base=True),  # the base's visibility V(wi)
)
"""The decoder's optional inputs, in the order its first layer reads them: after the texture features, before
the query columns. Every one is computed per light. The torch model (`training/model/material.py`) and the graph
writer (`training/export/graph.py`) each hold how a row is computed; the weights' shapes, the graph reader and
the command-line flags iterate this table."""


DERIVED_FIELDS = ("resolution", "base", "relief", "relief_steps", "ceiling")
"""`MaterialConfig` fields a command derives instead of taking each as a flag of its own (`core.flags`): the
pyramids' resolutions (from the data and the material's maps: `--base`, `--relief [STEPS]`) and the trainer's
ceiling. Every other field is a flag of `neumip train`, `fit` and `train-many`."""
FIELD_CHOICES = {"terminator": TERMINATORS, "head": HEADS}
"""The values a string field of `MaterialConfig` takes."""
RELIEF_DIVISION_FLOOR = 1e-12
"""The relief's secant step divides by at least this (its weight is 0 where the floor acts)."""


@dataclass(frozen=True)
class MaterialConfig:
    """Architecture of a NeuMIP material (paper Sec. 3; defaults follow the paper)."""

    resolution: int = 256
    """Texels per side of the finest pyramid level (a power of two); coarser levels halve down to 1 x 1."""
    channels: int = 7
    """Feature channels per texel of the neural texture pyramid."""
    hidden: int = 25
    """Width of the hidden layers of both MLPs."""
    layers: int = 4
    """Linear layers per MLP (the paper: 4, i.e. three hidden layers)."""
    offset: bool = True
    """Use the neural offset module (learned parallax)."""
    offset_channels: int = 7
    """Channels of the neural offset texture (single level at the finest resolution)."""
    offset_mip: bool = False
    """Read the neural offset texture at the query's footprint, as the latents are read: trilinear on its mip pyramid
    (each coarser level the mean of the 2 x 2 texels under it, derived from the learned finest level, not learned
    itself). A coarse footprint then reads a prefiltered offset (an average shift, not one texel's), and a model
    trimmed for far footprints keeps only the offset's coarse levels. False: the paper's single level, read
    bilinearly at the finest resolution by every query. Without the offset it has nothing to read (a recipe's value
    stays off there: `offset_pyramid` is None, and the config's JSON omits it)."""
    offset_scale: float = 0.1
    """Ray depth r = offset_scale * MLP output (author code: 0.1)."""
    offset_min_cos: float = 0.6
    """wo_z is clamped to at least this in offset = r * wo_xy / wo_z (grazing-angle stability; the
    authors' 0.6)."""
    half_vector: bool = False
    """The decoder also reads, per light, the half vector h = normalize(wi + wo) and cos(theta_d) =
    h . wi (the half and difference angles of Rusinkiewicz's parametrisation: a glossy lobe is simple
    in them); off: the paper's decoder, on (texture features, wi, wo)."""
    base: int = 0
    """Texels per side of the finest level of the base maps' pyramid (the material's maps' resolution; a
    power of two), 0: none. With a base the answer is base(maps, wi, wo) * exp(c) + a, with c and a the
    decoder's 6 outputs (`BASE_OUTPUTS`): the classical material as a start that the decoder corrects
    (training/model/base.py has the formula and the pyramid's channels)."""
    terminator: str = "all"
    """Which of the base's terms the shadow terminator's softening S(g) of a normal map (Chiang, Li and Burley 2019;
    training/model/base.py) multiplies: "all", "specular" or "none". S(g) bounds a bump's side facing a
    grazing light near its flat value; without it the base's only shadow is its horizon visibility. Needs a
    base."""
    local_frame: bool = False
    """The decoder also reads wi and wo in the shading frame of the base's normal (the base maps' mean slopes where
    the lookups land): 6 inputs (`DECODER_INPUTS`). A normal tilted by the texel's slopes is then a rotation of
    the inputs, not something every texel's features must teach the decoder. Needs a base."""
    visibility_input: bool = False
    """The decoder also reads the base's visibility V(wi) of each light (`base.light_visibility`: the horizon test at the
    maps' resolution where the lookups land), so that its correction, whose features are the latents' (coarser than
    the maps), can tell a lit facet from a shadowed one. Needs a base."""
    relief: int = 0
    """Texels per side of the finest level of the height pyramid the relief stage marches (the material's
    height map's resolution; a power of two), 0: none. With it, every lookup reads where the view ray
    first meets the height field, prefiltered at the query's footprint (`training/model/relief.py`), and the
    learned offset (if any) corrects from there."""
    relief_steps: int = 8
    """Linear-search steps of the relief stage (each one height lookup), refined by one secant step."""
    base_energy: bool = False
    """The base's coarse levels keep their finest texels' energy: each coarse texel's colours and F0 are scaled so
    that its answer, summed over fixed random direction pairs, is the mean of the finest texels' it covers
    (`training.model.base.keep_energy`; a prefiltered glossy lobe - mean slopes, LEAN widening, mean horizons -
    loses up to a third of it on turtle). Only how the base maps are computed: the graph is the same. The estimate
    uses `ENERGY_PAIRS` pairs per finest texel: too few for a near-mirror lobe (roughness 0.15). Needs a base."""
    half_textures: bool = False
    """Store the latent pyramid, the offset texture, the base's maps and the relief's heights in float16 (half a
    map-informed file; a height of a relief 0.12 tile deep moves by at most 3e-5 tile, 0.8 % of a 256^2 texel). The
    model reads its textures rounded to float16 in training too (the rounding's gradient passes straight through),
    so the file, torch and every engine answer one model. False: float32, as files before it."""
    lod_bias: int = 0
    """Levels by which a footprint's level of detail is raised: level = clamp(log2(sigma R) + lod_bias, 0, log2 R),
    for every pyramid of the model (the latents', the base maps', the relief's heights). 0 is the paper's
    convention (a footprint of one texel's std, and every sharper one, reads the finest level); with 2, level L
    answers a box of about 2^L texels (a Gaussian of std s weighs about as a box sqrt(12) s ~ 2^1.8 s wide) and
    the finest level the footprints of a quarter texel and less. The data must then hold footprints that fine
    (`QuerySampling.sub_texel_levels`; `neumip fit` generates them)."""
    ceiling: float = 0.0
    """The largest answer (every channel), 0: none. A trainer sets it to its data's largest target
    (`train.data_ceiling`): each target is an unbiased estimate of an answer, so an answer above all of them is
    the model's extrapolation, not the material's, and renders as fireflies. Training's loss reads the answers
    unclamped, so that a query above the ceiling still learns."""
    energy_bins: int = 0
    """Bins of each direction axis of the answers' energy table, 0: none. The answer is multiplied by a gain
    interpolated (linearly) from a table over the levels of detail, `energy_bins` bins of the half vector's angle from
    the normal and `energy_bins` bins of the light's elevation: the mean of the data's targets over the mean of the
    model's answers in each cell, fitted after training (`training.model.energy`). A log loss (comb2) settles below a
    noisy target's mean, most where the coarse footprints' glints and grazing lights make the targets noisiest; the
    table gives back that energy from thousands of queries per cell, where a per-query unbiased loss chases each
    target's noise. Needs the relu head."""
    energy_azimuths: int = 0
    """Bins of the half vector's azimuth in the tile's frame as the energy table's fourth axis (periodic), 0: none.
    A coarse texel of an anisotropic material (grooves, a tile's plates) answers darker along some azimuths and
    brighter along others; the 3-axis table pools them, so its gain is right on average and wrong along the axis a
    view happens to look (experiments/energy). The cells nearest the normal (the half vector's first angle bin) are
    one gain for every azimuth, so the gain stays continuous where the azimuth is undefined. Needs `energy_bins`."""
    energy_luminance: bool = False
    """One gain a cell of the energy table for the three channels (the ratio of the luminances' sums) instead of one
    a channel: a third of the table's values read a light (three lights a shading point, each reading its own 16
    cells; benchmarks/README.md: since the kernel reads a cell's row whole, the table costs a render little either
    way). Needs `energy_bins`."""
    coarse_decoder: int = 0
    """The level of detail K from which a second decoder, of the same shape and inputs, answers; 0: one decoder for
    every level. The answer is the first decoder's output blended into the second's by w = clamp(lod - K, 0, 1) (lod
    the latents' level of detail, `lod_bias` included): level K and finer read the first alone, K + 1 and coarser
    the second alone. The coarse footprints' queries are a small share of the data, and their answers change with
    the azimuth where a shared decoder answers as the fine levels taught it (experiments/energy: a second decoder
    trained on them cut turtle's error by azimuth to 0.65x, the finer levels untouched)."""
    head: str = "relu"
    """Decoder output head (core/head.py): "relu" (paper: RGB = max(out, 0)) or "yuv" (authors'
    code: exp(YUV) - 1 times a shadow mask 0.1 + sigmoid, 6 outputs)."""

    def __post_init__(self) -> None:
        if self.resolution < 1 or self.resolution & (self.resolution - 1):
            raise ValueError(f"resolution must be a power of two, got {self.resolution}")
        for name in ("channels", "hidden", "offset_channels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.layers < 1:
            raise ValueError(f"layers must be >= 1, got {self.layers}")
        if self.head not in HEADS:
            raise ValueError(f"head must be one of {HEADS}, got {self.head!r}")
        if self.base < 0 or self.base & (self.base - 1):
            raise ValueError(f"base must be 0 or a power of two, got {self.base}")
        if self.base_energy and not self.base:
            raise ValueError("base_energy needs a base (MaterialConfig.base)")
        if self.base and self.head != "relu":
            raise ValueError(f"a base works with the relu head only, got head {self.head!r}")
        if self.terminator not in TERMINATORS:
            raise ValueError(f"terminator must be one of {TERMINATORS}, got {self.terminator!r}")
        if self.terminator != "all" and not self.base:
            raise ValueError("terminator softens the base's terms: it needs a base")
        for row in DECODER_INPUTS:
            if row.reads_base and getattr(self, row.switch) and not self.base:
                raise ValueError(f"{row.switch} reads the base's maps: it needs a base")
        if self.relief < 0 or self.relief & (self.relief - 1):
            raise ValueError(f"relief must be 0 or a power of two, got {self.relief}")
        if self.relief_steps < 1:
            raise ValueError(f"relief_steps must be >= 1, got {self.relief_steps}")
        if not (self.ceiling >= 0 and math.isfinite(self.ceiling)):
            raise ValueError(f"ceiling must be 0 (none) or a finite positive answer, got {self.ceiling}")
        if not (isinstance(self.lod_bias, int) and 0 <= self.lod_bias <= 8):
            raise ValueError(f"lod_bias must be a whole number of levels in [0, 8], got {self.lod_bias!r}")
        if self.energy_bins < 0 or self.energy_bins == 1 or (self.energy_bins and self.head != "relu"):
            raise ValueError(f"energy_bins must be 0 (none) or at least 2, with the relu head, got {self.energy_bins} "
                             f"with head {self.head!r}")
        if self.energy_azimuths < 0 or self.energy_azimuths == 1 or (self.energy_azimuths and not self.energy_bins):
            raise ValueError(f"energy_azimuths must be 0 (none) or at least 2, with energy_bins, got "
                             f"{self.energy_azimuths} with energy_bins {self.energy_bins}")
        if self.energy_luminance and not self.energy_bins:
            raise ValueError("energy_luminance needs an energy table (energy_bins)")
        if not (isinstance(self.coarse_decoder, int) and (self.coarse_decoder == 0 or 0 < self.coarse_decoder < self.levels)):
            raise ValueError(f"coarse_decoder must be 0 (one decoder) or a level of detail below the coarsest "
                             f"({self.levels}), got {self.coarse_decoder!r}")
        if not 0 < self.offset_min_cos <= 1:
            raise ValueError(f"offset_min_cos must be in (0, 1], got {self.offset_min_cos}")

    def decoder_inputs(self) -> tuple[DecoderInput, ...]:
        """The rows of `DECODER_INPUTS` this material's decoder reads, in their order."""
        return tuple(row for row in DECODER_INPUTS if getattr(self, row.switch))

    @property
    def levels(self) -> int:
        """Index of the coarsest (1 x 1) level: log2(resolution)."""
        return int(math.log2(self.resolution))

    def level_sizes(self) -> list[int]:
        """Texels per side of each level, finest (level 0) first."""
        return [self.resolution >> level for level in range(self.levels + 1)]

    def level_starts(self) -> list[int]:
        """Row of each level's first texel in the flat texture atlas (levels stacked finest first)."""
        starts, total = [], 0
        for size in self.level_sizes():
            starts.append(total)
            total += size * size
        return starts

    def atlas_rows(self) -> int:
        """Texels in all levels together."""
        return sum(s * s for s in self.level_sizes())

    def base_pyramid(self) -> "MaterialConfig | None":
        """The base maps' pyramid as a config of its own: its resolution and channels, the material's `lod_bias` and
        `half_textures` (as the next two); None without a base."""
        return MaterialConfig(resolution=self.base, channels=BASE_CHANNELS, offset=False,
                              lod_bias=self.lod_bias, half_textures=self.half_textures) if self.base else None

    def relief_pyramid(self) -> "MaterialConfig | None":
        """The relief's height pyramid as a config of its own (one channel), or None without a relief."""
        return MaterialConfig(resolution=self.relief, channels=1, offset=False,
                              lod_bias=self.lod_bias, half_textures=self.half_textures) if self.relief else None

    def offset_pyramid(self) -> "MaterialConfig | None":
        """The neural offset texture's mip pyramid as a config of its own (`offset_mip`), or None without it."""
        if not (self.offset and self.offset_mip):
            return None
        return MaterialConfig(resolution=self.resolution, channels=self.offset_channels, offset=False,
                              lod_bias=self.lod_bias, half_textures=self.half_textures)

    def pyramid_finest_level(self, pyramid: "MaterialConfig", finest_level: int) -> int:
        """The finest level of `pyramid` (`base_pyramid`, `relief_pyramid`, `offset_pyramid`, or this config's own) read
        by a query whose latent level is at least K = ``finest_level`` (what a model trimmed to K keeps of it):
        `same_footprint_level`."""
        return same_footprint_level(self.levels, pyramid.levels, finest_level)

    def to_json(self) -> str:
        """The fields as JSON; each decoder input's switch, `base`, the relief's, `lod_bias`, `offset_mip`, `energy_bins`,
        `energy_azimuths`, `energy_luminance`, `coarse_decoder` and `ceiling` only when on, and `terminator` only when not "all", so that models made before each existed read as they did."""
        fields_ = asdict(self)
        for row in DECODER_INPUTS:
            if not getattr(self, row.switch):
                del fields_[row.switch]
        if not self.base:
            del fields_["base"]
        if self.terminator == "all":
            del fields_["terminator"]
        if not self.relief:
            del fields_["relief"], fields_["relief_steps"]
        if not self.ceiling:
            del fields_["ceiling"]
        if not self.lod_bias:
            del fields_["lod_bias"]
        if not (self.offset and self.offset_mip):
            del fields_["offset_mip"]
        if not self.energy_bins:
            del fields_["energy_bins"]
        if not self.energy_azimuths:
            del fields_["energy_azimuths"]
        if not self.energy_luminance:
            del fields_["energy_luminance"]
        if not self.coarse_decoder:
            del fields_["coarse_decoder"]
        return json.dumps(fields_, sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict) -> "MaterialConfig":
        return dataclass_from_dict(cls, data)

    @classmethod
    def from_json(cls, text: str) -> "MaterialConfig":
        return cls.from_dict(json.loads(text))
