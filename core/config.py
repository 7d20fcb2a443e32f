"""Model configuration: the architecture of one neural material, shared by training and export.

Kept free of torch so that export, the server and tests can read it anywhere.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields

from .head import HEADS


def dataclass_from_dict(cls, data: dict):
    """Build dataclass `cls` from `data`, refusing keys that are not its fields (typos in files)."""
    unknown = set(data) - {f.name for f in fields(cls)}
    if unknown:
        raise ValueError(f"unknown {cls.__name__} fields: {sorted(unknown)}")
    return cls(**data)


HALF_FLOOR = 1e-12
"""|wi + wo|^2 is clamped to at least this before the half vector is normalised (`MaterialConfig.half_vector`)."""


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
    offset_scale: float = 0.1
    """Ray depth r = offset_scale * MLP output (author code: 0.1)."""
    offset_min_cos: float = 0.6
    """wo_z is clamped to at least this in offset = r * wo_xy / wo_z (grazing-angle stability; the
    authors' 0.6). 0.3 was measured in images: within the training-seed spread alone, better only
    together with 48-wide MLPs (benchmarks/results/quality_levers_log.md, "Quality levers")."""
    half_vector: bool = False
    """The decoder also reads, per light, the half vector h = normalize(wi + wo) and cos(theta_d) =
    h . wi (the half and difference angles of Rusinkiewicz's parametrisation: a glossy lobe is simple
    in them); off: the paper's decoder, on (texture features, wi, wo)."""
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
        if not 0 < self.offset_min_cos <= 1:
            raise ValueError(f"offset_min_cos must be in (0, 1], got {self.offset_min_cos}")

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

    def to_json(self) -> str:
        """The fields as JSON; `half_vector` only when on, so the paper's models read as before it existed."""
        fields_ = asdict(self)
        if not self.half_vector:
            del fields_["half_vector"]
        return json.dumps(fields_, sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict) -> "MaterialConfig":
        return dataclass_from_dict(cls, data)

    @classmethod
    def from_json(cls, text: str) -> "MaterialConfig":
        return cls.from_dict(json.loads(text))
