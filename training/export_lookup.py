"""ONNX stages of the texture lookups: wrap-padded tap tables read with float row arithmetic.

Shapes: N queries, L levels read per query (1 for the offset texture, 2 for the pyramid), K = 4 // taps
table rows per level footprint. The stages keep every tensor flat, (N, k) with the same k on both
sides of each elementwise op: ONNX Runtime's broadcasting of small inner dimensions costs more than
the arithmetic. Row arithmetic runs in float32 on integers below 2^24 (exact) and is cast once to
the Gather index type; column shuffles are MatMuls with 0/1 matrices (exact for finite values).
"""

from __future__ import annotations

import numpy as np

from .config import MaterialConfig
from .export_lod import level_of_detail
from .onnx_graph import INDEX_TYPES, GraphWriter
from .texture_tables import tap_atlas


def expand_table(g: GraphWriter, texels: str, index_rows: np.ndarray, width: int) -> str:
    """Constant subgraph: (T, width) texels and (R, taps) index table -> (R, taps * width) tap table.

    Only initializers feed it, so ONNX Runtime computes it once when the session loads.
    """
    taps = index_rows.shape[1]
    table = g.op("Gather", texels, g.const(index_rows, INDEX_TYPES["int32"][0]), axis=0)
    return g.shape(table, [-1, taps * width])


def _tap_factors(levels: int, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Affine map (2L, 4L), (4L,) from (fx, fy) per level to each tap's factor along `axis` (0: x):
    f for the far tap (x1 or y1), 1 - f for the near one; taps in order (x0 y0, x1 y0, x0 y1, x1 y1)."""
    a = np.zeros((2 * levels, 4 * levels), np.float32)
    b = np.zeros(4 * levels, np.float32)
    for level in range(levels):
        for tap in range(4):
            far = (tap % 2, tap // 2)[axis]
            a[2 * level + axis, 4 * level + tap] = 1.0 if far else -1.0
            b[4 * level + tap] = 0.0 if far else 1.0
    return a, b


def level_weights(g: GraphWriter, t: str, repeat: int) -> str:
    """t (N, 1) -> (N, 2 repeat): 1 - t repeated, then t repeated (one Gemm, exact)."""
    a = np.asarray([[-1.0] * repeat + [1.0] * repeat], np.float32)
    b = np.asarray([1.0] * repeat + [0.0] * repeat, np.float32)
    return g.op("Gemm", t, g.const(a), g.const(b))


def tap_weights(g: GraphWriter, frac: str, levels: int, t: str | None) -> str:
    """frac (N, 2L) = (fx, fy) of each level, level fraction t (N, 1) or None -> (N, 4L) tap weights.

    Each weight is (x factor * y factor) * level weight, the reference's order of products; the
    factors 1 - f and f come from one Gemm each (f * -1 + 1 rounds as 1 - f does).
    """
    wx, wy = (g.op("Gemm", frac, *(g.const(m) for m in _tap_factors(levels, axis))) for axis in (0, 1))
    weights = g.op("Mul", wx, wy)
    return weights if t is None else g.op("Mul", weights, level_weights(g, t, 4))


def _gather(g: GraphWriter, table: str, line: str, bases: str, levels: int, width: int,
            index_type: str) -> str:
    """Rows (N, L K) float -> (N, 4 L width) texels in tap order, level by level."""
    rows = g.op("Cast", g.op("Add", line, bases), to=INDEX_TYPES[index_type][1])
    return g.shape(g.op("Gather", table, rows, axis=0), [-1, 4 * levels * width])


def level_pair_params(config: MaterialConfig, level_params: np.ndarray) -> np.ndarray:
    """Per level (S, 1, W, bases...) -> per lower level lo a row (8 + 2K,) for levels lo, hi:

    [S_lo, S_lo, S_hi, S_hi, 1, W_lo, 1, W_hi, bases_lo (K), bases_hi (K)], hi = min(lo + 1, levels).
    """
    lo = np.arange(config.levels + 1)
    a, b = level_params[lo], level_params[np.minimum(lo + 1, config.levels)]
    one = np.ones_like(a[:, 0])
    cols = [a[:, 0], a[:, 0], b[:, 0], b[:, 0], one, a[:, 2], one, b[:, 2]]
    return np.concatenate([np.stack(cols, axis=1), a[:, 3:], b[:, 3:]], axis=1).astype(np.float32)


def pyramid_texels(g: GraphWriter, config: MaterialConfig, atlas: str, width: int, uvw: str,
                   sigma: str, taps: int, index_type: str) -> tuple[str, str]:
    """Trilinear footprint: uvw (N, 2) in [0, 1], sigma (N, 1) -> texels (N, 8 width), weights (N, 8).

    `atlas` (T, width) holds the pyramid levels flat, finest first (width = channels, or hidden when
    the decoder's first layer is folded in).
    """
    k = 4 // taps
    tables = tap_atlas(config.level_sizes(), taps)
    lo, t = level_of_detail(g, sigma, config)
    pairs = g.const(level_pair_params(config, tables.level_params))
    params = g.op("Gather", pairs, lo, axis=0)  # (N, 8 + 2K)
    p = 8 + 2 * k
    size, coef, bases = (g.pick(params, p, list(c)) for c in (range(4), range(4, 8), range(8, p)))
    both = g.op("MatMul", uvw, g.const(np.tile(np.eye(2, dtype=np.float32), (1, 2))))  # (N, 4) u v u v
    x = g.op("Sub", g.op("Mul", both, size), g.scalar(0.5))  # (N, 4) texel coordinates per level
    x0 = g.op("Floor", x)
    spread = np.kron(np.eye(2, dtype=np.float32), np.ones((2, k), np.float32))  # (4, 2K): x0 + W y0
    line = g.op("MatMul", g.op("Mul", x0, coef), g.const(spread))  # (N, 2K)
    table = expand_table(g, atlas, tables.rows, width)
    texels = _gather(g, table, line, bases, 2, width, index_type)
    return texels, tap_weights(g, g.op("Sub", x, x0), 2, t)


def texture_texels(g: GraphWriter, texture: str, size: int, width: int, uvw: str, taps: int,
                   index_type: str) -> tuple[str, str]:
    """Bilinear footprint of one texture, (S * S, width) flat: uvw (N, 2) in [0, 1] -> texels
    (N, 4 width), weights (N, 4)."""
    tables = tap_atlas([size], taps)
    _, _, w, *bases = tables.level_params[0]
    x = g.op("Sub", g.op("Mul", uvw, g.scalar(size)), g.scalar(0.5))  # (N, 2)
    x0 = g.op("Floor", x)
    line = g.op("MatMul", x0, g.const(np.tile([[1.0], [w]], (1, len(bases)))))  # (N, K): x0 + W y0
    table = expand_table(g, texture, tables.rows, width)
    texels = _gather(g, table, line, g.const(bases), 1, width, index_type)
    return texels, tap_weights(g, g.op("Sub", x, x0), 1, None)
