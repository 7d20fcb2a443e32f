"""ONNX export: the material as one graph, textures stored as initializers.

The graph takes ``queries`` (N, 7) float32 and returns ``rgb`` (N, 3) float32, N dynamic, and
computes what `material.NeuMIPMaterial.forward` computes: the neural offset, a trilinear lookup of
the two nearest pyramid levels, then the decoder MLP. The file stores the textures once, in the layout
`weights_from_state` gives (flat atlas "pyramid" (T, C), "offset_texture" (R * R, C)); the default
graph expands them into wrap-padded tap tables in a constant subgraph that ONNX Runtime folds at
session load (see `texture_tables.py`), so each query reads one table row per level footprint with
float row arithmetic and no modulo. `GraphOptions` selects the variants the benchmark compares.
The model config, contract version and a description travel in the ONNX metadata.

Every graph answers a query with the same bits whatever the batch it sits in (its position, the call's
row count, the thread count): it uses only ops that round per element - Mul, Add, Sub, Div, Sqrt,
Floor, Max, Clip, Gather, integer Mod, GridSample, and Gemm/MatMul, whose sums run in one order per
row - and no Log (whose vectorised tail rounds otherwise; the level of detail is `export_lod.py`)
and no ReduceSum (which sums a 1-row call in another order). tests/training/test_export_determinism.py checks each variant.

`build_onnx` needs only numpy and onnx (weights as numpy arrays); `export_checkpoint` reads a torch
checkpoint.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
from onnx import helper

from neumip.client import contract as C

from .config import MaterialConfig
from .export_gridsample import pyramid_features, texture_features
from .export_lookup import pyramid_texels, texture_texels
from .export_modulo import modulo_graph
from .onnx_graph import INDEX_TYPES, GraphWriter
from .texture_tables import TAPS_PER_ROW

log = logging.getLogger(__name__)

OPSET = 18
IR_VERSION = 9  # onnxruntime 1.31 reads IR <= 13; onnx 1.23 would write 14 by default.

LOOKUPS = ("taps", "modulo", "gridsample")
"""Lookup graphs `GraphOptions.lookup` may name."""
BLENDS = ("sum", "gemm", "premultiplied")
"""Ways `GraphOptions.blend` may join the taps to an MLP's first layer."""


@dataclass(frozen=True)
class GraphOptions:
    """How `build_onnx` writes the material's graph; every choice computes the same function."""

    lookup: str = "taps"
    """"taps": wrap-padded tap tables read with float row arithmetic (`export_lookup.py`); "modulo":
    the first export's graph, int64 Mod index arithmetic on the flat atlas (`export_modulo.py`);
    "gridsample": GridSample on wrap-padded images (`export_gridsample.py`; about half as fast)."""
    taps_per_row: int = 4
    """lookup="taps": bilinear taps per Gather row, 1, 2 or 4 (4: one row per level footprint)."""
    blend: str = "sum"
    """lookup="taps": how the taps meet each MLP's first layer. "sum": a 0/1 MatMul sums the weighted
    taps, then the Gemm (fewest multiply-adds; about 5 % ahead of "gemm"); "gemm": the weighted taps
    feed one Gemm whose weights repeat per tap; "premultiplied": the first layer's texture weights
    are folded into the textures (hidden-wide taps, summed by a 0/1 MatMul). Taps are never summed
    by ReduceSum: ONNX Runtime sums a 1-row call in another order than a longer one, so a query's
    answer would depend on the batch (tests/training/test_export_determinism.py)."""
    index_type: str = "int64"
    """lookup="taps": integer type of the Gather rows, "int64" or "int32"."""

    def __post_init__(self) -> None:
        choices = {"lookup": LOOKUPS, "taps_per_row": TAPS_PER_ROW, "blend": BLENDS,
                   "index_type": tuple(INDEX_TYPES)}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"GraphOptions.{name} must be one of {allowed}, got {getattr(self, name)!r}")


def weights_from_state(state: dict, config: MaterialConfig) -> dict[str, np.ndarray]:
    """Torch state dict of `NeuMIPMaterial` -> the numpy weights `build_onnx` takes."""
    arr = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in state.items()}
    weights = {
        "pyramid": np.concatenate(
            [arr[f"pyramid.{i}"].reshape(-1, config.channels) for i in range(config.levels + 1)]
        )
    }
    prefixes = ["decoder"] + (["offset_mlp"] if config.offset else [])
    for prefix in prefixes:
        for i in range(config.layers):
            weights[f"{prefix}.{i}.weight"] = arr[f"{prefix}.{2 * i}.weight"]
            weights[f"{prefix}.{i}.bias"] = arr[f"{prefix}.{2 * i}.bias"]
    if config.offset:
        weights["offset_texture"] = arr["offset_texture"].reshape(-1, config.offset_channels)
    return weights


