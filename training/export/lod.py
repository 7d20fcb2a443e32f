"""ONNX stage of the level of detail, clamp(log2(sigma * R) + b, 0, L), from element-exact ops only
(b: `MaterialConfig.lod_bias`; R 2^b is a power of two, so the product stays exact).

ONNX Runtime's ``Log`` kernel computes the last few elements of a call (the remainder after its
vector blocks) differently from the others, so a query's answer would depend in its last bits on
where it sits in a call and on how many rows the call has. This stage uses only ops that IEEE
arithmetic rounds per element (Mul, Add, Div, Clip, Floor, Min) and 0/1-weighted sums of integers
and powers of two (Gemm, exact in any order), so a query's level of detail is the same bits in any
batch, and it reads no table with Gather (ONNX Runtime's Gather costs ~8 ns a row even from a table
in L1):

- x = clip(sigma * R 2^b, 1, 2^L); log2 of it is the clamped level (log2 is monotonic).
- the level steps s_j = min(floor(x 2^-j), 1), j = 1..L: s_j = 1 exactly for j <= lo = floor(log2 x).
- a per-level table's row lo is then row 0 plus the sum of its row differences up to lo:
  ``table[0] + steps @ diff(table)``, one Gemm (`level_rows`); the tables hold integers below 2^24
  and powers of two, so every partial sum is exact. One of them is 2^-lo.
- m = x * 2^-lo in [1, 2): a multiplication by a power of two, exact.
- t = log2(m) = s P(s^2), s = (m - 1) / (m + 1) in [0, 1/3): a degree-4 polynomial (fitted to
  log2 in float64, 6e-9 from it), evaluated in float32 within 2e-7 of log2 for every float32 m
  (tests/training/export/test_determinism.py checks all 2^23), exactly 0 at m = 1: level boundaries
  are exact, and t < 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neumip.core import weights as W
from neumip.core.config import MaterialConfig
from neumip.training.export.onnx_graph import GraphWriter

LOG2_POLYNOMIAL = (2.885390043258667, 0.9617878198623657, 0.5775499939918518, 0.40215760469436646,
                   0.41097143292427063)
"""P(z), lowest power first: log2(m) = s P(s^2) with s = (m - 1) / (m + 1), m in [1, 2). A weighted
Chebyshev fit of log2(m) / s over s in [0, 1/3] (2 / ln 2 = 2.88539... leads)."""


def clip_min(finest_level: int) -> float:
    """Lower bound of sigma * R in the level-of-detail Clip: 2^K for a model whose finest level is K."""
    return 2.0**finest_level


RELIEF_PREFIX = "relief."
"""Prefix of the relief's height pyramid's level-of-detail constants (``relief.lod.*``)."""
BASE_PREFIX = "base."
"""Prefix of the base maps' pyramid's level-of-detail constants (``base.lod.*``)."""
OFFSET_PREFIX = "offset."
"""Prefix of the neural offset texture's constants (its quad vectors ``offset.quad.*``; with
`MaterialConfig.offset_mip` its pyramid's ``offset.lod.*``)."""


@dataclass(frozen=True)
class Pyramid:
    """One pyramid the graph reads with a level of detail of its own (`level_of_detail`)."""

    texture: str
    """Its initializer: the atlas, levels flat, finest first (`weights.PYRAMID`, `OFFSET_TEXTURE`, `BASE`, `RELIEF`)."""
    config: MaterialConfig
    """Its levels, as a config (`MaterialConfig.base_pyramid`, `relief_pyramid`; the model's own for the latents)."""
    prefix: str
    """Prefix of its ``lod.*`` constants."""


def pyramids(config: MaterialConfig) -> list[Pyramid]:
    """Every pyramid a graph of `config` reads, in the order of their level-of-detail Clips: the relief's heights
    and the offset's mip pyramid (`MaterialConfig.offset_mip`; read before the latents), the latents, the base
    maps (read after)."""
    out = [Pyramid(W.RELIEF, config.relief_pyramid(), RELIEF_PREFIX)] if config.relief else []
    if config.offset_pyramid() is not None:
        out.append(Pyramid(W.OFFSET_TEXTURE, config.offset_pyramid(), OFFSET_PREFIX))
    out.append(Pyramid(W.PYRAMID, config, ""))
    return out + ([Pyramid(W.BASE, config.base_pyramid(), BASE_PREFIX)] if config.base else [])


