"""The first export's graph, kept as the baseline `bench_inference.py` compares the shipped one with.

It gathers 8 single texels per query from the flat atlas (+4 from the offset texture) and does the
wrap-around index arithmetic in int64 with Mod, as `training/model/pyramid.py` writes it. Like the shipped
graph it reads the level of detail from `lod.py` and sums taps with a 0/1 MatMul, so its
answers do not depend on the batch. The shipped graph (`neumip.training.export.graph`) reads wrap-padded
quad tables instead: one Gather row per level footprint, no Mod, and runs its MLPs column-major.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper

from neumip.core import contract as C
from neumip.core.config import MaterialConfig
from neumip.training.export.graph import IR_VERSION, OPSET
from neumip.training.export.lod import level_of_detail
from neumip.training.export.onnx_graph import GraphWriter


def _bilinear(g: GraphWriter, u: str, v: str, size: str, start: str) -> tuple[str, str]:
    """u, v (N, 1) in [0, 1]; size, start (N, L) or (1, 1) int64 -> rows, weights (N, L, 4)."""
    sizef = g.op("Cast", size, to=TensorProto.FLOAT)
    half, one = g.const(0.5), g.const(1.0)
    x = g.op("Sub", g.op("Mul", u, sizef), half)
    y = g.op("Sub", g.op("Mul", v, sizef), half)
    x0f, y0f = g.op("Floor", x), g.op("Floor", y)
    fx, fy = g.op("Sub", x, x0f), g.op("Sub", y, y0f)
    x0 = g.op("Mod", g.op("Cast", x0f, to=TensorProto.INT64), size)
    y0 = g.op("Mod", g.op("Cast", y0f, to=TensorProto.INT64), size)
    one_i = g.const(1, np.int64)
    x1 = g.op("Mod", g.op("Add", x0, one_i), size)
    y1 = g.op("Mod", g.op("Add", y0, one_i), size)
    row0 = g.op("Add", start, g.op("Mul", y0, size))
    row1 = g.op("Add", start, g.op("Mul", y1, size))
    axis = g.const([-1], np.int64)
    taps = [g.op("Add", r, c) for r, c in ((row0, x0), (row0, x1), (row1, x0), (row1, x1))]
    rows = g.op("Concat", *[g.op("Unsqueeze", t, axis) for t in taps], axis=-1)
    gx, gy = g.op("Sub", one, fx), g.op("Sub", one, fy)
    ws = [g.op("Mul", a, b) for a, b in ((gx, gy), (fx, gy), (gx, fy), (fx, fy))]
    weights = g.op("Concat", *[g.op("Unsqueeze", w, axis) for w in ws], axis=-1)
    return rows, weights


def _gather_blend(g: GraphWriter, table: str, rows: str, weights: str, taps: int, channels: int) -> str:
    """Gather `taps` rows per query of (T, C) `table` and blend with `weights` -> (N, C).

    The weighted texels are summed by a 0/1 MatMul, which adds them in one order whatever the batch
    (ReduceSum sums a 1-row call in another order).
    """
    flat = g.const([-1, taps], np.int64)
    texels = g.op("Gather", table, g.op("Reshape", rows, flat), axis=0)  # (N, K, C)
    weights = g.op("Unsqueeze", g.op("Reshape", weights, flat), g.const([-1], np.int64))
    weighted = g.shape(g.op("Mul", texels, weights), [-1, taps * channels])  # (N, K C)
    return g.op("MatMul", weighted, g.const(np.tile(np.eye(channels, dtype=np.float32), (taps, 1))))


def _mlp(g: GraphWriter, x: str, weights: dict, prefix: str, layers: int) -> str:
    """(N, in) -> (N, out): one Gemm (W transposed) + Relu per layer, no Relu after the last."""
    for i in range(layers):
        w, b = (g.const(weights[f"{prefix}.{i}.{part}"]) for part in ("weight", "bias"))
        x = g.op("Gemm", x, w, b, transB=1)
        x = g.op("Relu", x) if i < layers - 1 else x
    return x


def modulo_graph(g: GraphWriter, config: MaterialConfig, weights: dict[str, np.ndarray]) -> str:
    """Queries (N, 7) (graph input) -> decoder output (N, 3) before the final Relu."""
    cols = g.op("Split", C.ONNX_INPUT, axis=1, num_outputs=C.QUERY_DIM, outputs=C.QUERY_DIM)
    u, v, sigma, wi_x, wi_y, wo_x, wo_y = cols

    # --- neural offset: u += r * wo_xy / max(wo_z, min_cos) ------------------------------------
    if config.offset:
        res = g.const([[config.resolution]], np.int64)
        rows, w = _bilinear(g, g.wrap(u), g.wrap(v), res, g.const([[0]], np.int64))
        otex = g.const(weights["offset_texture"], name="offset_texture")
        feat = _gather_blend(g, otex, rows, w, 4, config.offset_channels)
        depth = _mlp(g, g.op("Concat", feat, wo_x, wo_y, axis=1), weights, "offset_mlp", config.layers)
        depth = g.op("Mul", depth, g.const(config.offset_scale))
        one = g.const(1.0)
        r2 = g.op("Add", g.op("Mul", wo_x, wo_x), g.op("Mul", wo_y, wo_y))
        wo_z = g.op("Sqrt", g.op("Max", g.op("Sub", one, r2), g.const(0.0)))
        scale = g.op("Div", depth, g.op("Max", wo_z, g.const(config.offset_min_cos)))
        u = g.op("Add", u, g.op("Mul", scale, wo_x))
        v = g.op("Add", v, g.op("Mul", scale, wo_y))

    # --- trilinear pyramid lookup ----------------------------------------------------------------
    sizes, starts = np.asarray(config.level_sizes()), np.asarray(config.level_starts())
    hi = np.minimum(np.arange(config.levels + 1) + 1, config.levels)
    tables = {"size": np.stack([sizes, sizes[hi]], 1), "start": np.stack([starts, starts[hi]], 1)}
    rows, t = level_of_detail(g, sigma, config, tables=tables)  # levels lo and hi: (N, 2) each, (N, 1)
    size, start = (g.op("Cast", rows[name], to=TensorProto.INT64) for name in ("size", "start"))
    rows, w = _bilinear(g, g.wrap(u), g.wrap(v), size, start)  # (N, 2, 4)
    level_w = g.op("Concat", g.op("Sub", g.const(1.0), t), t, axis=1)
    w = g.op("Mul", w, g.op("Unsqueeze", level_w, g.const([-1], np.int64)))
    atlas = g.const(weights["pyramid"], name="pyramid")
    features = _gather_blend(g, atlas, rows, w, 8, config.channels)

    # --- decoder ---------------------------------------------------------------------------------
    x = g.op("Concat", features, wi_x, wi_y, wo_x, wo_y, axis=1)
    return _mlp(g, x, weights, "decoder", config.layers)


def modulo_onnx(config: MaterialConfig, weights: dict[str, np.ndarray]) -> onnx.ModelProto:
    """The first export's model: (N, 7) float32 queries -> (N, 3) float32 RGB (no metadata)."""
    g = GraphWriter()
    rgb = modulo_graph(g, config, weights)
    g.nodes.append(helper.make_node("Relu", [rgb], [C.ONNX_OUTPUT]))
    return g.model(C.ONNX_INPUT, C.QUERY_DIM, C.ONNX_OUTPUT, C.RGB_DIM, OPSET, IR_VERSION)
