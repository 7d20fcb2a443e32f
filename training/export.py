"""ONNX export: the material as one graph, textures stored as initializers.

The graph takes ``queries`` (N, 7) float32 and returns ``rgb`` (N, 3) float32, or query groups (N, 5
+ 2 K) -> (N, 3 K) (`contract`: the offset and the lookups run once per group, the decoder once per
light), both dimensions dynamic, and computes what `material.NeuMIPMaterial.forward` computes, in
three stages read top to bottom in `material_graph` (after the relief's march with `MaterialConfig.relief`,
and with the classical base's BSDF per light after the decoder with `MaterialConfig.base`): the neural offset (a bilinear lookup of the
offset texture, the offset MLP, the parallax shift), a trilinear lookup of the two nearest pyramid
levels, then the decoder MLP. The lookups work on one query per row; the MLPs on one query per
column (`GraphWriter.product`: the first layers read the weighted texels and the queries transposed,
one Transpose after each MLP). The file stores the textures once, in the layout `weights_from_state`
gives (flat atlas "pyramid" (T, C), "offset_texture" (R * R, C)); a constant subgraph that ONNX
Runtime folds at session load expands them into wrap-padded quad tables (`export_lookup.py`), so
each query reads one table row per level footprint with float row arithmetic and no modulo. The
model config, contract version and a description travel in the ONNX metadata.

The graph answers a query with the same bits whatever the batch it sits in (its position, the call's
row count, the thread count): it uses only ops that round per element - Mul, Add, Sub, Div, Sqrt,
Floor, Max, Min, Clip, Neg, GreaterOrEqual, Cast, Gather, and Gemm/MatMul, whose sums run in one order per row - and no Log (whose
vectorised tail rounds otherwise; the level of detail is `export_lod.py`) and no ReduceSum (which sums
a 1-row call in another order: taps are summed by a 0/1 MatMul instead).
tests/training/test_export_determinism.py checks it. benchmarks/bench_inference.py measures it
against the first export's graph (benchmarks/export_modulo.py).

`build_onnx` needs only numpy and onnx (weights as numpy arrays); `export_material` takes a torch
material, `export_checkpoint` reads a training checkpoint.
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

from neumip.core import contract as C

from neumip.core import head
from neumip.core import weights as W
from neumip.core.config import (BASE_ALPHA2_FLOOR, BASE_AZIMUTH_FLOOR, BASE_AZIMUTH_KERNEL, BASE_AZIMUTHS,
                                BASE_CHANNELS, BASE_COS_FLOOR, BASE_HORIZONS, BASE_LOG_CEILING, BASE_OUTPUTS,
                                BASE_SHADOW_SOFTNESS, BASE_WI_FLOOR, HALF_FLOOR, RELIEF_DIVISION_FLOOR,
                                RELIEF_MIN_COS, MaterialConfig)
from .export_lookup import (expand_table, footprint_read, footprint_rows, footprint_texels, pyramid_footprint,
                            pyramid_texels, texture_texels)
from .onnx_graph import GraphWriter

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
    if config.offset:
        weights[W.OFFSET_TEXTURE] = arr["offset_texture"].reshape(-1, config.offset_channels)
    for name in (W.BASE, W.RELIEF):
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


def _half_direction(g: GraphWriter, wi3: str, wo3: str) -> str:
    """(M, 3) unit wi, wo -> (M, 3) h = (wi + wo) / sqrt(max(|wi + wo|^2, HALF_FLOOR)) (`base.half_direction`)."""
    total = g.op("Add", wi3, wo3)
    return g.op("Div", total, g.op("Sqrt", g.op("Max", _dot(g, total, total), g.scalar(HALF_FLOOR))))


def _half_vector(g: GraphWriter, wi: str, wo: str) -> str:
    """wi, wo (M, 2) -> (M, 4): h = normalize(wi + wo) and cos(theta_d) = h . wi, as `material.half_vector`
    computes them (z = sqrt(max(1 - x^2 - y^2, 0)); sums of squares by MatMuls with ones)."""
    wi3, wo3 = _lift(g, wi), _lift(g, wo)
    h = _half_direction(g, wi3, wo3)
    return g.op("Concat", h, _dot(g, h, wi3), axis=1)


def _dot(g: GraphWriter, a: str, b: str) -> str:
    """(M, 3), (M, 3) -> (M, 1) a . b (summed by a MatMul with ones: one order per row)."""
    return g.op("MatMul", g.op("Mul", a, b), g.const(np.ones((3, 1), np.float32)))


def _lift(g: GraphWriter, w: str) -> str:
    """(M, 2) x, y of unit vectors -> (M, 3) with z = sqrt(max(1 - x^2 - y^2, 0))."""
    r2 = g.op("MatMul", g.op("Mul", w, w), g.const(np.ones((2, 1), np.float32)))
    return g.op("Concat", w, g.op("Sqrt", g.op("Max", g.op("Sub", g.scalar(1.0), r2), g.scalar(0.0))), axis=1)


MAP_CHANNELS = BASE_CHANNELS - BASE_HORIZONS
"""The base pyramid's channels that the BSDF reads once per group (colours, F0, slopes, alpha^2); the
horizons after them are read per light."""


@dataclass(frozen=True)
class _BaseRead:
    """The base pyramid read once per query group (`_base_maps`)."""

    maps: str
    """(N, MAP_CHANNELS) the BSDF's maps at the group's footprint."""
    rows: str
    """(N, 2) the footprint's quad rows of levels lo, hi (float), where `_horizon` reads per light."""
    taps: str
    """(N, 8) the footprint's tap weights."""
    horizons: str
    """(R BASE_HORIZONS, 4) horizon table: row r BASE_HORIZONS + j holds azimuth j's sine at quad row r's 4 taps."""


