"""ONNX stage of the answers' energy table (`MaterialConfig.energy_bins`), as `training.model.energy.energy_gain`
computes it: hat weights over the levels of detail times the table (once per group), then per light and channel the
hat weights over the direction cells (the half vector's angle times the light's elevation), each sum a MatMul (one
order per row). The table is the
initializer ``energy`` (L + 1, 3 B^2), every level's
row (a trimmed model keeps them all: the level of detail is clamped at its finest level, so the rows below it weigh
exactly 0 and the answers above the cut keep their bits)."""

from __future__ import annotations

import numpy as np

from neumip.core import weights as W
from neumip.core.config import MaterialConfig
from neumip.training.export import base as B
from neumip.training.export.lod import level_of_detail
from neumip.training.export.onnx_graph import GraphWriter

ENERGY_PREFIX = "energy."
"""Prefix of the energy stage's level-of-detail constants (``energy.lod.*``)."""


def _hats(g: GraphWriter, x: str, count: int) -> str:
    """x (M, 1) in [0, count - 1] -> (M, count) max(0, 1 - |x - j|)."""
    nodes = g.const(np.arange(count, dtype=np.float32)[None, :])
    return g.op("Max", g.op("Sub", g.scalar(1.0), g.op("Abs", g.op("Sub", x, nodes))), g.scalar(0.0))


def energy_gain(g: GraphWriter, config: MaterialConfig, table: np.ndarray, sigma: str, wi: str, wo: str,
                each_light, finest_level: int = 0) -> str:
    """The groups' sigma (N, 1), each light's wi and wo (K N, 2) -> the gains (K N, 3); `each_light` repeats a
    group's rows per light (`graph.material_graph`)."""
    bins = config.energy_bins
    levels = np.arange(config.levels + 1, dtype=np.float32)[:, None]
    rows, t = level_of_detail(g, sigma, config, finest_level, {"level": levels}, ENERGY_PREFIX)
    lod = g.op("Add", rows["level"], t)  # (N, 1) in [K, L]
    cells = g.op("MatMul", _hats(g, lod, config.levels + 1),
                 g.const(np.asarray(table, np.float32), name=W.ENERGY))  # (N, 3 B^2): the group's level, every cell
    wi3 = B.lift(g, wi)
    h = B.half_direction(g, wi3, B.lift(g, wo))  # (K N, 3)
    s = g.op("Sqrt", g.op("Max", g.op("Sub", g.scalar(2.0), g.op("Mul", g.pick(h, 3, [2]), g.scalar(2.0))),
                          g.scalar(0.0)))
    x = g.op("Min", g.op("Mul", s, g.scalar((bins - 1) / np.sqrt(2.0))), g.scalar(bins - 1.0))  # (K N, 1)
    y = g.op("Min", g.op("Mul", g.op("Sqrt", g.pick(wi3, 3, [2])), g.scalar(bins - 1.0)), g.scalar(bins - 1.0))
    ones = np.ones((1, bins), np.float32)
    directions = g.op("Mul", g.op("MatMul", _hats(g, x, bins), g.const(np.kron(np.eye(bins, dtype=np.float32), ones))),
                      g.op("MatMul", _hats(g, y, bins), g.const(np.tile(np.eye(bins, dtype=np.float32), (1, bins)))))
    cells_n = bins * bins
    total = g.const(np.ones((cells_n, 1), np.float32))
    gains = []  # per channel: its B^2 cells (a Slice of the group's row), weighted by the light's and summed
    for c in range(3):
        part = g.op("Slice", cells, g.const([c * cells_n], np.int64), g.const([(c + 1) * cells_n], np.int64),
                    g.const([1], np.int64))  # (N, B^2)
        gains.append(g.op("MatMul", g.op("Mul", each_light(part), directions), total))  # (K N, 1)
    return g.op("Concat", *gains, axis=1)  # (K N, 3)
