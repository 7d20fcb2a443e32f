"""The inverse of `export.build_onnx`: a material's weights read back from an exported model.

Shipped materials are ONNX files only (no checkpoint). Reading their weights back lets `neumip
export MODEL.onnx -o NEW.onnx` rewrite a model with this version's graph: same weights, same
metadata (config, description, validation, trim record), and - when the graphs compute the same
function in the same float order - the same answer bits (query groups changed the order of the
decoder's first sum: models from before them change by rounding)
(`reexport_file` checks that on random queries and reports the largest difference).

What the graph keeps, by initializer name (the writer is `export.py`; matrices are stored halved,
`onnx_graph.GraphWriter.product`, and doubled back here, exact):

- the textures: ``pyramid`` (levels K..L of a trimmed model) and ``offset_texture``;
- every layer but the first of each MLP: ``{prefix}.{i}.half_weight`` (out, in) and ``.bias``
  (out, 1); the first layer's bias ``{prefix}.0.bias``, its weights on the texture features
  ``{prefix}.0.half_weight.texture`` (hidden, C) and on the query ``{prefix}.0.half_weight.query``
  (hidden, 7: the columns it reads, zeros elsewhere); the decoder's weights on a light's wi are
  ``decoder.0.half_weight.light`` (hidden, 2) (models written before query groups hold them in the
  query matrix);
- the offset MLP's last layer is stored folded (`export._depth_weights`: its one output repeated
  twice, times ``offset_scale``); it is unfolded to weights that fold to the same bits.

Models written before issue 12's graph (row-major MLPs: ``{prefix}.{i}.weight`` (out, in) and
``.bias`` (out,), the first layer split over a query Gemm and a texture Gemm) are read too
(`_previous_layer`), so `neumip export OLD.onnx` brings them to this layout.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from neumip.core import contract as C

from neumip.core.config import MaterialConfig
from .export import _depth_weights, build_onnx, save_onnx
from .onnx_graph import COLUMN_ALPHA

QUERY_COLUMNS = {"decoder": [C.WI_X, C.WI_Y, C.WO_X, C.WO_Y], "offset_mlp": [C.WO_X, C.WO_Y]}
"""The query columns each MLP's first layer reads after the texture features (`export.material_graph`)."""


class ModelLayoutError(ValueError):
    """A model whose graph is not one `export.build_onnx` wrote (its weights cannot be read back)."""


def _initializers(model: onnx.ModelProto) -> dict[str, np.ndarray]:
    return {init.name: numpy_helper.to_array(init) for init in model.graph.initializer}