def _texture_source(g: GraphWriter, weights: dict, name: str, prefix: str, blend: str) -> tuple[str, int]:
    """The table texels are read from: (T, C) texture, or (T, hidden) texture @ W1[:, :C].T when
    blend="premultiplied" (a constant subgraph, folded at load). Returns (name, width)."""
    texture = g.const(weights[name], name=name)
    if blend != "premultiplied":
        return texture, weights[name].shape[1]
    w1 = weights[f"{prefix}.0.weight"][:, : weights[name].shape[1]]  # (hidden, C)
    return g.op("MatMul", texture, g.const(np.ascontiguousarray(w1.T))), w1.shape[0]


def _query_part(g: GraphWriter, weights: dict, prefix: str, columns: list[int]) -> str:
    """First layer's weights on the query's own columns, plus its bias: (N, 7) queries -> (N, hidden).

    The layer's last inputs are the query `columns`; their weights sit in a (7, hidden) matrix with
    zero rows elsewhere, so no Slice/Concat of the query is needed.
    """
    w = weights[f"{prefix}.0.weight"]  # (hidden, C + len(columns))
    rows = np.zeros((C.QUERY_DIM, w.shape[0]), np.float32)
    rows[columns] = w[:, -len(columns):].T
    bias = g.const(weights[f"{prefix}.0.bias"], name=f"{prefix}.0.bias")
    return g.op("Gemm", C.ONNX_INPUT, g.const(rows), bias)


def _first_layer(g: GraphWriter, texels: str, tap_w: str, taps: int, columns: list[int], weights: dict,
                 prefix: str, layers: int, blend: str) -> str:
    """texels (N, K W), tap weights (N, K), K = taps -> first layer's output (N, hidden), the query
    `columns` being the layer's other inputs. W: the texture's channels C, or hidden ("premultiplied")."""
    w = weights[f"{prefix}.0.weight"]  # (hidden, C + D): texture part, then the query columns
    w_tex = w[:, : -len(columns)]
    width = w.shape[0] if blend == "premultiplied" else w_tex.shape[1]
    spread = np.kron(np.eye(taps, dtype=np.float32), np.ones((1, width), np.float32))  # (K, K W)
    weighted = g.op("Mul", texels, g.op("MatMul", tap_w, g.const(spread)))  # (N, K W)
    rest = _query_part(g, weights, prefix, columns)  # (N, hidden)
    if blend == "gemm":  # the weighted taps meet the texture weights repeated per tap
        x = g.op("Gemm", weighted, g.const(np.tile(w_tex, (1, taps)).T), rest)
    else:  # a 0/1 MatMul sums the taps (in a fixed order per row, unlike ReduceSum), then the weights
        summed = g.op("MatMul", weighted, g.const(np.tile(np.eye(width, dtype=np.float32), (taps, 1))))
        if blend == "premultiplied":
            x = g.op("Add", summed, rest)
        else:
            x = g.op("Gemm", summed, g.const(np.ascontiguousarray(w_tex.T)), rest)
    return g.op("Relu", x) if layers > 1 else x


def _depth_weights(weights: dict, config: MaterialConfig) -> dict:
    """Offset MLP with offset_scale folded into its last layer, whose one output is repeated twice
    (the depth beside each of wo_x, wo_y)."""
    last = config.layers - 1
    out = dict(weights)
    out[f"offset_mlp.{last}.weight"] = np.repeat(weights[f"offset_mlp.{last}.weight"], 2, 0) * config.offset_scale
    out[f"offset_mlp.{last}.bias"] = np.repeat(weights[f"offset_mlp.{last}.bias"], 2, 0) * config.offset_scale
    return out


def _parallax(g: GraphWriter, depth: str, wo: str, min_cos: float) -> str:
    """depth (N, 2) (r twice), wo (N, 2) -> shift (N, 2) = r * wo_xy / max(wo_z, min_cos).

    max(sqrt(max(1 - r2, 0)), m) is computed as sqrt(max(1 - r2, m^2)): equal for a correctly
    rounded sqrt, one op less; every op is on (N, 2) tensors (r2 summed by a 0/1 MatMul).
    """
    r2 = g.op("MatMul", g.op("Mul", wo, wo), g.const(np.ones((2, 2), np.float32)))  # (N, 2) x^2 + y^2
    floor = np.float32(min_cos) * np.float32(min_cos)
    wo_z = g.op("Sqrt", g.op("Max", g.op("Sub", g.scalar(1.0), r2), g.scalar(floor)))
    return g.op("Mul", g.op("Div", depth, wo_z), wo)


