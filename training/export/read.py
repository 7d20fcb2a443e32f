"""The inverse of `export.build_onnx`: a material's weights read back from an exported model.

Shipped materials are ONNX files only (no checkpoint). Reading their weights back lets `neumip
export MODEL.onnx -o NEW.onnx` rewrite a model with this version's graph: same weights, same
metadata (config, description, validation, trim record), and - when the graphs compute the same
function in the same float order - the same answer bits (`reexport_file` checks that on random
queries and reports the largest difference). A file of query contract version 1 is read by
`upgrade.read_v1` instead and comes out in this version (`neumip.core.contract.version_problem`).

The model is read by the one model-file reader (`neumip.core.modelfile`: metadata, config, trim, finite
weights); the graph's initializers and their shapes are `neumip.core.weights.initializer_shapes`; each
is checked, so a file this export did not write is refused by name, never guessed at. Matrices are
stored halved (`onnx_graph.GraphWriter.product`) and doubled back here, exact; a first layer is put
back together from its parts (texture, query, light columns); the offset MLP's last layer is stored
folded (`export._depth_weights`) and unfolded to weights that fold to the same bits.
"""

from __future__ import annotations

import numpy as np
import onnx

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.config import BASE_HORIZONS, DECODER_INPUTS, MaterialConfig
from neumip.core.modelfile import ModelError, ModelFile, read_model_file

from neumip.training.export.base import BASE_CONSTANT, BASE_PLACE, BASE_VARYING, base_from_stored
from neumip.training.export.graph import RELIEF_DEPTH, _depth_weights
from neumip.training.export.lookup import mip_atlas
from neumip.training.export.onnx_graph import COLUMN_ALPHA


ModelLayoutError = ModelError
"""A model whose graph is not one `export.build_onnx` wrote (its weights cannot be read back): the
model-file reader's one error."""

NEEDS_CONFIG = "reading its weights back needs the model's config"
"""What `ModelFile.require_config` says needs it here."""


def model_file(model: onnx.ModelProto, source: str = "model.onnx", any_version: bool = False) -> ModelFile:
    """In-memory `model` read by the one model-file reader (`core.modelfile.read_model_file`), its
    initializers included; `source`: the file's path, as its messages name it."""
    return read_model_file(source, model.SerializeToString(), any_version=any_version, initializers=True)


def metadata(model: onnx.ModelProto) -> dict[str, str]:
    """The model's ONNX metadata (of any contract version)."""
    return model_file(model, any_version=True).metadata


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
        if mlp in W.DECODERS:
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
    file = model_file(model, source)
    config = file.require_config(NEEDS_CONFIG)
    return config, read_weights(file.initializers, config, file.finest_level), file.metadata, file.finest_level


def read_weights(inits: dict[str, np.ndarray], config: MaterialConfig, finest: int) -> dict[str, np.ndarray]:
    """A graph's initializers, checked against `weights.initializer_shapes` -> the weights as
    `export.weights_from_state` gives them."""
    want = W.initializer_shapes(config, finest)
    place = inits.get(BASE_PLACE)
    base_whole = config.base and BASE_CONSTANT not in inits  # the layout before 2026-11-28: every channel stored
    if config.base and not base_whole:  # its varying map channels and the horizons (`base.read_base`)
        want[W.BASE] = (want[W.BASE][0], (0 if place is None else place.shape[0]) + BASE_HORIZONS)
    mips, mips_derived = config.offset_pyramid(), W.offset_levels_derived(config, finest)
    if mips_derived and inits.get(W.OFFSET_TEXTURE, np.zeros((0, 0))).shape == (mips.atlas_rows(), mips.channels):
        want[W.OFFSET_TEXTURE], mips_derived = (mips.atlas_rows(), mips.channels), False  # that layout's: every level
    check_shapes(inits, want)
    weights = {name: inits[name].astype(np.float32) for name in W.textures(config)}  # float16 with half_textures
    if mips_derived:  # the levels the graph derives
        weights[W.OFFSET_TEXTURE] = mip_atlas(weights[W.OFFSET_TEXTURE].reshape(mips.resolution, mips.resolution, -1))
    if config.base and not base_whole:
        try:
            weights[W.BASE], weights[BASE_VARYING] = base_from_stored(weights[W.BASE], place, inits[BASE_CONSTANT])
        except ValueError as exc:
            raise ModelLayoutError(str(exc)) from exc
    if config.energy_bins:
        weights[W.ENERGY] = inits[W.ENERGY].astype(np.float32)
    if RELIEF_DEPTH in inits:  # the depth of all the heights, which a trimmed model's kept levels may not reach
        weights[RELIEF_DEPTH] = inits[RELIEF_DEPTH]
    for mlp in W.mlps(config):
        for i in range(config.layers):
            weights[W.weight(mlp, i)], weights[W.bias(mlp, i)] = _layer(inits, mlp, i)
    return unfold_depth(weights, config) if config.offset else weights
