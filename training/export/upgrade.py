"""Reading model files of query contract version 1, so that `neumip export OLD.onnx -o NEW.onnx`
rewrites them in this version (`upgrade.reexport`). Nothing else reads them: every engine refuses
them with `neumip.core.contract.version_problem`, which names that command.

Version 1 files come in three layouts, told apart by their initializers' names:

- the last one (query groups, commit 906263c and before): this version's graph, read as it is;
- before query groups (commit 5889f6e): the same names without ``decoder.0.half_weight.light``, the
  decoder's weights on wi held in its ``.query`` matrix; the graph takes (N, 7) only;
- before issue 12 (commit 3a4acaa): row-major MLPs, ``{mlp}.{i}.weight`` (out, in) and ``.bias``
  (out,), the first layer split over a query Gemm and a texture Gemm.

Their answers and the upgraded file's are the same up to rounding (query groups changed the order of
the decoder's first sum); `upgrade.reexport_file` reports the largest difference.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import onnx

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.config import MaterialConfig
from neumip.core.modelfile import ModelError, read_model_file

from neumip.training.export.graph import build_onnx, save_onnx
from neumip.training.export.read import (NEEDS_CONFIG, ModelLayoutError, metadata, model_file, read_model, read_weights,
                                         unfold_depth)


def read_v1(model: onnx.ModelProto) -> tuple[MaterialConfig, dict[str, np.ndarray], dict[str, str], int]:
    """A version-1 `model` -> what `read.read_model` gives for this version's files."""
    file = model_file(model, any_version=True)
    meta, finest = file.metadata, file.finest_level
    if meta.get(C.META_CONTRACT) not in C.UPGRADABLE_VERSIONS:
        raise ModelLayoutError(f"not a model file of query contract version {', '.join(C.UPGRADABLE_VERSIONS)}")
    config = file.require_config(NEEDS_CONFIG)
    inits = dict(file.initializers)
    light = W.half_weight(W.DECODER, 0, "light")
    if light in inits or W.half_weight(W.DECODER, 0, "texture") in inits:
        if light not in inits:  # before query groups: wi's columns sat in the query matrix
            query = inits.get(W.half_weight(W.DECODER, 0, "query"), np.zeros((0, C.QUERY_DIM), np.float32))
            inits[light] = query[:, [C.WI_X, C.WI_Y]]
        return config, read_weights(inits, config, finest), meta, finest
    return config, _read_before_issue12(model, inits, config), meta, finest


def _read_before_issue12(model: onnx.ModelProto, inits: dict, config: MaterialConfig) -> dict[str, np.ndarray]:
    """The weights of a file written before issue 12's graph (row-major MLPs)."""
    weights = {name: inits[name] for name in W.textures(config) if name in inits}
    try:
        for mlp in W.mlps(config):
            for i in range(config.layers):
                weights[W.weight(mlp, i)], weights[W.bias(mlp, i)] = (
                    _first_gemms(model, inits, mlp) if i == 0 else (inits[W.weight(mlp, i)], inits[W.bias(mlp, i)]))
    except KeyError as exc:
        raise ModelLayoutError(f"no initializer {exc}: not a graph of a neumip export") from exc
    weights = unfold_depth(weights, config) if config.offset else weights
    for name, shape in W.weight_shapes(config).items():
        if name not in weights or weights[name].shape != shape:
            raise ModelLayoutError(f"{name}: {weights[name].shape if name in weights else 'absent'}, "
                                   f"the config needs {shape}")
    return weights


def _first_gemms(model: onnx.ModelProto, inits: dict, mlp: str) -> tuple[np.ndarray, np.ndarray]:
    """Layer 0 of MLP `mlp` before issue 12: two Gemms, the query's (7, hidden) rows, whose output is the
    texture Gemm's bias -> weights (out, in), bias (out,)."""
    gemms = [n for n in model.graph.node if n.op_type == "Gemm"]
    query = [n for n in gemms if n.input[0] == C.ONNX_INPUT and list(n.input[2:]) == [W.bias(mlp, 0)]]
    texture = [n for n in gemms if query and list(n.input[2:]) == [query[0].output[0]]]
    if len(query) != 1 or len(texture) != 1:
        raise ModelLayoutError(f"{mlp}.0: not the two Gemms of an export before issue 12")
    rows, w_tex = inits[query[0].input[1]], inits[texture[0].input[1]]  # (7, hidden), (C, hidden)
    columns = list(W.MLP_QUERY_COLUMNS[mlp])
    return np.concatenate([w_tex.T, rows[columns].T], axis=1), inits[W.bias(mlp, 0)]


def reexport(model: onnx.ModelProto, half_textures: bool = False) -> onnx.ModelProto:
    """`model` rewritten with this version's graph: its weights, config, finest level and metadata.
    A file of an older contract version (`contract.UPGRADABLE_VERSIONS`) comes out in this one. `half_textures`:
    its textures stored in float16 (`MaterialConfig.half_textures`), rounded where they were float32."""
    version = metadata(model).get(C.META_CONTRACT)
    config, weights, meta, finest = read_v1(model) if version in C.UPGRADABLE_VERSIONS else read_model(model)
    if half_textures:
        config = replace(config, half_textures=True)
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


def reexport_file(source: str | Path, out: str | Path, description: str = "",
                  sampling: C.SamplingLobe | None | str = "keep", half_textures: bool = False) -> tuple[Path, float]:
    """`neumip export MODEL.onnx`: rewrite the model at `source` with this version's graph to `out`
    (atomically); returns the path and the largest answer difference on random queries. `sampling`:
    the sampling lobe to declare (None: none), or ``"keep"`` the file's own; `half_textures`: see `reexport`."""
    data = Path(source).read_bytes()
    read_model_file(source, data, any_version=True)  # ModelError for a corrupt file, bad metadata, NaN weights
    old = onnx.load_model_from_string(data)
    new = reexport(old, half_textures)
    meta = metadata(new)
    if description:
        meta[C.META_DESCRIPTION] = description
    if sampling != "keep":
        meta.pop(C.META_SAMPLING, None)
        if sampling is not None:
            meta[C.META_SAMPLING] = sampling.to_json()
    del new.metadata_props[:]
    onnx.helper.set_model_props(new, meta)
    try:  # before writing: a file whose graph cannot run leaves nothing at `out`
        difference = answer_difference(old, new)
    except MemoryError:
        raise
    except Exception as exc:  # ONNX Runtime's own error types (InvalidArgument, Fail, ...) and a name not UTF-8
        raise ModelError(f"{source}: its graph, or its rewrite, does not run in ONNX Runtime: a damaged file? "
                         f"({str(exc)[:300]})") from None
    return save_onnx(new, out), difference