def _query_columns(g: GraphWriter) -> tuple[str, str, str]:
    """The query's uv (N, 2), sigma (N, 1) and wo (N, 2)."""
    q = C.ONNX_INPUT
    return (g.pick(q, C.QUERY_DIM, [C.U, C.V]), g.pick(q, C.QUERY_DIM, [C.SIGMA]),
            g.pick(q, C.QUERY_DIM, [C.WO_X, C.WO_Y]))


def _taps_graph(g: GraphWriter, config: MaterialConfig, weights: dict, opts: GraphOptions) -> str:
    """Queries (N, 7) (graph input) -> decoder output (N, 3) before the final Relu."""
    uv, sigma, wo = _query_columns(g)
    taps, index, blend = opts.taps_per_row, opts.index_type, opts.blend

    # --- neural offset: uv += r * wo_xy / max(wo_z, min_cos) -----------------------------------
    if config.offset:
        texture, width = _texture_source(g, weights, "offset_texture", "offset_mlp", blend)
        texels, tap_w = texture_texels(g, texture, config.resolution, width, g.wrap(uv), taps, index)
        mlp = _depth_weights(weights, config)
        hidden = _first_layer(g, texels, tap_w, 4, [C.WO_X, C.WO_Y], mlp, "offset_mlp", config.layers, blend)
        depth = g.mlp(hidden, mlp, "offset_mlp", config.layers, first=1)  # (N, 2)
        uv = g.op("Add", uv, _parallax(g, depth, wo, config.offset_min_cos))

    # --- trilinear pyramid lookup, then the decoder ----------------------------------------------
    atlas, width = _texture_source(g, weights, "pyramid", "decoder", blend)
    texels, tap_w = pyramid_texels(g, config, atlas, width, g.wrap(uv), sigma, taps, index)
    dirs = [C.WI_X, C.WI_Y, C.WO_X, C.WO_Y]
    hidden = _first_layer(g, texels, tap_w, 8, dirs, weights, "decoder", config.layers, blend)
    return g.mlp(hidden, weights, "decoder", config.layers, first=1)


def _gridsample_graph(g: GraphWriter, config: MaterialConfig, weights: dict) -> str:
    """Queries (N, 7) -> decoder output (N, 3) before the final Relu, lookups by GridSample."""
    uv, sigma, wo = _query_columns(g)
    if config.offset:
        texture = g.const(weights["offset_texture"], name="offset_texture")
        feat = texture_features(g, texture, config.resolution, config.offset_channels, g.wrap(uv))
        mlp = _depth_weights(weights, config)
        hidden = _channel_major_layer(g, feat, [C.WO_X, C.WO_Y], mlp, "offset_mlp", config.layers)
        depth = g.mlp(hidden, mlp, "offset_mlp", config.layers, first=1)  # (N, 2)
        uv = g.op("Add", uv, _parallax(g, depth, wo, config.offset_min_cos))
    atlas = g.const(weights["pyramid"], name="pyramid")
    feat = pyramid_features(g, config, atlas, g.wrap(uv), sigma)
    dirs = [C.WI_X, C.WI_Y, C.WO_X, C.WO_Y]
    hidden = _channel_major_layer(g, feat, dirs, weights, "decoder", config.layers)
    return g.mlp(hidden, weights, "decoder", config.layers, first=1)


def _channel_major_layer(g: GraphWriter, features: str, columns: list[int], weights: dict, prefix: str,
                         layers: int) -> str:
    """features (C, N), the query `columns` as the other inputs -> first layer's output (N, hidden)."""
    w_tex = weights[f"{prefix}.0.weight"][:, : -len(columns)]  # (hidden, C)
    rest = _query_part(g, weights, prefix, columns)
    x = g.op("Gemm", features, g.const(np.ascontiguousarray(w_tex.T)), rest, transA=1)
    return g.op("Relu", x) if layers > 1 else x


