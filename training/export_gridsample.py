"""ONNX stages of the texture lookups with GridSample (lookup="gridsample"), kept as a measured variant.

GridSample has no wrap-around mode, so each texture is wrap-padded by one texel (`texture_tables`) and
the pyramid levels are stacked into one 2-D image; a query samples it at two points, one per level.
The normalised coordinates GridSample takes cost some precision (3e-6 from torch at most on a 256^2
material, inside the parity contract), and ONNX Runtime's GridSample kernel made this graph about
half as fast as the tap tables (benchmarks/bench_inference.py), so it is not the default.
"""

from __future__ import annotations

import numpy as np

from .config import MaterialConfig
from .export_lod import level_of_detail
from .export_lookup import level_weights
from .onnx_graph import INDEX_TYPES, GraphWriter
from .texture_tables import wrap_pad


def stacked_levels(sizes: list[int]) -> tuple[np.ndarray, list[int]]:
    """Atlas rows of an image holding the wrap-padded levels stacked top to bottom, left-aligned.

    Returns (H, W) int64 rows into the flat atlas (-1: unused) and each level's first image row.
    """
    width = sizes[0] + 2
    blocks, tops, texel, top = [], [], 0, 0
    for size in sizes:
        index = wrap_pad(texel + np.arange(size * size).reshape(size, size, 1))[:, :, 0]
        block = np.full((size + 2, width), -1, np.int64)
        block[:, : size + 2] = index
        blocks.append(block)
        tops.append(top)
        top += size + 2
        texel += size * size
    return np.concatenate(blocks), tops


def _image(g: GraphWriter, texels: str, channels: int, index: np.ndarray) -> str:
    """Constant subgraph: (T, C) texels, (H, W) rows (-1: zero) -> (1, C, H, W) image, folded at load."""
    zero = g.const(np.zeros((1, channels), np.float32))
    padded = g.op("Concat", texels, zero, axis=0)  # row T is the zero texel
    rows = np.where(index < 0, index.max() + 1, index).astype(INDEX_TYPES["int32"][0])
    image = g.op("Gather", padded, g.const(rows, rows.dtype), axis=0)  # (H, W, C)
    return g.op("Unsqueeze", g.op("Transpose", image, perm=[2, 0, 1]), g.const([0], np.int64))


def _sample(g: GraphWriter, image: str, grid: str, points: int) -> str:
    """(1, C, H, W) image, grid (N, 2 points) normalised (x, y) -> (1, C, N, points) bilinear samples."""
    grid = g.shape(grid, [1, -1, points, 2])
    return g.op("GridSample", image, grid, mode="bilinear", padding_mode="border", align_corners=1)


def texture_features(g: GraphWriter, texture: str, size: int, channels: int, uvw: str) -> str:
    """Bilinear wrap-around lookup: uvw (N, 2) in [0, 1] -> features (C, N) (channel-major)."""
    index = wrap_pad(np.arange(size * size).reshape(size, size, 1))[:, :, 0]
    image = _image(g, texture, channels, index)
    # padded pixel = u * S - 0.5 + 1; align_corners: normalised = pixel * 2 / (W - 1) - 1
    pixel = g.op("Add", g.op("Mul", uvw, g.scalar(size)), g.scalar(0.5))
    grid = g.op("Sub", g.op("Mul", pixel, g.scalar(2.0 / (size + 1))), g.scalar(1.0))
    return g.shape(_sample(g, image, grid, 1), [channels, -1])


def pyramid_features(g: GraphWriter, config: MaterialConfig, atlas: str, uvw: str, sigma: str) -> str:
    """Trilinear lookup: uvw (N, 2) in [0, 1], sigma (N, 1) -> features (C, N) (channel-major)."""
    c = config.channels
    index, tops = stacked_levels(config.level_sizes())
    image = _image(g, atlas, c, index)
    lo, t = level_of_detail(g, sigma, config)
    sizes = np.asarray(config.level_sizes(), np.float32)
    hi = np.minimum(np.arange(config.levels + 1) + 1, config.levels)
    lo_ = np.arange(config.levels + 1)
    # per lower level: scale (S, S) and pixel offset (0.5, 0.5 + top) of both levels -> (L + 1, 8)
    params = np.stack([sizes[lo_], sizes[lo_], sizes[hi], sizes[hi],
                       np.full(len(lo_), 0.5), 0.5 + np.asarray(tops)[lo_],
                       np.full(len(lo_), 0.5), 0.5 + np.asarray(tops)[hi]], axis=1).astype(np.float32)
    rows = g.op("Gather", g.const(params), lo, axis=0)
    scale, offset = g.op("Split", rows, g.const([4, 4], np.int64), axis=1, outputs=2)  # (N, 4) each
    both = g.op("MatMul", uvw, g.const(np.tile(np.eye(2, dtype=np.float32), (1, 2))))  # u v u v
    pixel = g.op("Add", g.op("Mul", both, scale), offset)
    h, w = index.shape
    norm = np.asarray([[2.0 / (w - 1), 2.0 / (h - 1)] * 2], np.float32)
    grid = g.op("Sub", g.op("Mul", pixel, g.const(norm)), g.scalar(1.0))  # (N, 4)
    samples = _sample(g, image, grid, 2)  # (1, C, N, 2)
    weighted = g.op("Mul", samples, g.shape(level_weights(g, t, 1), [1, 1, -1, 2]))
    summed = g.op("MatMul", weighted, g.const(np.ones((2, 1), np.float32)))  # (1, C, N, 1), exact order
    return g.shape(summed, [c, -1])
