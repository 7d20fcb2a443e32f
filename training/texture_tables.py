"""Lookup tables the ONNX graph reads its texels from (pure numpy, built once at export).

A bilinear wrap-around tap at texel x0 in [-1, S-1] reads texels x0 and x0 + 1 modulo S. Padding each
level by one texel on every side with the opposite edge (`wrap_pad`) turns both into plain indices
x0 + 1 and x0 + 2 of the padded level, so the graph needs no modulo. `tap_table` then groups the taps
a query reads into rows: with 4 taps per row one Gather row holds the whole 2 x 2 footprint.

The tables are built from texel *indices* into the flat atlas: the model file stores the textures
once, and the graph's constant subgraph Gather(atlas, index table), which ONNX Runtime folds when the
session loads, expands them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TAPS_PER_ROW = (1, 2, 4)
"""Bilinear taps stored in one table row: single texels, horizontal pairs, or 2 x 2 quads."""


def wrap_pad(level: np.ndarray) -> np.ndarray:
    """(S, S, C) level -> (S + 2, S + 2, C); padded texel (i, j) is texel ((i - 1) % S, (j - 1) % S)."""
    return np.pad(level, ((1, 1), (1, 1), (0, 0)), mode="wrap")


@dataclass(frozen=True)
class TapTable:
    """One level's taps laid out as table rows, and how a graph finds them."""

    rows: np.ndarray
    """(rows, taps * C): row y * width + x holds the taps at padded (x, y) onwards."""
    width: int
    """Rows per line of padded texels (the stride of y in a row index)."""
    offsets: tuple[int, ...]
    """Row offsets of the 4 // taps rows a footprint reads, relative to its (x0, y0) row."""


def tap_table(level: np.ndarray, taps: int) -> TapTable:
    """(S, S, C) level -> its wrap-padded texels grouped `taps` per row (1, 2 or 4).

    The footprint with top-left padded texel (x, y) reads, in tap order (x0 y0, x1 y0, x0 y1, x1 y1):
    1 tap per row: rows r, r + 1, r + W, r + W + 1 (W = S + 2); 2 per row: rows r, r + W, each holding
    (x, x + 1) (W = S + 1); 4 per row: row r holding all four (W = S + 1).
    """
    if taps not in TAPS_PER_ROW:
        raise ValueError(f"taps per row must be one of {TAPS_PER_ROW}, got {taps}")
    p = wrap_pad(np.asarray(level))  # (S + 2, S + 2, C)
    s2, c = p.shape[0], p.shape[2]
    if taps == 1:
        return TapTable(p.reshape(-1, c), s2, (0, 1, s2, s2 + 1))
    pairs = np.concatenate([p[:, :-1], p[:, 1:]], axis=2)  # (S + 2, S + 1, 2C): texels x, x + 1
    w = s2 - 1
    if taps == 2:
        return TapTable(pairs.reshape(-1, 2 * c), w, (0, w))
    quads = np.concatenate([pairs[:-1], pairs[1:]], axis=2)  # (S + 1, S + 1, 4C): rows y, y + 1
    return TapTable(quads.reshape(-1, 4 * c), w, (0,))


@dataclass(frozen=True)
class TapAtlas:
    """All pyramid levels' tap tables stacked in one index table, with a per-level parameter table."""

    rows: np.ndarray
    """(rows, taps) int64: atlas rows (flat texel indices) of each table row's taps, finest level first."""
    level_params: np.ndarray
    """(levels, 3 + 4 // taps) float32 per level: size S, 1, width W, then the absolute rows of the
    footprint at padded (0, 0), i.e. start + offset; a query adds x0 + 1 + (y0 + 1) * W."""


def tap_atlas(sizes: list[int], taps: int) -> TapAtlas:
    """Tap index tables of levels of `sizes` texels per side, stacked flat (finest first) in one atlas."""
    params, tables, texel, start = [], [], 0, 0
    for size in sizes:
        index = texel + np.arange(size * size, dtype=np.int64).reshape(size, size, 1)
        table = tap_table(index, taps)
        base = start + table.width + 1  # table row of padded (1, 1), the footprint x0 = y0 = 0
        params.append([size, 1, table.width, *(base + o for o in table.offsets)])
        tables.append(table.rows)
        start += table.rows.shape[0]
        texel += size * size
    if start >= 2**24:
        raise ValueError(f"{start} table rows: float32 row arithmetic is exact only below 2^24")
    return TapAtlas(np.concatenate(tables), np.asarray(params, np.float32))
