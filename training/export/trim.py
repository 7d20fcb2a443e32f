"""`neumip trim`: an exported model without its pyramid levels finer than K.

Shipped models are ONNX files only, so trimming edits the exported graph in place rather than
re-exporting: it swaps constants and changes nothing else (no node, no other weight):

- the ``pyramid`` atlas keeps the texels of levels K..L (`config.level_starts()[K]` on);
- its quad index table and the per-level tables the level of detail reads (initializers ``lod.*``,
  `export_lod.stage_constants`) become those of the shorter atlas (`export_lookup.trimmed_atlas`:
  only the table rows move, each level's size and row width stay; levels finer than K repeat K's);
- the level-of-detail Clip's lower bound becomes 2^K (`export_lod.clip_min`).

So every query whose level ``clamp(log2(sigma R), 0, L)`` is >= K gathers the same texels with the
same weights through the same ops: its answer is bit-identical to the untrimmed model's. A finer query
reads level K alone (as a query finer than level 0 reads level 0 in an untrimmed model). The neural
offset texture is kept whole: it is read bilinearly at the finest resolution by every query,
whatever its footprint, so any reduction of it changes every answer of an offset model.

Each constant found is first checked against what the writer (`export_lookup`, `export_lod`) writes
for the model's config and current trim, so a graph of another layout is refused, never mis-edited.
The trimmed model's metadata keeps the config (levels are still numbered from the full resolution)
and adds ``neumip.trim``: the finest level kept, the levels and bytes cut.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.config import MaterialConfig
from neumip.core.errors import NeumipError
from neumip.core.modelfile import TrimRecord, read_model_file

from neumip.training.export.graph import save_onnx
from neumip.training.export.lod import clip_min, clip_node, stage_constants
from neumip.training.export.lookup import level_tables, texture_constants, trimmed_atlas
from neumip.training.export.read import model_file

__all__ = ["TrimError", "TrimRecord", "current_trim", "finest_level_from_budget", "trim_file", "trim_model"]

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
        raise TrimError(f"no initializer {name!r}: not a graph of this export; cannot trim this graph")
    current = numpy_helper.to_array(init)
    if current.shape != expected.shape or not np.array_equal(current, expected.astype(current.dtype)):
        raise TrimError(f"initializer {name!r} is not what this export writes; cannot trim this graph")
    init.CopyFrom(numpy_helper.from_array(value.astype(current.dtype), name))


def trim_model(model: onnx.ModelProto, finest_level: int, source: str = "model.onnx") -> onnx.ModelProto:
    """A copy of exported `model` holding pyramid levels ``finest_level``..L only (see the module);
    `source`: its file's path, as errors name it."""
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
    found = texture_constants(g, W.PYRAMID)
    _replace(g, found["quads"], trimmed_atlas(config, old)[0].rows, trimmed_atlas(config, finest_level)[0].rows)
    old_lod, new_lod = (stage_constants(config, k, level_tables(config, k)) for k in (old, finest_level))
    for name, value in new_lod.items():
        _replace(g, name, old_lod[name], value)
    _replace(g, clip_node(g, config).input[1], np.asarray(clip_min(old), np.float32),
             np.asarray(clip_min(finest_level), np.float32))
    starts = config.level_starts() + [config.atlas_rows()]
    expected = (starts[-1] - starts[old], config.channels)
    pyramid = next(i for i in g.initializer if i.name == W.PYRAMID)
    atlas = numpy_helper.to_array(pyramid)
    if atlas.shape != expected:
        raise TrimError(f"pyramid atlas of shape {atlas.shape}, expected {expected}")
    kept = np.ascontiguousarray(atlas[starts[finest_level] - starts[old]:])
    pyramid.CopyFrom(numpy_helper.from_array(kept, W.PYRAMID))

    sizes = config.level_sizes()
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
