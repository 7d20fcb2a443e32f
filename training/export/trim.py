"""`neumip trim`: an exported model without its pyramid levels finer than K.

Shipped models are ONNX files only, so trimming edits the exported graph in place rather than
re-exporting: it swaps constants and changes no op. Every pyramid the model reads is cut at the level of
the same footprint (`lod.pyramids`: the latents, the base maps' ``base_maps``, the relief's
``relief_heights``, the offset's mip pyramid; each one's level of detail is relative to its own resolution, so a pyramid finer than
the latents keeps log2 of the ratio levels more of its own, `MaterialConfig.pyramid_finest_level`):

- each atlas keeps the texels of its levels K_p..L_p;
- the vectors its quad index table is computed from (``quad.*``, ``base.quad.*``, ``relief.quad.*``,
  `lookup.quad_vectors`) and the per-level tables its level of detail reads (``lod.*``, ``base.lod.*``,
  ``relief.lod.*``, `lod.stage_constants`) become those of the shorter atlas (`lookup.trimmed_atlas`: only
  the table rows move, each level's size and row width stay; levels finer than K_p have no quad rows, and
  their level-of-detail rows repeat K_p's);
- its level-of-detail Clip's lower bound becomes 2^K_p (`lod.clip_min`).

So every query whose level ``clamp(log2(sigma R) + lod_bias, 0, L)`` is >= K gathers the same texels with
the same weights through the same ops in every pyramid: its answer is bit-identical to the untrimmed
model's. A finer query reads level K_p alone (as a query finer than level 0 reads level 0 in an untrimmed
model). The neural offset is cut as a pyramid where the model reads its mip pyramid (`MaterialConfig.offset_mip`,
``offset_texture``, ``offset.lod.*``, ``offset.quad.*``); the paper's single-level offset texture is kept whole:
every query reads it bilinearly at the finest resolution, whatever its footprint, so any reduction of it changes
every answer of such a model.

Each constant found is first checked against what the writer (`lookup`, `lod`) writes
for the model's config and current trim, so a graph of another layout is refused, never mis-edited.
The trimmed model's metadata keeps the config (levels are still numbered from the full resolution)
and adds ``neumip.trim``: the finest latent level kept (the maps' follow from it), the latent levels
and bytes cut.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from neumip.core import contract as C
from neumip.core.config import MaterialConfig
from neumip.core.errors import NeumipError
from neumip.core.modelfile import TrimRecord, read_model_file

from neumip.training.export.graph import RELIEF_DEPTH, relief_depth, save_onnx
from neumip.training.export.lod import Pyramid, clip_min, clip_nodes, pyramids, stage_constants
from neumip.training.export.lookup import level_tables, quad_vectors
from neumip.training.export.read import model_file

__all__ = ["TrimError", "TrimRecord", "current_trim", "finest_level_from_budget", "trim_file", "trim_model",
           "trimmed_weights"]

log = logging.getLogger(__name__)


class TrimError(NeumipError, ValueError):
    """A model that cannot be trimmed as asked (a graph of another layout, or a level it does not have);
    a file the model-file reader refuses (not a neumip material, another contract version...) raises
    its `ModelError`."""


NEEDS_CONFIG = "neumip trim needs the model's config (its pyramid's levels)"
"""What `ModelFile.require_config` says needs it here."""


def model_config(model: onnx.ModelProto) -> MaterialConfig:
    return model_file(model).require_config(NEEDS_CONFIG)


def current_trim(model: onnx.ModelProto) -> TrimRecord | None:
    """The model's ``neumip.trim`` record (None: never trimmed)."""
    return model_file(model).trim


def _replace(graph, name: str, expected: np.ndarray, value: np.ndarray) -> None:
    """Swap initializer `name` for `value`, after checking it holds `expected` (the writer's layout)."""
    init = next((i for i in graph.initializer if i.name == name), None)
    if init is None:
        raise TrimError(f"no initializer {name!r}: not a graph of this export (an older export's file: `neumip "
                        f"export OLD.onnx -o NEW.onnx` rewrites it with this version's graph); cannot trim this graph")
    current = numpy_helper.to_array(init)
    if current.shape != expected.shape or not np.array_equal(current, expected.astype(current.dtype)):
        raise TrimError(f"initializer {name!r} is not what this export writes; cannot trim this graph")
    init.CopyFrom(numpy_helper.from_array(value.astype(current.dtype), name))


def _cut_atlas(graph, pyramid: Pyramid, old: int, new: int) -> None:
    """Initializer `pyramid.texture`, holding levels `old`..L of it, keeps levels `new`..L."""
    starts = pyramid.config.level_starts() + [pyramid.config.atlas_rows()]
    expected = (starts[-1] - starts[old], pyramid.config.channels)
    init = next((i for i in graph.initializer if i.name == pyramid.texture), None)
    atlas = numpy_helper.to_array(init) if init is not None else None
    if atlas is None or atlas.shape != expected:
        raise TrimError(f"{pyramid.texture} atlas of shape {None if atlas is None else atlas.shape}, expected {expected}")
    init.CopyFrom(numpy_helper.from_array(np.ascontiguousarray(atlas[starts[new] - starts[old]:]), pyramid.texture))


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
    g = out.graph
    try:
        clips = clip_nodes(g, config)
    except ValueError as exc:
        raise TrimError(f"{exc}; cannot trim this graph") from exc
    for pyramid, clip in zip(pyramids(config), clips):
        k_old, k_new = (config.pyramid_finest_level(pyramid.config, k) for k in (old, finest_level))
        if k_old == k_new:  # maps coarser than level K's footprint: none of their levels is finer
            continue
        old_lod, new_lod = (stage_constants(pyramid.config, k, level_tables(pyramid.config, k)) for k in (k_old, k_new))
        for name, value in new_lod.items():
            _replace(g, pyramid.prefix + name, old_lod[name], value)
        old_quad, new_quad = (quad_vectors(pyramid.config.level_sizes(), k, pyramid.prefix) for k in (k_old, k_new))
        for name, value in new_quad.items():
            _replace(g, name, old_quad[name], value)
        _replace(g, clip.input[1], np.asarray(clip_min(k_old), np.float32), np.asarray(clip_min(k_new), np.float32))
        _cut_atlas(g, pyramid, k_old, k_new)

    sizes, starts = config.level_sizes(), config.level_starts()
    record = TrimRecord(
        finest_level=finest_level,
        finest_resolution=sizes[finest_level],
        levels_cut=sizes[:finest_level],
        texels_cut=starts[finest_level],
        bytes_before=before.bytes_before if before else model.ByteSize(),
    )
    props = {**file.metadata, C.META_TRIM: record.to_json()}
    onnx.helper.set_model_props(out, props)
    onnx.checker.check_model(out, full_check=True)
    return out


def trimmed_weights(config: MaterialConfig, weights: dict[str, np.ndarray], finest_level: int) -> dict[str, np.ndarray]:
    """Untrimmed `weights` (`export.weights_from_state`) -> those `export.build_onnx` takes with ``finest_level``:
    every pyramid's atlas from its level of the same footprint on (`MaterialConfig.pyramid_finest_level`)."""
    out = dict(weights)
    if config.relief:  # the depth of all the heights, which the kept levels may not reach
        out[RELIEF_DEPTH] = np.full((1, 1), relief_depth(weights), np.float32)
    for pyramid in pyramids(config):
        level = config.pyramid_finest_level(pyramid.config, finest_level)
        out[pyramid.texture] = weights[pyramid.texture][pyramid.config.level_starts()[level]:]
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
