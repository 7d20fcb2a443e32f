"""ONNX export: the material as one graph, textures stored as initializers.

The graph takes ``queries`` (N, 7) float32 and returns ``rgb`` (N, 3) float32, or query groups (N, 5
+ 2 K) -> (N, 3 K) (`contract`: the offset and the lookups run once per group, the decoder once per
light), both dimensions dynamic, and computes what `material.NeuMIPMaterial.forward` computes, in
three stages read top to bottom in `material_graph` (after the relief's march with `MaterialConfig.relief`,
and with the classical base's BSDF per light after the decoder with `MaterialConfig.base`, `export/base.py`): the neural offset (a bilinear lookup of the
offset texture, or a trilinear one of its mip pyramid with `MaterialConfig.offset_mip`, the offset MLP, the parallax shift), a trilinear lookup of the two nearest pyramid
levels, then the decoder MLP. The lookups work on one query per row; the MLPs on one query per
column (`GraphWriter.product`: the first layers read the weighted texels and the queries transposed,
one Transpose after each MLP). The file stores the textures once, in the layout `weights_from_state`
gives (flat atlas "pyramid" (T, C), "offset_texture" (R * R, C)), and nothing it can derive: the offset's mip
pyramid (`MaterialConfig.offset_mip`) as its finest level (`lookup.mip_const` computes the others), the base's
maps without their channels that are the same in every texel (`base.read_base`); a constant subgraph that ONNX
Runtime folds at session load expands them into wrap-padded quad tables (`lookup.py`), so
each query reads one table row per level footprint with float row arithmetic and no modulo. The
model config, contract version and a description travel in the ONNX metadata.

The graph answers a query with the same bits whatever the batch it sits in (its position, the call's
row count, the thread count): it uses only ops that round per element - Mul, Add, Sub, Div, Sqrt,
Floor, Max, Min, Clip, Neg, GreaterOrEqual, Cast, Gather, and Gemm/MatMul, whose sums run in one order per row - and no Log (whose
vectorised tail rounds otherwise; the level of detail is `lod.py`) and no ReduceSum (which sums
a 1-row call in another order: taps are summed by a 0/1 MatMul instead).
tests/training/export/test_determinism.py checks it. benchmarks/bench_inference.py measures it
against the first export's graph (benchmarks/export_modulo.py).

`build_onnx` needs only numpy and onnx (weights as numpy arrays); `export_material` takes a torch
material (`neumip.training.loop.outputs.export_checkpoint` reads a training checkpoint).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from neumip.core import contract as C

from neumip.core import head
from neumip.core import weights as W
from neumip.core.config import RELIEF_DIVISION_FLOOR, RELIEF_MIN_COS, MaterialConfig
from neumip.training.export import base as B
from neumip.training.export.energy import energy_gain, group_lod
from neumip.training.export.lookup import (footprint_texels, mip_atlas, mip_const, pyramid_footprint, pyramid_texels,
                                          stored_texture, texture_const, texture_texels)
from neumip.training.export.lod import OFFSET_PREFIX, RELIEF_PREFIX, pyramids
from neumip.training.export.onnx_graph import GraphWriter

log = logging.getLogger(__name__)

OPSET = 18
IR_VERSION = 9  # onnxruntime 1.31 reads IR <= 13; onnx 1.23 would write 14 by default.


def weights_from_state(state: dict, config: MaterialConfig) -> dict[str, np.ndarray]:
    """Torch state dict of `NeuMIPMaterial` -> the numpy weights `build_onnx` takes."""
    arr = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in state.items()}
    weights = {
        W.PYRAMID: np.concatenate(
            [arr[f"pyramid.{i}"].reshape(-1, config.channels) for i in range(config.levels + 1)]
        )
    }
    for prefix in W.mlps(config):
        for i in range(config.layers):
            weights[W.weight(prefix, i)] = arr[f"{prefix}.{2 * i}.weight"]
            weights[W.bias(prefix, i)] = arr[f"{prefix}.{2 * i}.bias"]
    if config.offset_pyramid() is not None:  # its pyramid, derived from the finest level as the model reads it
        from neumip.training.model.pyramid import as_stored, mip_atlas  # torch: only this function reads a torch state

        texture = as_stored(state["offset_texture"].detach().cpu().float(), config)
        weights[W.OFFSET_TEXTURE] = mip_atlas(texture).numpy()
    elif config.offset:
        weights[W.OFFSET_TEXTURE] = arr["offset_texture"].reshape(-1, config.offset_channels)
    for name in (W.BASE, W.RELIEF, W.ENERGY):
        if name in arr:
            weights[name] = arr[name]
    return weights


def _query_part(g: GraphWriter, q: str, weights: dict, prefix: str, columns: list[int],
                weight_columns: slice) -> str:
    """First layer's weights on the query's own `columns` (its weight columns `weight_columns`), plus
    its bias: the group's first query (N, 7) -> (hidden, N).

    Their weights sit in a (hidden, 7) matrix with zero columns elsewhere, so no Slice/Concat of the
    query is needed.
    """
    w = weights[W.weight(prefix, 0)]  # (hidden, C + query columns)
    matrix = np.zeros((w.shape[0], C.QUERY_DIM), np.float32)
    matrix[:, columns] = w[:, weight_columns]
    bias = g.const(weights[W.bias(prefix, 0)][:, None], name=W.bias(prefix, 0))
    return g.product(matrix, q, bias, rows=True, name=W.half_weight(prefix, 0, "query"))


def _first_layer(g: GraphWriter, q: str, texels: str, tap_w: str, taps: int, columns: list[int],
                 weights: dict, prefix: str, inputs: int) -> str:
    """texels (N, K C), tap weights (N, K), K = taps -> first layer's output (hidden, N) before its
    activation (column-major, `GraphWriter.product`); the MLP's last `inputs` inputs are query
    columns, of which this layer reads `columns` (the first ones; the others are the lights').

    A 0/1 matrix sums the weighted taps (in one order per query, unlike ReduceSum), then one Gemm
    applies the texture weights and adds the query part.
    """
    w = weights[W.weight(prefix, 0)]  # (hidden, C + inputs): texture part, then the query columns
    w_tex = w[:, :-inputs]
    width = w_tex.shape[1]
    spread = np.kron(np.eye(taps, dtype=np.float32), np.ones((1, width), np.float32))  # (K, K C)
    weighted = g.op("Mul", texels, g.op("MatMul", tap_w, g.const(spread)))  # (N, K C)
    rest = _query_part(g, q, weights, prefix, columns, slice(w.shape[1] - len(columns), None))  # (hidden, N)
    summed = g.product(np.tile(np.eye(width, dtype=np.float32), (1, taps)), weighted, rows=True)  # (C, N)
    return g.product(w_tex, summed, rest, name=W.half_weight(prefix, 0, "texture"))


def _reshape(g: GraphWriter, x: str, *dims: str | int, output: str | None = None) -> str:
    """Reshape `x` to `dims`: 1-element int64 shape tensors (by name) or constants. Sizes computed in
    the graph, never -1 (Reshape cannot infer it for an empty batch), taken with allowzero (a 0 is a
    size, not "copy this dimension"). `output` names the result (default: a new name)."""
    parts = [d if isinstance(d, str) else g.const([d], np.int64) for d in dims]
    shape = g.op("Concat", *parts, axis=0)
    if output is None:
        return g.op("Reshape", x, shape, allowzero=1)
    g.nodes.append(helper.make_node("Reshape", [x, shape], [output], allowzero=1))
    return output


def _lights(g: GraphWriter, q: str) -> tuple[str, str, str, str]:
    """The groups' light directions, one per row, light-major: (K N, 2), row ``j N + n`` is light j
    of group n; and the 1-element shapes [N], [K], [K N]."""
    first = g.pick(q, C.QUERY_DIM, [C.WI_X, C.WI_Y])  # (N, 2)
    more = g.op("Slice", C.ONNX_INPUT, g.const([C.QUERY_DIM], np.int64), g.const([2**62], np.int64),
                g.const([1], np.int64))  # (N, 2 K - 2)
    n = g.op("Shape", C.ONNX_INPUT, end=1)
    width = g.op("Shape", C.ONNX_INPUT, start=1)
    k = g.op("Div", g.op("Sub", width, g.const([5], np.int64)), g.const([2], np.int64))  # width 5 + 2 K
    kn = g.op("Mul", k, n)
    wi = _reshape(g, g.op("Concat", first, more, axis=1), n, k, 2)  # (N, K, 2)
    return _reshape(g, g.op("Transpose", wi, perm=[1, 0, 2]), kn, 2), n, k, kn


def _depth_weights(weights: dict, config: MaterialConfig) -> dict:
    """Offset MLP with offset_scale folded into its last layer, whose one output is repeated twice
    (the depth beside each of wo_x, wo_y)."""
    out = dict(weights)
    for name in (W.weight(W.OFFSET_MLP, config.layers - 1), W.bias(W.OFFSET_MLP, config.layers - 1)):
        out[name] = np.repeat(weights[name], W.DEPTH_COPIES, 0) * config.offset_scale
    return out


def _clamped_wo_z(g: GraphWriter, wo: str, min_cos: float) -> str:
    """wo (N, 2) -> (N, 2) max(wo_z, min_cos) twice (the offset's and the relief's divisor).

    max(sqrt(max(1 - r2, 0)), m) is computed as sqrt(max(1 - r2, m^2)): equal for a correctly
    rounded sqrt, one op less; every op is on (N, 2) tensors (r2 summed by a 0/1 MatMul).
    """
    r2 = g.op("MatMul", g.op("Mul", wo, wo), g.const(np.ones((2, 2), np.float32)))  # (N, 2) x^2 + y^2
    floor = np.float32(min_cos) * np.float32(min_cos)
    return g.op("Sqrt", g.op("Max", g.op("Sub", g.scalar(1.0), r2), g.scalar(floor)))


def _parallax(g: GraphWriter, depth: str, wo: str, min_cos: float) -> str:
    """depth (N, 2) (r twice), wo (N, 2) -> shift (N, 2) = r * wo_xy / max(wo_z, min_cos)."""
    return g.op("Mul", g.op("Div", depth, _clamped_wo_z(g, wo, min_cos)), wo)


def _half_vector(g: GraphWriter, wi: str, wo: str) -> str:
    """wi, wo (M, 2) -> (M, 4): h = normalize(wi + wo) and cos(theta_d) = h . wi, as `material.half_vector`
    computes them (z = sqrt(max(1 - x^2 - y^2, 0)); sums of squares by MatMuls with ones)."""
    wi3, wo3 = B.lift(g, wi), B.lift(g, wo)
    h = B.half_direction(g, wi3, wo3)
    return g.op("Concat", h, B.dot(g, h, wi3), axis=1)


class LightStage:
    """What the decoder's optional inputs read, per light (K N rows): the group's base maps (`read`, or None), each
    light's wi, the group's wo repeated per light; and what they leave for the base's answer (its normal, its
    visibility of the light)."""

    def __init__(self, g: GraphWriter, read, wi: str, wo: str, each_light) -> None:
        self.g, self.read, self.wi, self.each_light, self.group_wo = g, read, wi, each_light, wo
        self.normal: str | None = None  # (K N, 3) the base's normal, where an input computed it
        self.lit: str | None = None  # (K N, 1) the base's visibility of the light, where an input computed it

    @property
    def wo(self) -> str:
        """The group's wo repeated per light (K N, 2)."""
        return self.each_light(self.group_wo)


