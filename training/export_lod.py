"""ONNX stage of the level of detail, clamp(log2(sigma * R), 0, L), from element-exact ops only.

ONNX Runtime's ``Log`` kernel computes the last few elements of a call (the remainder after its
vector blocks) differently from the others, so a query's answer would depend in its last bits on
where it sits in a call and on how many rows the call has. This stage uses only ops that IEEE
arithmetic rounds per element (Mul, Add, Div, Clip, Floor, Gather), so a query's level of
detail is the same bits in any batch:

- x = clip(sigma * R, 1, 2^L); log2 of it is the clamped level (log2 is monotonic).
- lo = floor(log2 x) and 2^-lo: two tables of 2^L + 1 rows indexed by floor(x), exact (L <= 11 for
  the graph, whose quad tables need R <= 2048).
- m = x * 2^-lo in [1, 2): a multiplication by a power of two, exact.
- t = log2(m) = s P(s^2), s = (m - 1) / (m + 1) in [0, 1/3): a degree-4 polynomial (fitted to
  log2 in float64, 6e-9 from it), evaluated in float32 within 2e-7 of log2 for every float32 m
  (tests/training/test_export_determinism.py checks all 2^23), exactly 0 at m = 1: level boundaries
  are exact, and t < 1.
"""

from __future__ import annotations

import numpy as np
from onnx import TensorProto

from .config import MaterialConfig
from .onnx_graph import GraphWriter

LOG2_POLYNOMIAL = (2.885390043258667, 0.9617878198623657, 0.5775499939918518, 0.40215760469436646,
                   0.41097143292427063)
"""P(z), lowest power first: log2(m) = s P(s^2) with s = (m - 1) / (m + 1), m in [1, 2). A weighted
Chebyshev fit of log2(m) / s over s in [0, 1/3] (2 / ln 2 = 2.88539... leads)."""


def clip_min(finest_level: int) -> float:
    """Lower bound of sigma * R in the level-of-detail Clip: 2^K for a model whose finest level is K."""
    return 2.0**finest_level


def clip_node(graph) -> "onnx.NodeProto":
    """The level-of-detail Clip of an exported graph (the graph's only Clip; `level_of_detail`)."""
    clips = [node for node in graph.node if node.op_type == "Clip"]
    if len(clips) != 1:
        raise ValueError(f"expected the level-of-detail Clip, found {len(clips)} Clip nodes")
    return clips[0]


def log2_mantissa(g: GraphWriter, m: str) -> str:
    """m (N, 1) in [1, 2) -> log2(m) (N, 1) in [0, 1), 0 exactly at m = 1 (Horner in s^2)."""
    one = g.scalar(1.0)
    s = g.op("Div", g.op("Sub", m, one), g.op("Add", m, one))  # (N, 1) in [0, 1/3)
    z = g.op("Mul", s, s)
    p = g.scalar(LOG2_POLYNOMIAL[-1])
    for c in reversed(LOG2_POLYNOMIAL[:-1]):
        p = g.op("Add", g.op("Mul", z, p), g.scalar(c))
    return g.op("Mul", s, p)


def level_of_detail(g: GraphWriter, sigma: str, config: MaterialConfig, finest_level: int = 0) -> tuple[str, str]:
    """sigma (N, 1) -> lower level lo (N,) int64 in [K, L] and the fraction t (N, 1) in [0, 1) towards
    level lo + 1; lo + t = clamp(log2(sigma * R), K, L), sigma <= 0 reading the finest level K.

    K = ``finest_level`` (> 0 for a trimmed model) only raises the Clip's lower bound from 1 to 2^K:
    every query whose level is >= K computes the same bits as in the untrimmed graph.
    """
    levels = config.levels
    x = g.op("Clip", g.op("Mul", sigma, g.scalar(config.resolution)), g.const(clip_min(finest_level)),
             g.const(2.0**levels))
    index = g.shape(g.op("Cast", g.op("Floor", x), to=TensorProto.INT64), [-1])  # (N,) in [1, 2^L]
    k = np.maximum(np.arange(2**levels + 1), 1)
    floor_log2 = np.asarray([int(i).bit_length() - 1 for i in k], np.int64)  # row k: floor(log2 k)
    lo = g.op("Gather", g.const(floor_log2, np.int64), index, axis=0)  # (N,)
    scale = g.op("Gather", g.const(2.0 ** -floor_log2[:, None].astype(np.float64)), index, axis=0)  # (N, 1)
    return lo, log2_mantissa(g, g.op("Mul", x, scale))  # m = x 2^-lo (N, 1) in [1, 2)
