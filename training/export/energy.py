"""ONNX stage of the answers' energy table (`MaterialConfig.energy_bins`), as `training.model.energy.energy_gain`
computes it: the table is a 3-D texture of RGB gains (level of detail, half-vector angle, light elevation; with
`energy_azimuths` a 4-D one, the half vector's azimuth fourth), read per light as a texture is, its 8 (16) corner
cells Gathered in one call and weighted multilinearly (the taps summed by a 0/1 MatMul: one order per row). The
table is the initializer ``energy`` (`weights.energy_rows`, 3, or 1 with `energy_luminance`), every level's cells (a trimmed model keeps them all:
its level of detail is clamped at its finest level, so the answers above the cut keep their bits)."""

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


def corner_list(axes: int) -> list[tuple[int, ...]]:
    """The 2^axes corners of a multilinear read, each axis 0 (lower) or 1 (upper), the first axis slowest: (level,
    half-vector bin, elevation bin[, azimuth bin]), as `training.model.energy.corners` orders them."""
    return [tuple((k >> (axes - 1 - a)) & 1 for a in range(axes)) for k in range(2**axes)]


def _pairs(g: GraphWriter, x: str, top: int) -> tuple[str, str]:
    """x (M, 1) in [0, top] -> its lower and upper nodes (M, 2), both at most `top`, and their weights (M, 2)."""
    low = g.op("Floor", x)
    frac = g.op("Sub", x, low)
    nodes = g.op("Concat", low, g.op("Min", g.op("Add", low, g.scalar(1.0)), g.scalar(float(top))), axis=1)
    return nodes, g.op("Concat", g.op("Sub", g.scalar(1.0), frac), frac, axis=1)


def _periodic_pairs(g: GraphWriter, a: str, period: int) -> tuple[str, str]:
    """a (M, 1) in [0, period] -> its lower and upper nodes (M, 2) in [0, period) (the upper wraps to 0) and their
    weights (M, 2)."""
    low = g.op("Min", g.op("Floor", a), g.scalar(period - 1.0))
    frac = g.op("Sub", a, low)
    up = g.op("Add", low, g.scalar(1.0))
    high = g.op("Where", g.op("GreaterOrEqual", up, g.scalar(float(period))), g.scalar(0.0), up)
    return g.op("Concat", low, high, axis=1), g.op("Concat", g.op("Sub", g.scalar(1.0), frac), frac, axis=1)


def _azimuth(g: GraphWriter, h: str, azimuths: int) -> str:
    """The half vectors h (M, 3) -> their pseudo-angle azimuth (M, 1) in [0, azimuths], as
    `training.model.energy.azimuth_coordinate`."""
    x, y = g.pick(h, 3, [0]), g.pick(h, 3, [1])
    ratio = g.op("Div", x, g.op("Max", g.op("Add", g.op("Abs", x), g.op("Abs", y)), g.scalar(1e-30)))
    turn = g.op("Where", g.op("GreaterOrEqual", y, g.scalar(0.0)), g.op("Sub", g.scalar(1.0), ratio),
                g.op("Add", g.scalar(3.0), ratio))
    return g.op("Mul", turn, g.scalar(azimuths / 4.0))


def group_lod(g: GraphWriter, config: MaterialConfig, sigma: str, finest_level: int = 0,
              prefix: str = ENERGY_PREFIX) -> str:
    """The groups' sigma (N, 1) -> their latents' level of detail (N, 1) in [K, L], K = ``finest_level``."""
    rows, t = level_of_detail(g, sigma, config, finest_level, {"level": np.arange(config.levels + 1.0)[:, None]},
                              prefix)
    return g.op("Add", rows["level"], t)


def energy_gain(g: GraphWriter, config: MaterialConfig, table: np.ndarray, sigma: str, wi: str, wo: str,
                each_light, finest_level: int = 0, lod: str | None = None) -> str:
    """The groups' sigma (N, 1), each light's wi and wo (K N, 2) -> the gains (K N, 3), or (K N, 1) for a table of one
    gain a cell (`MaterialConfig.energy_luminance`); `each_light` repeats a
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
    sizes = [config.levels + 1, bins, bins]
    if config.energy_azimuths:
        axes.append(_periodic_pairs(g, _azimuth(g, h, config.energy_azimuths), config.energy_azimuths))
        sizes.append(config.energy_azimuths)
    strides = [int(np.prod(sizes[a + 1:])) for a in range(len(axes))]  # row ((B l + b) B + e) A + a
    # each corner's row and weight (the product of its axes' weights): sums and products over the pairs, by MatMuls
    corners = corner_list(len(axes))
    place = np.zeros((2 * len(axes), len(corners)), np.float32)
    pick = [np.zeros((2, len(corners)), np.float32) for _ in axes]
    for k, corner in enumerate(corners):
        for a, side in enumerate(corner):
            place[2 * a + side, k] = strides[a]
            pick[a][side, k] = 1.0
    nodes = g.op("Concat", *(n for n, _ in axes), axis=1)  # (K N, 2 axes)
    index = g.op("Cast", g.op("MatMul", nodes, g.const(place)), to=TensorProto.INT64)  # (K N, corners): exact
    weight = g.op("MatMul", axes[0][1], g.const(pick[0]))
    for (_, w), p in zip(axes[1:], pick[1:]):
        weight = g.op("Mul", weight, g.op("MatMul", w, g.const(p)))  # (K N, corners)
    n, c = len(corners), np.shape(table)[1]  # c: 3 gains a cell, or 1 (`MaterialConfig.energy_luminance`)
    cells = g.shape(g.op("Gather", g.const(np.asarray(table, np.float32), name=W.ENERGY), index, axis=0),
                    [0, n * c])  # (K N, c corners): corner-major, RGB
    if c == 1:
        return g.op("MatMul", g.op("Mul", cells, weight), g.const(np.ones((n, 1), np.float32)))  # (K N, 1)
    spread = np.kron(np.eye(n, dtype=np.float32), np.ones((1, c), np.float32))  # (corners, c corners)
    total = np.tile(np.eye(c, dtype=np.float32), (n, 1))  # (c corners, c)
    return g.op("MatMul", g.op("Mul", cells, g.op("MatMul", weight, g.const(spread))), g.const(total))  # (K N, c)