def _frame_input(s: LightStage) -> str:
    """wi and the group's wo in the frame of the group's base normal (K N, 6); the normal is the base's too."""
    s.normal = B.base_normal(s.g, s.each_light(s.read.maps))  # (K N, 3)
    return B.frame_inputs(s.g, s.normal, s.wi, s.wo)


def _visibility_input(s: LightStage) -> str:
    """The base's visibility of each light at the group's maps (K N, 1); the base's answer reads it too."""
    horizon = B.horizon_sine(s.g, s.read, s.each_light(s.read.rows), s.each_light(s.read.taps), s.wi)  # (K N, 1)
    s.lit = B.light_visibility(s.g, horizon, s.wi)
    return s.lit


DECODER_INPUTS = {
    "half_vector": lambda s: _half_vector(s.g, s.wi, s.wo),
    "frame": _frame_input,
    "visibility": _visibility_input,
}
"""How each row of `core.config.DECODER_INPUTS` is computed in the graph, per light: `LightStage` -> a (K N, width)
tensor. The torch model's twin is `training.model.material.DECODER_INPUTS`."""


COARSE_PREFIX = "coarse_decoder."
"""Names of the constants of the coarse decoder's blend (its level of detail's tables)."""


RELIEF_DEPTH = "relief.depth"
"""The initializer (1, 1) holding the relief's depth, -min of its heights (0 at least): by name, as the heights of
a model trimmed (`neumip trim`) may no longer hold their minimum. A weights dict may give it (read back from such
a model); otherwise it comes from ``weights["relief_heights"]``."""