def _base_maps(g: GraphWriter, config: MaterialConfig, weights: dict, uv: str, sigma: str) -> _BaseRead:
    """The base pyramid's trilinear footprint at uv (N, 2) in [0, 1), sigma (N, 1): the maps, and where the
    horizons are read per light.

    A map channel that is the same in every texel (F0 of a material without metal, the colour of a plain
    one) is a constant of the graph, not read: the lookup of a constant answers it. The stored atlas is
    the whole one (`export_read` reads it back)."""
    base = config.base_pyramid()
    atlas = weights[W.BASE]
    stored = g.const(atlas, name=W.BASE)
    varying = [c for c in range(MAP_CHANNELS) if not np.all(atlas[:, c] == atlas[0, c])]
    fp = pyramid_footprint(g, base, g.op("Gather", stored, g.const(varying, np.int64), axis=1), len(varying),
                           sigma, prefix="base.")
    rows, taps = footprint_rows(g, fp, uv)  # (N, 2), (N, 8)
    index = g.const(fp.rows, np.int32)  # (R, 4) the quad table's texels, shared by both tables
    constants = np.where(np.isin(np.arange(MAP_CHANNELS), varying), 0.0, atlas[0, :MAP_CHANNELS])[None]
    if varying:
        fp.table = expand_table(g, fp.atlas, index, len(varying))
        texels = footprint_read(g, fp, len(varying), rows)  # (N, 8 V)
        spread = np.kron(np.eye(8, dtype=np.float32), np.ones((1, len(varying)), np.float32))  # (8, 8 V)
        weighted = g.op("Mul", texels, g.op("MatMul", taps, g.const(spread)))
        summed = g.op("MatMul", weighted, g.const(np.tile(np.eye(len(varying), dtype=np.float32), (8, 1))))
        place = np.zeros((len(varying), MAP_CHANNELS), np.float32)
        place[np.arange(len(varying)), varying] = 1.0
        maps = g.op("Add", g.op("MatMul", summed, g.const(place)), g.const(constants))
    else:
        maps = g.op("Add", g.op("MatMul", taps, g.const(np.zeros((8, MAP_CHANNELS), np.float32))), g.const(constants))
    return _BaseRead(maps, rows, taps, _horizon_table(g, stored, index, len(fp.rows)))