def _layer(inits: dict, prefix: str, i: int, columns: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Layer i of MLP `prefix`: weights (out, in), bias (out,)."""
    if i > 0:
        weight = inits[f"{prefix}.{i}.half_weight"] * np.float32(COLUMN_ALPHA)
    else:
        texture, query = (inits[f"{prefix}.0.half_weight.{part}"] * np.float32(COLUMN_ALPHA)
                          for part in ("texture", "query"))
        light = inits.get(f"{prefix}.0.half_weight.light")  # absent before query groups
        if light is not None:
            query = query.copy()
            query[:, [C.WI_X, C.WI_Y]] = light * np.float32(COLUMN_ALPHA)
        weight = np.concatenate([texture, query[:, columns]], axis=1)
    bias = inits[f"{prefix}.{i}.bias"]
    if bias.shape != (weight.shape[0], 1):
        raise ModelLayoutError(f"{prefix}.{i}.bias of shape {bias.shape}, expected ({weight.shape[0]}, 1)")
    return weight, bias[:, 0]


def _previous_layer(model: onnx.ModelProto, inits: dict, prefix: str, i: int,
                    columns: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Layer i of MLP `prefix` in the layout before issue 12: weights (out, in), bias (out,). The first
    layer is two Gemms: the query's (7, hidden) rows, whose output is the texture Gemm's bias."""
    if i > 0:
        return inits[f"{prefix}.{i}.weight"], inits[f"{prefix}.{i}.bias"]
    gemms = [n for n in model.graph.node if n.op_type == "Gemm"]
    query = [n for n in gemms if n.input[0] == C.ONNX_INPUT and list(n.input[2:]) == [f"{prefix}.0.bias"]]
    texture = [n for n in gemms if query and list(n.input[2:]) == [query[0].output[0]]]
    if len(query) != 1 or len(texture) != 1:
        raise ModelLayoutError(f"{prefix}.0: not the two Gemms of an older export")
    rows, w_tex = inits[query[0].input[1]], inits[texture[0].input[1]]  # (7, hidden), (C, hidden)
    return np.concatenate([w_tex.T, rows[columns].T], axis=1), inits[f"{prefix}.0.bias"]


def _unfold_depth(folded: dict, config: MaterialConfig) -> dict:
    """The offset MLP's last layer as stored (2 rows, times offset_scale) -> weights of one output
    that `export._depth_weights` folds to the same bits (of the float32 neighbours of w / scale)."""
    last = f"offset_mlp.{config.layers - 1}"
    out = dict(folded)
    for part in ("weight", "bias"):
        stored = folded[f"{last}.{part}"]
        if not np.array_equal(stored[0], stored[1]):
            raise ModelLayoutError(f"{last}.{part}: the depth's two rows differ")
        guess = (stored[:1] / np.float32(config.offset_scale)).astype(np.float32)
        found = np.full(guess.shape, np.nan, np.float32)
        for candidate in (guess, np.nextafter(guess, np.float32(np.inf)), np.nextafter(guess, np.float32(-np.inf))):
            refold = _depth_weights({**out, f"{last}.{part}": candidate}, config)[f"{last}.{part}"][0]
            found = np.where(np.isnan(found) & (refold == stored[0]), candidate, found)
        if np.isnan(found).any():
            raise ModelLayoutError(f"{last}.{part}: no weights fold to the stored ones")
        out[f"{last}.{part}"] = found
    return out


def read_model(model: onnx.ModelProto) -> tuple[MaterialConfig, dict[str, np.ndarray], dict[str, str], int]:
    """Exported `model` -> (config, weights as `export.weights_from_state` gives them, its metadata,
    its finest level K: 0 unless trimmed)."""
    meta = {p.key: p.value for p in model.metadata_props}
    if meta.get(C.META_CONTRACT) != C.CONTRACT_VERSION or C.META_CONFIG not in meta:
        raise ModelLayoutError("not a neumip material of this contract version (no neumip.config metadata)")
    config = MaterialConfig.from_json(meta[C.META_CONFIG])
    finest = json.loads(meta[C.META_TRIM])["finest_level"] if meta.get(C.META_TRIM) else 0
    inits = _initializers(model)
    textures = ["pyramid"] + (["offset_texture"] if config.offset else [])
    prefixes = ["decoder"] + (["offset_mlp"] if config.offset else [])
    previous = "decoder.0.half_weight.texture" not in inits  # the layout before issue 12
    try:
        weights = {name: inits[name] for name in textures}
        for prefix in prefixes:
            for i in range(config.layers):
                layer = (_previous_layer(model, inits, prefix, i, QUERY_COLUMNS[prefix]) if previous
                         else _layer(inits, prefix, i, QUERY_COLUMNS[prefix]))
                weights[f"{prefix}.{i}.weight"], weights[f"{prefix}.{i}.bias"] = layer
    except KeyError as exc:
        raise ModelLayoutError(f"no initializer {exc}: not a graph of this export or the one before") from exc
    if config.offset:
        weights = _unfold_depth(weights, config)
    return config, weights, meta, finest


def reexport(model: onnx.ModelProto) -> onnx.ModelProto:
    """`model` rewritten with this version's graph: its weights, config, finest level and metadata."""
    config, weights, meta, finest = read_model(model)
    owned = {C.META_CONTRACT, C.META_CONFIG, C.META_DESCRIPTION}
    extra = {key: value for key, value in meta.items() if key not in owned}
    return build_onnx(config, weights, meta.get(C.META_DESCRIPTION, ""), extra, finest)


CHECK_QUERIES = 65536
"""Random queries on which a rewritten model is compared with the file it came from."""


def answer_difference(old: onnx.ModelProto, new: onnx.ModelProto, n: int = CHECK_QUERIES,
                      seed: int = 0) -> float:
    """Largest |old - new| answer of the two models on `n` random queries (one thread)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.log_severity_level = 3
    q = C.random_queries(n, seed=seed)
    old_rgb, new_rgb = (ort.InferenceSession(m.SerializeToString(), opts, providers=["CPUExecutionProvider"])
                        .run(None, {C.ONNX_INPUT: q})[0] for m in (old, new))
    return float(np.abs(old_rgb - new_rgb).max())


def reexport_file(source: str | Path, out: str | Path, description: str = "") -> tuple[Path, float]:
    """`neumip export MODEL.onnx`: rewrite the model at `source` with this version's graph to `out`
    (atomically); returns the path and the largest answer difference on random queries."""
    old = onnx.load(str(source))
    new = reexport(old)
    if description:
        onnx.helper.set_model_props(new, {**{p.key: p.value for p in new.metadata_props},
                                          C.META_DESCRIPTION: description})
    return save_onnx(new, out), answer_difference(old, new)