def relief_depth(weights: dict, config: MaterialConfig) -> np.float32:
    """The relief's depth: ``weights[RELIEF_DEPTH]`` where given, else -min(heights as stored), 0 at least."""
    if RELIEF_DEPTH in weights:
        return np.float32(np.asarray(weights[RELIEF_DEPTH], np.float32).reshape(()))
    return np.float32(max(-float(stored_texture(weights[W.RELIEF], config).min()), 0.0))


def _relief(g: GraphWriter, config: MaterialConfig, weights: dict, uv: str, sigma: str, wo: str,
            finest_level: int = 0) -> str:
    """uv (N, 2), sigma (N, 1), wo (N, 2) -> (N, 2) the relief's shift of the lookups, as `relief.relief_shift`
    computes it: one footprint of the height pyramid, read at each step's position. ``finest_level``: the
    finest level ``weights["relief_heights"]`` holds (a trimmed model, `MaterialConfig.pyramid_finest_level`)."""
    depth = relief_depth(weights, config)
    steps = config.relief_steps
    heights = texture_const(g, stored_texture(weights[W.RELIEF], config), W.RELIEF, config)
    fp = pyramid_footprint(g, config.relief_pyramid(), heights, 1, sigma, finest_level, RELIEF_PREFIX)
    d = g.op("Div", wo, _clamped_wo_z(g, wo, RELIEF_MIN_COS))
    ones = g.const(np.ones((8, 1), np.float32))
    found = missed = s_prev = t_prev = None
    for k in range(steps + 1):
        t = np.float32(depth * np.float32(k / steps))
        texels, tap_w = footprint_texels(g, fp, 1, g.wrap(g.op("Sub", uv, g.op("Mul", d, g.scalar(t)))))
        s = g.op("Add", g.op("MatMul", g.op("Mul", texels, tap_w), ones), g.scalar(t))  # (N, 1)
        below = g.op("Cast", g.op("GreaterOrEqual", s, g.scalar(0.0)), to=TensorProto.FLOAT)
        if k == 0:
            found, missed = g.op("Mul", below, g.scalar(0.0)), g.op("Sub", g.scalar(1.0), below)
        else:
            gap = g.op("Max", g.op("Sub", s, s_prev), g.scalar(RELIEF_DIVISION_FLOOR))
            ratio = g.op("Min", g.op("Max", g.op("Div", g.op("Neg", s_prev), gap), g.scalar(0.0)), g.scalar(1.0))
            here = g.op("Add", g.op("Mul", ratio, g.scalar(depth / np.float32(steps))), g.scalar(t_prev))
            found = g.op("Add", found, g.op("Mul", g.op("Mul", missed, below), here))
            missed = g.op("Mul", missed, g.op("Sub", g.scalar(1.0), below))
        s_prev, t_prev = s, t
    deepest = g.const(np.full((1, 1), depth, np.float32), name=RELIEF_DEPTH)
    found = g.op("Add", found, g.op("Mul", missed, deepest))
    return g.op("Mul", d, g.op("Neg", found))