def _horizon_table(g: GraphWriter, atlas: str, index: str, rows: int) -> str:
    """Constant subgraph: the base atlas (T, BASE_CHANNELS) and its quad index table (R, 4) -> (R BASE_HORIZONS,
    4) the horizons' quad table, one row per quad row and azimuth (`_BaseRead.horizons`)."""
    if rows * BASE_HORIZONS >= 2**24:
        raise ValueError(f"{rows} base table rows: the horizons' float32 row arithmetic is exact only below "
                         f"2^24 / {BASE_HORIZONS}")
    columns = g.const(np.arange(MAP_CHANNELS, BASE_CHANNELS), np.int64)
    flat = g.shape(g.op("Gather", atlas, columns, axis=1), [-1])  # (T BASE_HORIZONS,): texel t, azimuth j at t H + j
    texel = g.op("Cast", g.shape(index, [-1, 1, 4]), to=TensorProto.INT64)  # (R, 1, 4)
    azimuths = g.const(np.arange(BASE_HORIZONS).reshape(1, -1, 1), np.int64)  # (1, H, 1)
    entries = g.op("Add", g.op("Mul", texel, g.const([BASE_HORIZONS], np.int64)), azimuths)  # (R, H, 4)
    return g.op("Gather", flat, g.shape(entries, [-1, 4]), axis=0)


def _horizon(g: GraphWriter, read: _BaseRead, rows: str, taps: str, wi: str) -> str:
    """The sine of the horizon's elevation towards each light, as `base.visibility` interpolates it: (M, 2)
    quad rows and (M, 8) tap weights of the base footprint, (M, 2) wi -> (M, 1).

    Of the BASE_HORIZONS azimuths' weights max(cos(phi - phi_j) - cos(45 deg), 0) only the two azimuths
    around wi's can be nonzero (j0 = floor(phi / 45 deg) and j0 + 1), so only their columns are read, per
    light: 16 texels, not the 64 of all eight azimuths at the footprint's 8 taps."""
    if BASE_HORIZONS != 8:
        raise ValueError("the octant arithmetic below assumes 8 horizon azimuths")
    x, y = g.pick(wi, 2, [0]), g.pick(wi, 2, [1])
    below = g.op("Less", y, g.scalar(0.0))  # phi in [180, 360): turn by 180 degrees
    x1, y1 = g.op("Where", below, g.op("Neg", x), x), g.op("Where", below, g.op("Neg", y), y)
    left = g.op("LessOrEqual", x1, g.scalar(0.0))  # phi in [90, 180]: turn by -90 degrees
    x2, y2 = g.op("Where", left, y1, x1), g.op("Where", left, g.op("Neg", x1), y1)
    upper = g.op("GreaterOrEqual", y2, x2)  # phi in [45, 90]

    def count(b: str, k: float) -> str:
        return g.op("Mul", g.op("Cast", b, to=TensorProto.FLOAT), g.scalar(k))

    j0 = g.op("Add", g.op("Add", count(below, 4.0), count(left, 2.0)), count(upper, 1.0))  # (M, 1) in 0..7
    j1 = g.op("Sub", g.op("Add", j0, g.scalar(1.0)), count(g.op("GreaterOrEqual", j0, g.scalar(7.0)), 8.0))
    pair = g.op("Concat", j0, j1, axis=1)  # (M, 2)
    # cos(phi - phi_j) for j0, j1: phi turned by the octant's quarter turns is in [0, 90], phi_j0 in it is 45 upper
    diagonal = g.op("Mul", g.op("Add", x2, y2), g.scalar(math.sqrt(0.5)))
    r2 = g.op("MatMul", g.op("Mul", wi, wi), g.const(np.ones((2, 1), np.float32)))
    r = g.op("Sqrt", g.op("Max", r2, g.scalar(BASE_AZIMUTH_FLOOR * BASE_AZIMUTH_FLOOR)))
    cosines = [g.op("Div", g.op("Where", upper, diagonal, x2), r), g.op("Div", g.op("Where", upper, y2, diagonal), r)]
    kernel = g.op("Max", g.op("Sub", g.op("Concat", *cosines, axis=1), g.scalar(BASE_AZIMUTH_KERNEL)), g.scalar(0.0))
    total = g.op("MatMul", kernel, g.const(np.ones((2, 1), np.float32)))
    weight = g.op("Div", kernel, g.op("Max", total, g.scalar(BASE_AZIMUTH_FLOOR)))  # (M, 2)
    # table rows (M, 4): (lo, j0), (lo, j1), (hi, j0), (hi, j1); each holds 4 taps
    at = np.array([[8.0, 8.0, 0.0, 0.0], [0.0, 0.0, 8.0, 8.0]], np.float32)
    of = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]], np.float32)
    line = g.op("Add", g.op("MatMul", rows, g.const(at)), g.op("MatMul", pair, g.const(of)))
    texels = g.shape(g.op("Gather", read.horizons, g.op("Cast", line, to=TensorProto.INT64), axis=0), [-1, 16])
    spread = np.zeros((8, 16), np.float32)  # tap weight (level l, tap t) -> columns (l, a, t) for a = j0, j1
    pick = np.zeros((16, 2), np.float32)  # columns (l, a, t) -> azimuth a
    for level in range(2):
        for a in range(2):
            for t in range(4):
                spread[4 * level + t, 8 * level + 4 * a + t] = 1.0
                pick[8 * level + 4 * a + t, a] = 1.0
    sines = g.op("MatMul", g.op("Mul", texels, g.op("MatMul", taps, g.const(spread))), g.const(pick))  # (M, 2)
    return g.op("MatMul", g.op("Mul", weight, sines), g.const(np.ones((2, 1), np.float32)))