def build_onnx(
    config: MaterialConfig,
    weights: dict[str, np.ndarray],
    description: str = "",
    extra_metadata: dict[str, str] | None = None,
    options: GraphOptions | None = None,
) -> onnx.ModelProto:
    """The material's inference graph: (N, 7) float32 queries -> (N, 3) float32 RGB."""
    options = options or GraphOptions()
    g = GraphWriter()
    if options.lookup == "modulo":
        rgb = modulo_graph(g, config, weights)
    elif options.lookup == "gridsample":
        rgb = _gridsample_graph(g, config, weights)
    else:
        rgb = _taps_graph(g, config, weights, options)
    g.nodes.append(helper.make_node("Relu", [rgb], [C.ONNX_OUTPUT]))
    model = g.model(C.ONNX_INPUT, C.QUERY_DIM, C.ONNX_OUTPUT, C.RGB_DIM, OPSET, IR_VERSION)
    meta = {
        C.META_CONTRACT: C.CONTRACT_VERSION,
        C.META_CONFIG: config.to_json(),
        C.META_DESCRIPTION: description,
        **(extra_metadata or {}),
    }
    helper.set_model_props(model, meta)
    onnx.checker.check_model(model, full_check=True)
    return model


def save_onnx(model: onnx.ModelProto, path: str | Path) -> Path:
    """Write `model` to `path` atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(model.SerializeToString())
    os.replace(tmp, path)
    return path


def export_checkpoint(
    checkpoint: str | Path, out: str | Path, description: str = "", extra_metadata: dict | None = None
) -> Path:
    """`neumip export`: read a training checkpoint, write the ONNX model."""
    from .checkpoint import load  # torch only here

    material, extra = load(checkpoint)
    from .train import bake_checkpoint_textures

    if bake_checkpoint_textures(material, extra):
        log.warning(
            "%s was written mid-run (step %d): exporting with that step's blurred textures",
            checkpoint, extra["state"]["step"],
        )
    meta = dict(extra_metadata or {})
    if "validation" in extra and C.META_VALIDATION not in meta:
        import json

        meta[C.META_VALIDATION] = json.dumps(extra["validation"])
    model = build_onnx(material.config, weights_from_state(material.state_dict(), material.config),
                       description or extra.get("description", ""), meta)
    return save_onnx(model, out)


# --- weight factories (no torch): known-answer and random materials for tests and benchmarks ------


def _shapes(config: MaterialConfig) -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {"pyramid": (config.atlas_rows(), config.channels)}
    mlps = {"decoder": (config.channels + 4, C.RGB_DIM)}
    if config.offset:
        mlps["offset_mlp"] = (config.offset_channels + 2, 1)
        shapes["offset_texture"] = (config.resolution**2, config.offset_channels)
    for prefix, (n_in, n_out) in mlps.items():
        widths = [n_in] + [config.hidden] * (config.layers - 1) + [n_out]
        for i in range(config.layers):
            shapes[f"{prefix}.{i}.weight"] = (widths[i + 1], widths[i])
            shapes[f"{prefix}.{i}.bias"] = (widths[i + 1],)
    return shapes


def random_weights(config: MaterialConfig, seed: int = 0, scale: float = 0.5) -> dict[str, np.ndarray]:
    """Random weights of the right shapes: a material whose answers are positive and vary with
    position, footprint and directions in every channel, whatever the seed.

    Textures are N(0, scale^2); every layer's weights N(0, 2 / fan_in) (He: the signal keeps its size
    through the ReLUs), hidden biases small and positive (units stay alive). The decoder's last layer
    has positive weights on ReLU outputs (>= 0) and a positive bias, so each channel answers its bias
    plus a query-dependent non-negative sum (with one layer only the bias is positive).
    """
    rng = np.random.default_rng(seed)
    out = {}
    last = f"decoder.{config.layers - 1}"
    for name, shape in _shapes(config).items():
        if name.endswith("weight"):
            w = rng.normal(size=shape) * np.sqrt(2.0 / shape[1])
            out[name] = np.abs(w) * (scale / shape[1]) ** 0.5 if name == f"{last}.weight" and config.layers > 1 else w
        elif name.endswith("bias"):
            out[name] = rng.uniform(0.1, 0.3, shape) if name == f"{last}.bias" else rng.uniform(0.0, 0.1, shape)
        else:  # a texture
            out[name] = rng.normal(size=shape) * scale
    return {name: value.astype(np.float32) for name, value in out.items()}


def constant_weights(config: MaterialConfig, rgb) -> dict[str, np.ndarray]:
    """Weights of a material that answers `rgb` for every query (e.g. albedo / pi: a Lambertian)."""
    out = {name: np.zeros(shape, np.float32) for name, shape in _shapes(config).items()}
    out[f"decoder.{config.layers - 1}.bias"] = np.asarray(rgb, np.float32).reshape(C.RGB_DIM)
    return out