def _query_columns(g: GraphWriter, q: str) -> tuple[str, str, str]:
    """The query's uv (N, 2), sigma (N, 1) and wo (N, 2)."""
    return (g.pick(q, C.QUERY_DIM, [C.U, C.V]), g.pick(q, C.QUERY_DIM, [C.SIGMA]),
            g.pick(q, C.QUERY_DIM, [C.WO_X, C.WO_Y]))


def material_graph(g: GraphWriter, config: MaterialConfig, weights: dict,
                   finest_level: int = 0) -> tuple[str, list[str]]:
    """Query groups (N, 5 + 2 K) (graph input) -> decoder output (N K, O) before the head, row
    ``n K + j`` answering light j of group n, and the answer's shape ([N], [3 K]).

    The offset and the lookups run once per group (on its first query's u, v, sigma, wo); the decoder's
    first layer adds each light's wi part to the group's texture-and-wo part, and the rest of the
    decoder runs once per light. ``weights["pyramid"]`` holds levels ``finest_level``..L (all of them
    unless trimmed), the base maps' and the relief's pyramids the levels of the same footprint on
    (`MaterialConfig.pyramid_finest_level`).
    """
    q = g.op("Slice", C.ONNX_INPUT, g.const([0], np.int64), g.const([C.QUERY_DIM], np.int64),
             g.const([1], np.int64))  # (N, 7): each group's first query
    uv, sigma, wo = _query_columns(g, q)

    # --- relief: uv moves to where the view ray first meets the height field --------------------
    finest = {p.texture: config.pyramid_finest_level(p.config, finest_level) for p in pyramids(config)}
    if config.relief:
        uv = g.op("Add", uv, _relief(g, config, weights, uv, sigma, wo, finest[W.RELIEF]))

    # --- neural offset: uv += r * wo_xy / max(wo_z, min_cos) -----------------------------------
    if config.offset:
        mips = config.offset_pyramid()
        if W.offset_levels_derived(config, finest_level):  # the file stores its finest level, the graph the rest
            texture = mip_const(g, weights[W.OFFSET_TEXTURE], mips, W.OFFSET_TEXTURE, config)
        else:  # a trimmed mip pyramid's levels (a finest level alone would not give them the same bits), or one level
            texture = texture_const(g, stored_texture(weights[W.OFFSET_TEXTURE], config), W.OFFSET_TEXTURE, config)
        if mips is not None:  # trilinear on its mip pyramid, at the query's footprint: 8 taps
            texels, tap_w = pyramid_texels(g, mips, texture, config.offset_channels, g.wrap(uv), sigma,
                                           finest[W.OFFSET_TEXTURE], OFFSET_PREFIX)
        else:  # bilinear at the finest resolution: 4 taps
            texels, tap_w = texture_texels(g, config, texture, config.resolution, config.offset_channels, g.wrap(uv),
                                           OFFSET_PREFIX)
        mlp = _depth_weights(weights, config)
        hidden = _first_layer(g, q, texels, tap_w, 4 if mips is None else 8, [C.WO_X, C.WO_Y], mlp, W.OFFSET_MLP, 2)
        if config.layers > 1:
            hidden = g.op("Relu", hidden)
        depth = g.op("Transpose", g.mlp(hidden, mlp, W.OFFSET_MLP, config.layers, first=1), perm=[1, 0])  # (N, 2)
        uv = g.op("Add", uv, _parallax(g, depth, wo, config.offset_min_cos))

    # --- trilinear pyramid lookup, then the decoder once per light -------------------------------
    atlas = texture_const(g, stored_texture(weights[W.PYRAMID], config), W.PYRAMID, config)
    uvw = g.wrap(uv)
    texels, tap_w = pyramid_texels(g, config, atlas, config.channels, uvw, sigma, finest_level)
    shared = _first_layer(g, q, texels, tap_w, 8, [C.WO_X, C.WO_Y], weights, W.DECODER,
                          4 + W.decoder_extra_inputs(config))  # (hidden, N)
    inputs = config.decoder_inputs()
    read = (B.read_base(g, config, weights, uvw, sigma, finest[W.BASE]) if any(row.reads_base for row in inputs)
            else None)
    wi, n, k, kn = _lights(g, q)  # (K N, 2)
    per_light: list[str] = []  # Tile repeats of a group's row, light-major (made when a stage needs it)

    def each_light(x: str) -> str:
        """A group's rows (N, F) -> (K N, F), row j N + n that of group n."""
        if not per_light:
            per_light.append(g.op("Concat", k, g.const([1], np.int64), axis=0))
        return g.op("Tile", x, per_light[0])

    stage = LightStage(g, read, wi, wo, each_light)
    values: list[str] = []  # each optional input per light (K N, width), computed by the first decoder that reads it

    def decoder(mlp: str, shared: str) -> str:
        """The decoder `mlp`'s output (K N, O) from its first layer's group part `shared` (hidden, N): its light part
        and optional inputs' parts per light, then the rest of it."""
        w = weights[W.weight(mlp, 0)]
        light = g.product(w[:, -4:-2], wi, rows=True, name=W.half_weight(mlp, 0, "light"))  # (hidden, K N)
        hidden = g.op("Add", g.op("Tile", shared, g.op("Concat", g.const([1], np.int64), k, axis=0)), light)
        first = config.channels
        for i, row in enumerate(inputs):  # per light, each optional input's columns of the first layer
            if i == len(values):
                values.append(DECODER_INPUTS[row.name](stage))
            hidden = g.op("Add", hidden, g.product(w[:, first : first + row.width], values[i], rows=True,
                                                   name=W.half_weight(mlp, 0, row.name)))  # (hidden, K N)
            first += row.width
        if config.layers > 1:
            hidden = g.op("Relu", hidden)
        return g.op("Transpose", g.mlp(hidden, weights, mlp, config.layers, first=1), perm=[1, 0])  # (K N, O)

    out = decoder(W.DECODER, shared)
    normal, lit = stage.normal, stage.lit
    lod = None  # the groups' level of detail, where the coarse decoder's blend computes it (the energy table reads it)
    if config.coarse_decoder:  # blended into the coarse levels' by w = clamp(lod - K, 0, 1), per light
        coarse = decoder(W.COARSE_DECODER, _first_layer(g, q, texels, tap_w, 8, [C.WO_X, C.WO_Y], weights,
                                                        W.COARSE_DECODER, 4 + W.decoder_extra_inputs(config)))
        lod = group_lod(g, config, sigma, finest_level, COARSE_PREFIX)  # (N, 1) in [finest_level, L]
        blend = g.op("Min", g.op("Max", g.op("Sub", lod, g.scalar(float(config.coarse_decoder))), g.scalar(0.0)),
                     g.scalar(1.0))  # (N, 1)
        out = g.op("Add", out, g.op("Mul", each_light(blend), g.op("Sub", coarse, out)))
    size = head.outputs(config.head)
    if config.base:  # per light: the base's answer from the group's maps, corrected by the decoder
        read = read or B.read_base(g, config, weights, uvw, sigma, finest[W.BASE])
        horizon = None if lit else B.horizon_sine(g, read, each_light(read.rows), each_light(read.taps), wi)  # (K N, 1)
        out = B.corrected(g, B.base_answer(g, each_light(read.maps), horizon, wi, each_light(wo), normal,
                                                terminator=config.terminator, lit=lit), out)
    if config.energy_bins:  # per light: the gain of the group's level of detail, the half vector and the light's elevation
        out = g.op("Mul", out, energy_gain(g, config, weights[W.ENERGY], sigma, wi, stage.wo, each_light,
                                           finest_level, lod))
    rows = _reshape(g, out, k, n, size)  # (K, N, O)
    rows = _reshape(g, g.op("Transpose", rows, perm=[1, 0, 2]), kn, size)  # (N K, O)
    return rows, [n, g.op("Mul", k, g.const([C.RGB_DIM], np.int64))]