def _base_normal(g: GraphWriter, maps: str) -> str:
    """maps (M, MAP_CHANNELS) -> (M, 3) the base's normal normalize(-dh/du, -dh/dv, 1)."""
    to_normal = np.zeros((MAP_CHANNELS, 3), np.float32)
    to_normal[6, 0] = to_normal[7, 1] = -1.0
    n = g.op("Add", g.op("MatMul", maps, g.const(to_normal)), g.const(np.array([[0.0, 0.0, 1.0]], np.float32)))
    return g.op("Div", n, g.op("Sqrt", _dot(g, n, n)))


def _frame_inputs(g: GraphWriter, maps: str, wi: str, wo: str) -> str:
    """maps (M, MAP_CHANNELS), wi, wo (M, 2) -> (M, 6) wi and wo in the base normal's frame, as
    `base.frame_inputs` computes them."""
    n = _base_normal(g, maps)
    nx, ny, nz = (g.pick(n, 3, [i]) for i in range(3))
    a = g.op("Div", g.scalar(1.0), g.op("Add", nz, g.scalar(1.0)))
    cross = g.op("Mul", g.op("Mul", g.op("Neg", nx), ny), a)
    t = g.op("Concat", g.op("Sub", g.scalar(1.0), g.op("Mul", g.op("Mul", nx, nx), a)), cross, g.op("Neg", nx), axis=1)
    b = g.op("Concat", cross, g.op("Sub", g.scalar(1.0), g.op("Mul", g.op("Mul", ny, ny), a)), g.op("Neg", ny), axis=1)
    return g.op("Concat", *(_dot(g, w, f) for w in (_lift(g, wi), _lift(g, wo)) for f in (t, b, n)), axis=1)


