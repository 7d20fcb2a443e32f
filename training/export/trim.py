"""`neumip trim`: an exported model without its pyramid levels finer than K.

Trimming reads the model's weights back (`read.read_model`) and writes the graph again with ``finest_level``
K (`graph.build_onnx`): every pyramid the model reads is cut at the level of the same footprint (`lod.pyramids`:
the latents, the base maps' ``base_maps``, the relief's ``relief_heights``, the offset's mip pyramid; each one's
level of detail is relative to its own resolution, so a pyramid finer than the latents keeps log2 of the ratio
levels more of its own, `MaterialConfig.pyramid_finest_level`):

- each atlas keeps the texels of its levels K_p..L_p (the offset's mip pyramid stores only its finest kept level; the
  graph derives the coarser ones when it loads, as it does untrimmed);
- the vectors its quad index table is computed from (``quad.*``, ``base.quad.*``, ``relief.quad.*``,
  `lookup.quad_vectors`) and the per-level tables its level of detail reads (``lod.*``, ``base.lod.*``,
  ``relief.lod.*``, `lod.level_of_detail`) become those of the shorter atlas (`lookup.trimmed_atlas`: only
  the table rows move, each level's size and row width stay; levels finer than K_p have no quad rows, and
  their level-of-detail rows repeat K_p's);
- its level-of-detail Clip's lower bound becomes 2^K_p (`lod.clip_min`).

So every query whose level ``clamp(log2(sigma R) + lod_bias, 0, L)`` is >= K gathers the same texels with
the same weights through the same ops in every pyramid: its answer is bit-identical to the untrimmed
model's. A finer query reads level K_p alone (as a query finer than level 0 reads level 0 in an untrimmed
model). The neural offset is cut as a pyramid where the model reads its mip pyramid (`MaterialConfig.offset_mip`);
the paper's single-level offset texture is kept whole: every query reads it bilinearly at the finest resolution,
whatever its footprint, so any reduction of it changes every answer of such a model.

Before anything is cut, the weights read back are written again at the model's own level, and that graph must be
the model's, byte for byte: a graph of another layout is refused, never mis-edited.
The trimmed model's metadata keeps the config (levels are still numbered from the full resolution)
and adds ``neumip.trim``: the finest latent level kept (the maps' follow from it), the latent levels
and bytes cut.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import onnx

from neumip.core import contract as C
from neumip.core.config import MaterialConfig
from neumip.core.errors import NeumipError
from neumip.core.modelfile import TrimRecord, read_model_file

from neumip.training.export.base import BASE_VARYING, base_layout
from neumip.training.export.graph import RELIEF_DEPTH, build_onnx, relief_depth, save_onnx
from neumip.training.export.lod import pyramids
from neumip.training.export.read import ModelLayoutError, model_file, read_model

__all__ = ["TrimError", "TrimRecord", "current_trim", "finest_level_from_budget", "trim_file", "trim_model",
           "trimmed_weights"]

log = logging.getLogger(__name__)


class TrimError(NeumipError, ValueError):
    """A model that cannot be trimmed as asked (a graph of another layout, or a level it does not have);
    a file the model-file reader refuses (not a neumip material, another contract version...) raises
    its `ModelError`."""


NEEDS_CONFIG = "neumip trim needs the model's config (its pyramid's levels)"
"""What `ModelFile.require_config` says needs it here."""


def current_trim(model: onnx.ModelProto) -> TrimRecord | None:
    """The model's ``neumip.trim`` record (None: never trimmed)."""
    return model_file(model).trim


def trim_model(model: onnx.ModelProto, finest_level: int, source: str = "model.onnx") -> onnx.ModelProto:
    """A copy of exported `model` holding latent pyramid levels ``finest_level``..L only, and every other
    pyramid from the level of the same footprint on (see the module); `source`: its file's path, as errors
    name it."""
    file = model_file(model, source)
    config, before = file.require_config(NEEDS_CONFIG), file.trim
    old = before.finest_level if before else 0
    if not old <= finest_level <= config.levels:
        raise TrimError(f"finest level must be in [{old}, {config.levels}] for this model, got {finest_level}")
    out = onnx.ModelProto()
    out.CopyFrom(model)
    if finest_level == old:  # nothing to cut: the same model, bit for bit
        return out
    try:
        config, weights, metadata, _ = read_model(model, source)
    except ModelLayoutError as exc:
        raise TrimError(f"{exc}; cannot trim this graph") from exc
    rest = {k: v for k, v in metadata.items() if k not in (C.META_CONTRACT, C.META_CONFIG, C.META_DESCRIPTION)}
    description = metadata.get(C.META_DESCRIPTION, "")
    if build_onnx(config, weights, description, rest, old).graph.SerializeToString() != model.graph.SerializeToString():
        raise TrimError(f"{source}: its graph is not what this export writes for its weights (an older export's "
                        f"file: `neumip export OLD.onnx -o NEW.onnx` rewrites it with this version's graph); cannot "
                        f"trim this graph")
    sizes, starts = config.level_sizes(), config.level_starts()
    record = TrimRecord(
        finest_level=finest_level,
        finest_resolution=sizes[finest_level],
        levels_cut=sizes[:finest_level],
        texels_cut=starts[finest_level],
        bytes_before=before.bytes_before if before else model.ByteSize(),
    )
    return build_onnx(config, trimmed_weights(config, weights, finest_level, old), description,
                      {**rest, C.META_TRIM: record.to_json()}, finest_level)


def trimmed_weights(config: MaterialConfig, weights: dict[str, np.ndarray], finest_level: int,
                    held: int = 0) -> dict[str, np.ndarray]:
    """`weights` (`export.weights_from_state`) of a model holding latent levels `held`..L (0: untrimmed) -> those
    `export.build_onnx` takes with ``finest_level``: every pyramid's atlas from its level of the same footprint on
    (`MaterialConfig.pyramid_finest_level`)."""
    out = dict(weights)
    if config.relief:  # the depth of all the heights, which the kept levels may not reach
        out[RELIEF_DEPTH] = np.full((1, 1), relief_depth(weights, config), np.float32)
    if config.base:  # the channels that vary in all the levels: a coarse level alone may hold fewer
        out[BASE_VARYING] = np.asarray(base_layout(weights, config)[0], np.int64)
    for pyramid in pyramids(config):
        starts = pyramid.config.level_starts()
        first, level = (config.pyramid_finest_level(pyramid.config, k) for k in (held, finest_level))
        out[pyramid.texture] = weights[pyramid.texture][starts[level] - starts[first]:]
    return out


def finest_level_from_budget(budget: dict, material: str) -> int:
    """The finest level that matters for `material` in a `neumip budget --json` output."""
    for entry in budget.get("materials", []):
        if entry.get("material") == material:
            return int(entry["finest_level"])
    names = ", ".join(e.get("material", "?") for e in budget.get("materials", [])) or "none"
    raise TrimError(f"the budget has no material {material!r} (it has: {names})")


def trim_file(model_path: str | Path, out: str | Path, finest_level: int) -> TrimRecord:
    """Trim the model file at `model_path` to `finest_level`, written atomically to `out`."""
    data = Path(model_path).read_bytes()
    read_model_file(model_path, data)  # ModelError, naming the file, for one it cannot read
    trimmed = trim_model(onnx.load_model_from_string(data), finest_level, str(model_path))
    save_onnx(trimmed, out)
    return current_trim(trimmed)