def _yuv_head(g: GraphWriter, out: str) -> str:
    """Decoder output (N, 6) -> (N, 3) exp(YUV_TO_RGB yuv) - 1 times the shadow mask (core/head.py)."""
    yuv = np.zeros((6, 3), np.float64)
    yuv[:3] = head.YUV_TO_RGB.T  # columns 0-2 -> RGB in log space, in one MatMul (no Slice)
    shadow = np.zeros((6, 3), np.float32)
    shadow[3:] = np.eye(3)
    colour = g.op("Sub", g.op("Exp", g.op("MatMul", out, g.const(yuv))), g.scalar(1.0))
    mask = g.op("Add", g.op("Sigmoid", g.op("MatMul", out, g.const(shadow))), g.scalar(head.SHADOW_FLOOR))
    return g.op("Mul", colour, mask)


def build_onnx(
    config: MaterialConfig,
    weights: dict[str, np.ndarray],
    description: str = "",
    extra_metadata: dict[str, str] | None = None,
    finest_level: int = 0,
) -> onnx.ModelProto:
    """The material's inference graph: (N, 7) float32 queries -> (N, 3) float32 RGB, and query groups
    (N, 5 + 2 K) -> (N, 3 K) (`contract.group_width`).

    With ``finest_level`` K > 0 the pyramid holds levels K..L only, and the base maps' and the relief's
    pyramids the levels of the same footprint on (`trim.trimmed_weights`; `trim.trim_model` makes such a
    model from an exported one): finer queries read level K.
    """
    g = GraphWriter()
    rgb, shape = material_graph(g, config, weights, finest_level)
    if config.head == "yuv":
        rgb = _yuv_head(g, rgb)
    rgb = g.op("Relu", rgb)
    if config.ceiling:
        rgb = g.op("Min", rgb, g.scalar(config.ceiling))
    _reshape(g, rgb, *shape, output=C.ONNX_OUTPUT)  # (N, 3 K)
    model = g.model(C.ONNX_INPUT, "width", C.ONNX_OUTPUT, "answers", OPSET, IR_VERSION)
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
    """Write `model` to `path` atomically (`core.files.write_bytes_atomic`: temporary file, then rename)."""
    from neumip.core.files import write_bytes_atomic

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_bytes_atomic(path, model.SerializeToString())