def _base_answer(g: GraphWriter, maps: str, horizon: str, wi: str, wo: str) -> str:
    """maps (M, MAP_CHANNELS), the horizon's sine towards wi (M, 1) (`_horizon`), wi, wo (M, 2) -> (M, 3): the
    base's answer, as `base.base_answer` computes it."""
    def columns(lo: int, hi: int) -> str:
        return g.pick(maps, MAP_CHANNELS, list(range(lo, hi)))

    def clamp_low(x: str, low: float) -> str:
        return g.op("Max", x, g.scalar(low))

    wi3, wo3 = _lift(g, wi), _lift(g, wo)
    n = _base_normal(g, maps)
    h = _half_direction(g, wi3, wo3)
    alpha2 = clamp_low(columns(8, 9), BASE_ALPHA2_FLOOR)
    cos_i, cos_o, cos_h = (clamp_low(_dot(g, n, w), 0.0) for w in (wi3, wo3, h))
    d = g.op("Add", g.op("Mul", g.op("Mul", cos_h, cos_h), g.op("Sub", alpha2, g.scalar(1.0))), g.scalar(1.0))
    distribution = g.op("Div", alpha2, g.op("Mul", g.op("Mul", d, d), g.scalar(math.pi)))

    def smith_g1(c: str) -> str:
        root = g.op("Sqrt", g.op("Add", alpha2, g.op("Mul", g.op("Sub", g.scalar(1.0), alpha2), g.op("Mul", c, c))))
        return g.op("Div", g.op("Mul", c, g.scalar(2.0)), g.op("Add", c, root))

    f0 = columns(3, 6)
    s = g.op("Sub", g.scalar(1.0), g.op("Min", clamp_low(_dot(g, h, wi3), 0.0), g.scalar(1.0)))
    s2 = g.op("Mul", s, s)
    schlick = g.op("Mul", g.op("Mul", s2, s2), s)
    fresnel = g.op("Add", f0, g.op("Mul", g.op("Sub", g.scalar(1.0), f0), schlick))
    masking = g.op("Mul", g.op("Mul", distribution, smith_g1(cos_i)), smith_g1(cos_o))
    specular = g.op("Div", g.op("Mul", masking, fresnel), g.op("Mul", clamp_low(cos_o, BASE_COS_FLOOR), g.scalar(4.0)))
    diffuse = g.op("Mul", columns(0, 3), g.op("Div", cos_i, g.scalar(math.pi)))
    z = g.const(np.array([[0.0], [0.0], [1.0]], np.float32))
    wi_z = g.op("MatMul", wi3, z)
    terminator = g.op("Min", g.op("Div", wi_z, clamp_low(g.op("Mul", cos_i, g.op("MatMul", n, z)), BASE_COS_FLOOR)),
                      g.scalar(1.0))
    soften = g.op("Mul", terminator, g.op("Sub", g.op("Add", g.scalar(1.0), terminator), g.op("Mul", terminator, terminator)))
    lit = g.op("Add", g.op("Div", g.op("Sub", wi_z, horizon), g.scalar(BASE_SHADOW_SOFTNESS)), g.scalar(0.5))
    lit = g.op("Min", g.op("Max", lit, g.scalar(0.0)), g.scalar(1.0))  # the visibility V(wi), `base.visibility`
    return g.op("Div", g.op("Mul", g.op("Mul", g.op("Add", diffuse, specular), soften), lit), clamp_low(wi_z, BASE_WI_FLOOR))


def _corrected(g: GraphWriter, base: str, out: str) -> str:
    """base (M, 3), decoder output (M, BASE_OUTPUTS) -> base * exp(min(c, ceiling)) + a (`base.corrected`)."""
    log_part = np.zeros((BASE_OUTPUTS, 3), np.float32)
    log_part[:3] = np.eye(3)
    add_part = np.zeros((BASE_OUTPUTS, 3), np.float32)
    add_part[3:] = np.eye(3)
    c = g.op("Min", g.op("MatMul", out, g.const(log_part)), g.scalar(BASE_LOG_CEILING))
    return g.op("Add", g.op("Mul", base, g.op("Exp", c)), g.op("MatMul", out, g.const(add_part)))


