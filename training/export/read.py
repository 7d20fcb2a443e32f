"""The inverse of `export.build_onnx`: a material's weights read back from an exported model.

Shipped materials are ONNX files only (no checkpoint). Reading their weights back lets `neumip
export MODEL.onnx -o NEW.onnx` rewrite a model with this version's graph: same weights, same
metadata (config, description, validation, trim record), and - when the graphs compute the same
function in the same float order - the same answer bits (`reexport_file` checks that on random
queries and reports the largest difference). A file of query contract version 1 is read by
`upgrade.read_v1` instead and comes out in this version (`neumip.core.contract.version_problem`).

The graph's initializers and their shapes are `neumip.core.weights.initializer_shapes`; each is
checked, so a file this export did not write is refused by name, never guessed at. Matrices are
stored halved (`onnx_graph.GraphWriter.product`) and doubled back here, exact; a first layer is put
back together from its parts (texture, query, light columns); the offset MLP's last layer is stored
folded (`export._depth_weights`) and unfolded to weights that fold to the same bits.
"""

from __future__ import annotations

import json

import numpy as np
import onnx
from onnx import numpy_helper

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.config import DECODER_INPUTS, MaterialConfig
from neumip.core.errors import NeumipError

from neumip.training.export.graph import _depth_weights
from neumip.training.export.onnx_graph import COLUMN_ALPHA


class ModelLayoutError(NeumipError, ValueError):
    """A model whose graph is not one `export.build_onnx` wrote (its weights cannot be read back)."""


def initializers(model: onnx.ModelProto) -> dict[str, np.ndarray]:
    """Every initializer of `model` by name."""
    return {init.name: numpy_helper.to_array(init) for init in model.graph.initializer}


def metadata(model: onnx.ModelProto) -> dict[str, str]:
    """The model's ONNX metadata."""
    return {p.key: p.value for p in model.metadata_props}


def model_facts(meta: dict[str, str]) -> tuple[MaterialConfig, int]:
    """(config, finest level: 0 unless trimmed) from a model's metadata; ModelLayoutError without a config."""
    if C.META_CONFIG not in meta:
        raise ModelLayoutError(f"not a neumip material (no {C.META_CONFIG} in its ONNX metadata)")
    finest = json.loads(meta[C.META_TRIM])["finest_level"] if meta.get(C.META_TRIM) else 0
    return MaterialConfig.from_json(meta[C.META_CONFIG]), finest


def check_shapes(inits: dict[str, np.ndarray], want: dict[str, tuple[int, ...]]) -> None:
    """ModelLayoutError naming the first initializer of `want` that `inits` lacks or holds in another shape."""
    for name, shape in want.items():
        if name not in inits:
            raise ModelLayoutError(f"no initializer {name!r}: not a graph of this export")
        if inits[name].shape != shape:
            raise ModelLayoutError(f"initializer {name!r} of shape {inits[name].shape}, this export writes {shape}")


def _layer(inits: dict, mlp: str, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Layer i of MLP `mlp` as stored -> weights (out, in), bias (out,)."""
    alpha = np.float32(COLUMN_ALPHA)
    if i > 0:
        weight = inits[W.half_weight(mlp, i)] * alpha
    else:
        query = inits[W.half_weight(mlp, 0, "query")] * alpha  # (hidden, 7): the columns it reads
        if mlp == W.DECODER:
            query[:, [C.WI_X, C.WI_Y]] = inits[W.half_weight(mlp, 0, "light")] * alpha
        texture = [inits[W.half_weight(mlp, 0, "texture")] * alpha]
        for row in DECODER_INPUTS:  # the decoder's optional inputs, in their order
            if W.half_weight(mlp, 0, row.name) in inits:
                texture.append(inits[W.half_weight(mlp, 0, row.name)] * alpha)
        weight = np.concatenate([*texture, query[:, list(W.MLP_QUERY_COLUMNS[mlp])]], axis=1)
    return weight, inits[W.bias(mlp, i)][:, 0]


def unfold_depth(folded: dict, config: MaterialConfig) -> dict:
    """The offset MLP's last layer as stored (2 rows, times offset_scale) -> weights of one output
    that `export._depth_weights` folds to the same bits (of the float32 neighbours of w / scale)."""
    out = dict(folded)
    for name in (W.weight(W.OFFSET_MLP, config.layers - 1), W.bias(W.OFFSET_MLP, config.layers - 1)):
        stored = folded[name]
        if not np.array_equal(stored[0], stored[1]):
            raise ModelLayoutError(f"{name}: the depth's two rows differ")
        guess = (stored[:1] / np.float32(config.offset_scale)).astype(np.float32)
        found = np.full(guess.shape, np.nan, np.float32)
        for candidate in (guess, np.nextafter(guess, np.float32(np.inf)), np.nextafter(guess, np.float32(-np.inf))):
            refold = _depth_weights({**out, name: candidate}, config)[name][0]
            found = np.where(np.isnan(found) & (refold == stored[0]), candidate, found)
        if np.isnan(found).any():
            raise ModelLayoutError(f"{name}: no weights fold to the stored ones")
        out[name] = found
    return out


def read_model(model: onnx.ModelProto, source: str = "OLD.onnx",
               ) -> tuple[MaterialConfig, dict[str, np.ndarray], dict[str, str], int]:
    """Exported `model` of this contract version -> (config, weights as `export.weights_from_state`
    gives them, its metadata, its finest level K: 0 unless trimmed). ModelLayoutError otherwise (of
    another version: `contract.version_problem`, naming `source`)."""
    meta = metadata(model)
    problem = C.version_problem(meta, source)
    if problem:
        raise ModelLayoutError(problem)
    config, finest = model_facts(meta)
    return config, read_weights(initializers(model), config, finest), meta, finest


def read_weights(inits: dict[str, np.ndarray], config: MaterialConfig, finest: int) -> dict[str, np.ndarray]:
    """A graph's initializers, checked against `weights.initializer_shapes` -> the weights as
    `export.weights_from_state` gives them."""
    check_shapes(inits, W.initializer_shapes(config, finest))
    weights = {name: inits[name] for name in W.textures(config)}
    for mlp in W.mlps(config):
        for i in range(config.layers):
            weights[W.weight(mlp, i)], weights[W.bias(mlp, i)] = _layer(inits, mlp, i)
    return unfold_depth(weights, config) if config.offset else weights