def export_material(material, out: str | Path, description: str = "", validation: dict | None = None,
                    sampling: C.SamplingLobe | None = None) -> Path:
    """Write a torch `NeuMIPMaterial` (its weights as they are) to `out` as an ONNX model, with its
    validation table and sampling lobe (where given) in the metadata."""
    meta = {C.META_VALIDATION: json.dumps(validation)} if validation is not None else {}
    if sampling is not None:
        meta[C.META_SAMPLING] = sampling.to_json()
    weights = weights_from_state(material.state_dict(), material.config)
    return save_onnx(build_onnx(material.config, weights, description, meta), out)


# --- weight factories (no torch): known-answer and random materials for tests and benchmarks ------


def random_weights(config: MaterialConfig, seed: int = 0, scale: float = 0.5) -> dict[str, np.ndarray]:
    """Random weights of the right shapes: a material whose answers are positive and vary with
    position, footprint and directions in every channel, whatever the seed.

    Textures are N(0, scale^2) (a base's maps: colours, slopes and alpha^2 in their ranges; the energy table's gains
    in [0.5, 2]); every layer's weights N(0, 2 / fan_in) (He: the signal keeps its size
    through the ReLUs), hidden biases small and positive (units stay alive). The decoder's last layer
    has positive weights on ReLU outputs (>= 0) and a positive bias, so each channel answers its bias
    plus a query-dependent non-negative sum (with one layer only the bias is positive).
    """
    rng = np.random.default_rng(seed)
    out = {}
    last = {W.weight(mlp, config.layers - 1) for mlp in W.DECODERS}
    last_bias = {W.bias(mlp, config.layers - 1) for mlp in W.DECODERS}
    for name, shape in W.weight_shapes(config).items():
        if name.endswith("weight"):
            w = rng.normal(size=shape) * np.sqrt(2.0 / shape[1])
            out[name] = np.abs(w) * (scale / shape[1]) ** 0.5 if name in last and config.layers > 1 else w
        elif name.endswith("bias"):
            out[name] = rng.uniform(0.1, 0.3, shape) if name in last_bias else rng.uniform(0.0, 0.1, shape)
        elif name == W.BASE:  # maps a base can hold: colours and F0 in [0, 1), slopes, alpha^2 in (0, 1), horizons
            out[name] = np.concatenate([rng.uniform(0, 1, (shape[0], 6)), rng.normal(size=(shape[0], 2)) * 0.5,
                                        rng.uniform(0.01, 1, (shape[0], 1)), rng.uniform(0, 0.6, (shape[0], shape[1] - 9))],
                                       axis=1)
        elif name == W.ENERGY:  # gains that move the answers both ways (tied at the normal, as a fit's)
            out[name] = rng.uniform(0.5, 2.0, shape)
            W.tie_normal_cells(out[name], config)
        elif name == W.RELIEF:  # a smooth periodic relief `scale` / 4 tile deep, the same at every level
            out[name] = _random_relief(config.relief_pyramid().level_sizes(), rng, scale / 4)
        elif name == W.OFFSET_TEXTURE and config.offset_pyramid() is not None:  # the mip pyramid of a random texture
            size = config.offset_pyramid().resolution  # as stored, as `weights_from_state` derives it
            finest = stored_texture((rng.normal(size=(size * size, shape[1])) * scale).astype(np.float32), config)
            out[name] = mip_atlas(finest.reshape(size, size, shape[1]))
        else:  # a texture
            out[name] = rng.normal(size=shape) * scale
    return {name: value.astype(np.float32) for name, value in out.items()}