def _relief(g: GraphWriter, config: MaterialConfig, weights: dict, uv: str, sigma: str, wo: str) -> str:
    """uv (N, 2), sigma (N, 1), wo (N, 2) -> (N, 2) the relief's shift of the lookups, as `relief.relief_shift`
    computes it: one footprint of the height pyramid, read at each step's position."""
    heights = weights[W.RELIEF]
    depth = np.float32(max(-float(heights.min()), 0.0))
    steps = config.relief_steps
    fp = pyramid_footprint(g, config.relief_pyramid(), g.const(heights, name=W.RELIEF), 1, sigma, prefix="relief.")
    d = g.op("Div", wo, _clamped_wo_z(g, wo, RELIEF_MIN_COS))
    ones = g.const(np.ones((8, 1), np.float32))
    found = missed = s_prev = None
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
    found = g.op("Add", found, g.op("Mul", missed, g.scalar(depth)))
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
    unless trimmed).
    """
    q = g.op("Slice", C.ONNX_INPUT, g.const([0], np.int64), g.const([C.QUERY_DIM], np.int64),
             g.const([1], np.int64))  # (N, 7): each group's first query
    uv, sigma, wo = _query_columns(g, q)

    # --- relief: uv moves to where the view ray first meets the height field --------------------
    if config.relief:
        uv = g.op("Add", uv, _relief(g, config, weights, uv, sigma, wo))

    # --- neural offset: uv += r * wo_xy / max(wo_z, min_cos) -----------------------------------
    if config.offset:
        texture = g.const(weights[W.OFFSET_TEXTURE], name=W.OFFSET_TEXTURE)
        texels, tap_w = texture_texels(g, texture, config.resolution, config.offset_channels, g.wrap(uv))
        mlp = _depth_weights(weights, config)
        hidden = _first_layer(g, q, texels, tap_w, 4, [C.WO_X, C.WO_Y], mlp, W.OFFSET_MLP, 2)
        if config.layers > 1:
            hidden = g.op("Relu", hidden)
        depth = g.op("Transpose", g.mlp(hidden, mlp, W.OFFSET_MLP, config.layers, first=1), perm=[1, 0])  # (N, 2)
        uv = g.op("Add", uv, _parallax(g, depth, wo, config.offset_min_cos))

    # --- trilinear pyramid lookup, then the decoder once per light -------------------------------
    atlas = g.const(weights[W.PYRAMID], name=W.PYRAMID)
    uvw = g.wrap(uv)
    texels, tap_w = pyramid_texels(g, config, atlas, config.channels, uvw, sigma, finest_level)
    half_inputs = W.HALF_INPUTS if config.half_vector else 0
    frame_inputs = W.FRAME_INPUTS if config.local_frame else 0
    shared = _first_layer(g, q, texels, tap_w, 8, [C.WO_X, C.WO_Y], weights, W.DECODER,
                          4 + half_inputs + frame_inputs)  # (hidden, N)
    read = _base_maps(g, config, weights, uvw, sigma) if config.local_frame else None  # (the decoder reads it)
    wi, n, k, kn = _lights(g, q)  # (K N, 2)
    per_light: list[str] = []  # Tile repeats of a group's row, light-major (made when a stage needs it)

    def each_light(x: str) -> str:
        """A group's rows (N, F) -> (K N, F), row j N + n that of group n."""
        if not per_light:
            per_light.append(g.op("Concat", k, g.const([1], np.int64), axis=0))
        return g.op("Tile", x, per_light[0])

    w = weights[W.weight(W.DECODER, 0)]
    light = g.product(w[:, -4:-2], wi, rows=True, name=W.half_weight(W.DECODER, 0, "light"))  # (hidden, K N)
    hidden = g.op("Add", g.op("Tile", shared, g.op("Concat", g.const([1], np.int64), k, axis=0)), light)
    if config.half_vector:  # per light: h and cos(theta_d) from its wi and the group's wo
        texture = config.channels
        half = g.product(w[:, texture : texture + half_inputs], _half_vector(g, wi, each_light(wo)), rows=True,
                         name=W.half_weight(W.DECODER, 0, "half_vector"))  # (hidden, K N)
        hidden = g.op("Add", hidden, half)
    if config.local_frame:  # per light: wi and the group's wo in the frame of the group's base normal
        first = config.channels + half_inputs
        frame = g.product(w[:, first : first + frame_inputs], _frame_inputs(g, each_light(read.maps), wi, each_light(wo)),
                          rows=True, name=W.half_weight(W.DECODER, 0, "frame"))  # (hidden, K N)
        hidden = g.op("Add", hidden, frame)
    if config.layers > 1:
        hidden = g.op("Relu", hidden)
    out = g.op("Transpose", g.mlp(hidden, weights, W.DECODER, config.layers, first=1), perm=[1, 0])  # (K N, O)
    size = head.outputs(config.head)
    if config.base:  # per light: the base's answer from the group's maps, corrected by the decoder
        read = read or _base_maps(g, config, weights, uvw, sigma)
        horizon = _horizon(g, read, each_light(read.rows), each_light(read.taps), wi)  # (K N, 1)
        out = _corrected(g, _base_answer(g, each_light(read.maps), horizon, wi, each_light(wo)), out)
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

    With ``finest_level`` K > 0 the pyramid holds levels K..L only (`trim.trim_model` makes such a
    model from an exported one) and finer queries read level K.
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
    """Write `model` to `path` atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(model.SerializeToString())
    os.replace(tmp, path)
    return path


def export_material(material, out: str | Path, description: str = "", validation: dict | None = None) -> Path:
    """Write a torch `NeuMIPMaterial` (its weights as they are) to `out` as an ONNX model, with its
    validation table (if given) in the metadata."""
    meta = {C.META_VALIDATION: json.dumps(validation)} if validation is not None else {}
    weights = weights_from_state(material.state_dict(), material.config)
    return save_onnx(build_onnx(material.config, weights, description, meta), out)


def export_checkpoint(checkpoint: str | Path, out: str | Path, description: str = "") -> Path:
    """`neumip export`: read a training checkpoint, write the ONNX model.

    A checkpoint written mid-run holds raw textures while training evaluated blurred copies: the
    blur of its step is baked in first, so the model computes what training computed.
    """
    from .blur import bake_checkpoint_textures  # torch only here
    from .checkpoint import load

    material, extra = load(checkpoint)
    if bake_checkpoint_textures(material, extra):
        log.warning(
            "%s was written mid-run (step %d): exporting with that step's blurred textures",
            checkpoint, extra["state"]["step"],
        )
    description = description or extra.get("description", "")
    return export_material(material, out, description, extra.get("validation"))


# --- weight factories (no torch): known-answer and random materials for tests and benchmarks ------


def random_weights(config: MaterialConfig, seed: int = 0, scale: float = 0.5) -> dict[str, np.ndarray]:
    """Random weights of the right shapes: a material whose answers are positive and vary with
    position, footprint and directions in every channel, whatever the seed.

    Textures are N(0, scale^2) (a base's maps: colours, slopes and alpha^2 in their ranges); every layer's weights N(0, 2 / fan_in) (He: the signal keeps its size
    through the ReLUs), hidden biases small and positive (units stay alive). The decoder's last layer
    has positive weights on ReLU outputs (>= 0) and a positive bias, so each channel answers its bias
    plus a query-dependent non-negative sum (with one layer only the bias is positive).
    """
    rng = np.random.default_rng(seed)
    out = {}
    last = W.weight(W.DECODER, config.layers - 1)
    for name, shape in W.weight_shapes(config).items():
        if name.endswith("weight"):
            w = rng.normal(size=shape) * np.sqrt(2.0 / shape[1])
            out[name] = np.abs(w) * (scale / shape[1]) ** 0.5 if name == last and config.layers > 1 else w
        elif name.endswith("bias"):
            out[name] = (rng.uniform(0.1, 0.3, shape) if name == W.bias(W.DECODER, config.layers - 1)
                         else rng.uniform(0.0, 0.1, shape))
        elif name == W.BASE:  # maps a base can hold: colours and F0 in [0, 1), slopes, alpha^2 in (0, 1), horizons
            out[name] = np.concatenate([rng.uniform(0, 1, (shape[0], 6)), rng.normal(size=(shape[0], 2)) * 0.5,
                                        rng.uniform(0.01, 1, (shape[0], 1)), rng.uniform(0, 0.6, (shape[0], shape[1] - 9))],
                                       axis=1)
        elif name == W.RELIEF:  # a smooth periodic relief `scale` / 4 tile deep, the same at every level
            out[name] = _random_relief(config.relief_pyramid().level_sizes(), rng, scale / 4)
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
    out[W.bias(W.DECODER, config.layers - 1)] = head.answer_bias(config.head, rgb)
    return out