def log2_mantissa(g: GraphWriter, m: str) -> str:
    """m (N, 1) in [1, 2) -> log2(m) (N, 1) in [0, 1), 0 exactly at m = 1 (Horner in s^2)."""
    one = g.scalar(1.0)
    s = g.op("Div", g.op("Sub", m, one), g.op("Add", m, one))  # (N, 1) in [0, 1/3)
    z = g.op("Mul", s, s)
    p = g.scalar(LOG2_POLYNOMIAL[-1])
    for c in reversed(LOG2_POLYNOMIAL[:-1]):
        p = g.op("Add", g.op("Mul", z, p), g.scalar(c))
    return g.op("Mul", s, p)


def scale_table(config: MaterialConfig, finest_level: int = 0) -> np.ndarray:
    """(L + 1, 1) per lower level lo: 2^-lo, levels finer than K repeating level K's row."""
    lo = np.maximum(np.arange(config.levels + 1), finest_level)
    return (2.0 ** -lo[:, None]).astype(np.float32)


def level_constants(tables: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per-level tables (L + 1, k) -> the initializers `level_rows` writes, by name: row 0 as
    ``lod.NAME.first`` (k,) and the row differences as ``lod.NAME.steps`` (L, k) (one zero row
    when L = 0, whose one step is always 0)."""
    out = {}
    for name, table in tables.items():
        table = np.asarray(table, np.float32)
        table = np.concatenate([table, table[-1:]]) if len(table) == 1 else table  # L = 0: one step, 0
        out[f"lod.{name}.first"] = table[0]
        out[f"lod.{name}.steps"] = np.diff(table, axis=0)
    return out


def _with_scale(config: MaterialConfig, finest_level: int, tables: dict | None) -> dict[str, np.ndarray]:
    return {"scale": scale_table(config, finest_level), **(tables or {})}


def level_rows(g: GraphWriter, steps: str, tables: dict[str, np.ndarray], prefix: str = "") -> dict[str, str]:
    """Level steps (N, L) -> each (L + 1, k) table's row lo, (N, k): one Gemm each (exact). The
    initializers are named ``{prefix}lod.*`` (a second pyramid's stage, the base maps', has its own)."""
    consts = level_constants(tables)
    return {name: g.op("Gemm", steps, g.const(consts[f"lod.{name}.steps"], name=f"{prefix}lod.{name}.steps"),
                       g.const(consts[f"lod.{name}.first"], name=f"{prefix}lod.{name}.first"))
            for name in tables}


def level_of_detail(g: GraphWriter, sigma: str, config: MaterialConfig, finest_level: int = 0,
                    tables: dict[str, np.ndarray] | None = None, prefix: str = "") -> tuple[dict[str, str], str]:
    """sigma (N, 1) -> (row lo (N, k) of each per-level table (L + 1, k) of `tables`, the fraction
    t (N, 1) in [0, 1) towards level lo + 1); lo + t = clamp(log2(sigma * R) + b, K, L), sigma <= 0
    reading the finest level K.

    K = ``finest_level`` (> 0 for a trimmed model) only raises the Clip's lower bound from 1 to 2^K
    (and the tables repeat level K's row for finer levels): every query whose level is >= K computes
    the same bits as in the untrimmed graph.
    """
    levels = config.levels
    x = g.op("Clip", g.op("Mul", sigma, g.scalar(config.resolution * 2**config.lod_bias)), g.const(clip_min(finest_level)),
             g.const(2.0**levels))
    inverse = (2.0 ** -np.arange(1, max(levels, 1) + 1))[None, :]  # (1, L): x 2^-j, exact
    steps = g.op("Min", g.op("Floor", g.op("MatMul", x, g.const(inverse))), g.scalar(1.0))  # (N, L)
    rows = level_rows(g, steps, _with_scale(config, finest_level, tables), prefix)
    t = log2_mantissa(g, g.op("Mul", x, rows.pop("scale")))  # m = x 2^-lo (N, 1) in [1, 2)
    return rows, t