def _random_relief(sizes: list[int], rng: np.random.Generator, depth: float) -> np.ndarray:
    """A height atlas (levels of `sizes`, finest first, one channel): 3 random periodic waves of up to 4
    periods per tile, sampled at each level's texel centres, within [-depth, 0]."""
    freqs, phases = rng.integers(1, 5, (3, 2)), rng.uniform(0, 2 * np.pi, 3)
    levels = []
    for size in sizes:
        x = (np.arange(size) + 0.5) / size
        u, v = np.meshgrid(x, x)
        levels.append(sum(np.cos(2 * np.pi * (f[0] * u + f[1] * v) + p) for f, p in zip(freqs, phases)).reshape(-1, 1))
    return (np.concatenate(levels) / 6.0 - 0.5) * depth


def constant_weights(config: MaterialConfig, rgb) -> dict[str, np.ndarray]:
    """Weights of a material that answers `rgb` for every query (e.g. albedo / pi: a Lambertian)."""
    out = {name: np.zeros(shape, np.float32) for name, shape in W.weight_shapes(config).items()}
    if config.energy_bins:
        out[W.ENERGY] = np.ones(W.weight_shapes(config)[W.ENERGY], np.float32)
    out[W.bias(W.DECODER, config.layers - 1)] = head.answer_bias(config.head, rgb)
    return out
