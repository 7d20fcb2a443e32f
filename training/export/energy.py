"""ONNX stage of the answers' energy table (`MaterialConfig.energy_bins`), as `training.model.energy.energy_gain`
computes it: the table is a 3-D texture of RGB gains (level of detail, half-vector angle, light elevation), read per
light as a texture is, its 8 corner cells Gathered in one call and weighted trilinearly (the taps summed by a 0/1
MatMul: one order per row). The table is the initializer ``energy`` ((L + 1) B^2, 3), every level's cells (a
trimmed model keeps them all: its level of detail is clamped at its finest level, so the answers above the cut keep
their bits)."""

from __future__ import annotations

import numpy as np
from onnx import TensorProto

from neumip.core import weights as W
from neumip.core.config import MaterialConfig
from neumip.training.export import base as B
from neumip.training.export.lod import level_of_detail
from neumip.training.export.onnx_graph import GraphWriter

ENERGY_PREFIX = "energy."
"""Prefix of the energy stage's level-of-detail constants (``energy.lod.*``)."""


CORNERS = [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1)]
"""The 8 corners of a trilinear read: (level, half-vector bin, elevation bin), each 0 (lower) or 1 (upper)."""


def _pairs(g: GraphWriter, x: str, top: int) -> tuple[str, str]:
    """x (M, 1) in [0, top] -> its lower and upper nodes (M, 2), both at most `top`, and their weights (M, 2)."""
    low = g.op("Floor", x)
    frac = g.op("Sub", x, low)
    nodes = g.op("Concat", low, g.op("Min", g.op("Add", low, g.scalar(1.0)), g.scalar(float(top))), axis=1)
    return nodes, g.op("Concat", g.op("Sub", g.scalar(1.0), frac), frac, axis=1)


def group_lod(g: GraphWriter, config: MaterialConfig, sigma: str, finest_level: int = 0,
              prefix: str = ENERGY_PREFIX) -> str:
    """The groups' sigma (N, 1) -> their latents' level of detail (N, 1) in [K, L], K = ``finest_level``."""
    rows, t = level_of_detail(g, sigma, config, finest_level, {"level": np.arange(config.levels + 1.0)[:, None]},
                              prefix)
    return g.op("Add", rows["level"], t)


def energy_gain(g: GraphWriter, config: MaterialConfig, table: np.ndarray, sigma: str, wi: str, wo: str,
                each_light, finest_level: int = 0, lod: str | None = None) -> str:
    """The groups' sigma (N, 1), each light's wi and wo (K N, 2) -> the gains (K N, 3); `each_light` repeats a
    group's rows per light (`graph.material_graph`); ``lod``: the groups' `group_lod`, where the graph has it."""
    bins, top = config.energy_bins, float(config.energy_bins - 1)
    lod = each_light(lod or group_lod(g, config, sigma, finest_level))  # (K N, 1) in [K, L]
    wi3 = B.lift(g, wi)
    h = B.half_direction(g, wi3, B.lift(g, wo))  # (K N, 3)
    s = g.op("Sqrt", g.op("Max", g.op("Sub", g.scalar(2.0), g.op("Mul", g.pick(h, 3, [2]), g.scalar(2.0))),
                          g.scalar(0.0)))
    x = g.op("Min", g.op("Mul", s, g.scalar(top / np.sqrt(2.0))), g.scalar(top))  # (K N, 1) half-vector bin
    y = g.op("Min", g.op("Mul", g.op("Sqrt", g.pick(wi3, 3, [2])), g.scalar(top)), g.scalar(top))  # elevation bin
    axes = [_pairs(g, v, n) for v, n in ((lod, config.levels), (x, bins - 1), (y, bins - 1))]
    # each corner's row (B l + b) B + e and weight w_l w_b w_e: sums and products over the axes' pairs, by MatMuls
    strides = (bins * bins, bins, 1)
    place = np.zeros((6, 8), np.float32)
    pick = [np.zeros((2, 8), np.float32) for _ in range(3)]
    for k, corner in enumerate(CORNERS):
        for a, side in enumerate(corner):
            place[2 * a + side, k] = strides[a]
            pick[a][side, k] = 1.0
    nodes = g.op("Concat", *(n for n, _ in axes), axis=1)  # (K N, 6)
    index = g.op("Cast", g.op("MatMul", nodes, g.const(place)), to=TensorProto.INT64)  # (K N, 8): exact integers
    weight = g.op("Mul", g.op("Mul", g.op("MatMul", axes[0][1], g.const(pick[0])),
                              g.op("MatMul", axes[1][1], g.const(pick[1]))),
                  g.op("MatMul", axes[2][1], g.const(pick[2])))  # (K N, 8)
    cells = g.shape(g.op("Gather", g.const(np.asarray(table, np.float32), name=W.ENERGY), index, axis=0),
                    [0, 8 * 3])  # (K N, 24): corner-major, RGB
    spread = np.kron(np.eye(8, dtype=np.float32), np.ones((1, 3), np.float32))  # (8, 24)
    total = np.tile(np.eye(3, dtype=np.float32), (8, 1))  # (24, 3)
    return g.op("MatMul", g.op("Mul", cells, g.op("MatMul", weight, g.const(spread))), g.const(total))  # (K N, 3)
