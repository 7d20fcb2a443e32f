"""ONNX stages of the texture lookups: wrap-padded quad tables read with float row arithmetic.

A bilinear wrap-around tap at texel x0 in [-1, S-1] reads texels x0 and x0 + 1 modulo S. Padding each
level by one texel on every side with the opposite edge (`wrap_pad`) turns both into plain indices
x0 + 1 and x0 + 2 of the padded level, so the graph needs no modulo, and grouping the 2 x 2 taps of
each footprint into one row (`quad_table`) lets a query read a level's footprint with one Gather row.

The model file stores the textures once and no table: a constant subgraph computes each pyramid's quad
index table (texel *indices* into the flat atlas) from two short vectors per level (`quad_vectors`,
`quad_rows`), and Gather(atlas, index table) (`expand_table`) expands it into the quad table. ONNX Runtime
folds both when the session loads, and so does the kernel engine (`engines/onnx_kernel.py`).

Shapes: N queries, L levels read per query (1 for the offset texture, 2 for the pyramid). The stages
keep every tensor flat, (N, k) with the same k on both sides of each elementwise op: ONNX Runtime's
broadcasting of small inner dimensions costs more than the arithmetic. Row arithmetic runs in float32
on integers below 2^24 (exact) and is cast once to int64; column shuffles are MatMuls with 0/1
matrices (exact for finite values).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from onnx import TensorProto

from neumip.core.config import MaterialConfig
from neumip.training.export.lod import level_of_detail
from neumip.training.export.onnx_graph import GraphWriter

# --- the quad tables (numpy, built once at export) -----------------------------------------------


def wrap_pad(level: np.ndarray) -> np.ndarray:
    """(S, S, C) level -> (S + 2, S + 2, C); padded texel (i, j) is texel ((i - 1) % S, (j - 1) % S)."""
    return np.pad(level, ((1, 1), (1, 1), (0, 0)), mode="wrap")


def quad_table(level: np.ndarray) -> np.ndarray:
    """(S, S, C) level -> ((S + 1)^2, 4C) rows: row y (S + 1) + x holds the wrap-padded texels at
    (x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1), the footprint whose top-left padded texel is (x, y)."""
    p = wrap_pad(np.asarray(level))  # (S + 2, S + 2, C)
    pairs = np.concatenate([p[:, :-1], p[:, 1:]], axis=2)  # (S + 2, S + 1, 2C): texels x, x + 1
    quads = np.concatenate([pairs[:-1], pairs[1:]], axis=2)  # (S + 1, S + 1, 4C): rows y, y + 1
    return quads.reshape(-1, quads.shape[2])


@dataclass(frozen=True)
class QuadAtlas:
    """All pyramid levels' quad tables stacked in one index table, with a per-level parameter table."""

    rows: np.ndarray
    """(rows, 4) int64: atlas rows (flat texel indices) of each table row's taps, finest level first."""
    level_params: np.ndarray
    """(levels, 4) float32 per level: size S, 1, width W = S + 1, and the table row of the footprint
    at padded (1, 1) (x0 = y0 = 0); a query adds x0 + y0 * W."""


def quad_atlas(sizes: list[int]) -> QuadAtlas:
    """Quad index tables of levels of `sizes` texels per side, stacked flat (finest first) in one atlas."""
    params, tables, texel, start = [], [], 0, 0
    for size in sizes:
        table = quad_table(texel + np.arange(size * size, dtype=np.int64).reshape(size, size, 1))
        width = size + 1
        params.append([size, 1, width, start + width + 1])
        tables.append(table)
        start += table.shape[0]
        texel += size * size
    if start >= 2**24:
        raise ValueError(f"{start} table rows: float32 row arithmetic is exact only below 2^24")
    return QuadAtlas(np.concatenate(tables), np.asarray(params, np.float32))


def quad_vectors(sizes: list[int], finest_level: int = 0, prefix: str = "") -> dict[str, np.ndarray]:
    """The initializers from which the graph computes the quad index table of a pyramid of `sizes` texels per
    side (all its levels, finest first), held from level `finest_level` on (`quad_rows`). Per level l:
    ``{prefix}quad.l.rows`` (S + 2, 1) int32, the atlas row of each wrap-padded row's first texel, and
    ``{prefix}quad.l.cols`` (1, S + 2), each wrap-padded column's texel within its row, so that padded texel
    (i, j) is atlas row rows[i] + cols[j] (`wrap_pad`); levels finer than `finest_level` hold none (0 x 1,
    1 x 0). A few kilobytes where the table is (rows, 4) int32: 1.4 MB for 256^2. What `neumip trim` swaps."""
    out, start = {}, 0
    for level, size in enumerate(sizes):
        wrapped = np.arange(-1, size + 1) % size if level >= finest_level else np.zeros(0, np.int64)
        out[f"{prefix}quad.{level}.rows"] = (start + size * wrapped).astype(np.int32).reshape(-1, 1)
        out[f"{prefix}quad.{level}.cols"] = wrapped.astype(np.int32).reshape(1, -1)
        start += size * size if level >= finest_level else 0
    return out


def quad_rows(g: GraphWriter, sizes: list[int], finest_level: int = 0, prefix: str = "") -> str:
    """Constant subgraph: the (R, 4) int32 quad index table of levels `finest_level`.. of a pyramid of `sizes`
    (`quad_atlas`'s rows, computed from `quad_vectors`): per level the padded grid rows + cols, its 2 x 2 taps
    as four shifted slices, levels stacked."""
    vectors = quad_vectors(sizes, finest_level, prefix)
    big = np.iinfo(np.int64).max
    levels = []
    for level in range(len(sizes)):
        padded = g.op("Add", *(g.const(vectors[f"{prefix}quad.{level}.{part}"], np.int32,
                                       name=f"{prefix}quad.{level}.{part}") for part in ("rows", "cols")))
        taps = [g.shape(g.op("Slice", padded, g.const([dy, dx], np.int64),
                             g.const([-1 if dy == 0 else big, -1 if dx == 0 else big], np.int64)), [-1, 1])
                for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1))]  # (x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1)
        levels.append(g.op("Concat", *taps, axis=1))
    return levels[0] if len(levels) == 1 else g.op("Concat", *levels, axis=0)


def trimmed_atlas(config: MaterialConfig, finest_level: int = 0) -> tuple[QuadAtlas, np.ndarray]:
    """Quad atlas of levels K..L (K = ``finest_level``) and its per-level parameters indexed by the
    full level number 0..L (levels finer than K repeat level K's row; the graph never reads them)."""
    tables = quad_atlas(config.level_sizes()[finest_level:])
    params = np.concatenate([np.repeat(tables.level_params[:1], finest_level, 0), tables.level_params])
    return tables, params


def level_tables(config: MaterialConfig, finest_level: int = 0) -> dict[str, np.ndarray]:
    """Per lower level lo (rows 0..L) the parameters of levels lo and hi = min(lo + 1, L) that a
    query reads, finer levels than K repeating level K's (`trimmed_atlas`): "size" (4,)
    [S_lo, S_lo, S_hi, S_hi], "coef" (4,) [1, W_lo, 1, W_hi] and "base" (2,) [base_lo, base_hi]."""
    _, level_params = trimmed_atlas(config, finest_level)
    lo = np.arange(config.levels + 1)
    a, b = level_params[lo], level_params[np.minimum(lo + 1, config.levels)]
    one = np.ones_like(a[:, 0])
    tables = {"size": [a[:, 0], a[:, 0], b[:, 0], b[:, 0]], "coef": [one, a[:, 2], one, b[:, 2]],
              "base": [a[:, 3], b[:, 3]]}
    return {name: np.stack(cols, axis=1).astype(np.float32) for name, cols in tables.items()}


# --- graph stages ----------------------------------------------------------------------------------


def stored_texture(value: np.ndarray, config: MaterialConfig) -> np.ndarray:
    """A texture's float32 values as the file stores them (`MaterialConfig.half_textures`: rounded to float16, as
    `training.model.pyramid.as_stored` rounds them in torch); ValueError where float16 cannot hold one."""
    value = np.asarray(value, np.float32)
    if not config.half_textures:
        return value
    half = value.astype(np.float16)
    if not np.isfinite(half).all():
        raise ValueError(f"a texture value beyond float16's range ({np.abs(value).max():.4g}): export with "
                         f"half_textures off")
    return half.astype(np.float32)


def texture_const(g: GraphWriter, value: np.ndarray, name: str, config: MaterialConfig) -> str:
    """Texture initializer `name` in the type the file stores it: float32, or float16 with
    `MaterialConfig.half_textures`; `value` as `stored_texture` gives it. The quad tables built from it at load keep
    that type, and a query's read turns its rows to float32 (`read_rows`): float16 values are exact in float32, so
    the answers are the same bits as from a float32 table, at half the table's memory."""
    return g.const(value, np.float16 if config.half_textures else np.float32, name=name)


def as_float(g: GraphWriter, x: str, config: MaterialConfig) -> str:
    """A tensor of a texture's type (`texture_const`) as float32, for arithmetic."""
    return g.op("Cast", x, to=TensorProto.FLOAT) if config.half_textures else x


def mip_atlas(texture: np.ndarray) -> np.ndarray:
    """(S, S, C) float32 texture -> (T, C) its mip pyramid's atlas, finest first: each coarser texel is
    ((a + b) + (c + d)) * 0.25 of the 2 x 2 under it in float32, in the order of `training.model.pyramid.mip_levels`
    (the same bits; `mip_const` computes it in the graph)."""
    levels = [np.asarray(texture, np.float32)]
    while levels[-1].shape[0] > 1:
        t = levels[-1]
        levels.append(((t[0::2, 0::2] + t[0::2, 1::2]) + (t[1::2, 0::2] + t[1::2, 1::2])) * np.float32(0.25))
    return np.concatenate([level.reshape(-1, texture.shape[-1]) for level in levels])


def mip_const(g: GraphWriter, atlas: np.ndarray, pyramid: MaterialConfig, name: str, config: MaterialConfig) -> str:
    """Constant subgraph: a mip pyramid's atlas (T, C) in the texture's type (`texture_const`), from its finest level
    alone, which the file stores (`texture_const`, named `name`): every coarser level is `mip_atlas`'s average in
    float32 from the level above, then rounded as the file would store it (`stored_texture`; the next level averages
    the unrounded one, as the model does). ValueError where `atlas` (float32, every level), as stored, is not that
    pyramid of its finest level as stored."""
    size, width = pyramid.resolution, pyramid.channels
    finest = stored_texture(atlas[:size * size], config)
    if not np.array_equal(stored_texture(mip_atlas(finest.reshape(size, size, width)), config),
                          stored_texture(atlas, config)):
        raise ValueError(f"{name}: its coarser levels are not the mip pyramid of its finest level")
    stored = texture_const(g, finest, name, config)
    level = g.shape(as_float(g, stored, config), [size, size, width])
    big = np.iinfo(np.int64).max
    levels = [g.shape(stored, [-1, width])]
    for _ in pyramid.level_sizes()[1:]:
        taps = [g.op("Slice", level, g.const([dy, dx], np.int64), g.const([big, big], np.int64),
                     g.const([0, 1], np.int64), g.const([2, 2], np.int64)) for dy, dx in ((0, 0), (0, 1), (1, 0), (1, 1))]
        level = g.op("Mul", g.op("Add", g.op("Add", taps[0], taps[1]), g.op("Add", taps[2], taps[3])), g.scalar(0.25))
        stored = g.op("Cast", level, to=TensorProto.FLOAT16) if config.half_textures else level
        levels.append(g.shape(stored, [-1, width]))
    return g.op("Concat", *levels, axis=0)


def expand_table(g: GraphWriter, texels: str, index: str, width: int) -> str:
    """Constant subgraph: (T, width) texels and the (R, 4) index table `index` (`quad_rows`) -> (R, 4 width)
    quad table.

    Only initializers feed it, so ONNX Runtime computes it once when the session loads.
    """
    table = g.op("Gather", texels, index, axis=0)
    return g.shape(table, [-1, 4 * width])


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


def read_rows(g: GraphWriter, table: str, rows: str, config: MaterialConfig) -> str:
    """A query's read of a quad table in a texture's type (`texture_const`): Gather(table, rows) as float32."""
    return as_float(g, g.op("Gather", table, g.op("Cast", rows, to=TensorProto.INT64), axis=0), config)


def _gather(g: GraphWriter, table: str, rows: str, levels: int, width: int, config: MaterialConfig) -> str:
    """Table rows (N, L) float -> (N, 4 L width) float32 texels in tap order, level by level."""
    return g.shape(read_rows(g, table, rows, config), [-1, 4 * levels * width])


@dataclass
class Footprint:
    """A pyramid's level-of-detail rows of N queries (`pyramid_footprint`): what `footprint_texels` reads
    the pyramid at any (u, v) with."""

    size: str
    """(N, 4) texels per side of levels lo, lo, hi, hi."""
    coef: str
    """(N, 4) row coefficients [1, W_lo, 1, W_hi] (x0 + W y0)."""
    bases: str
    """(N, 2) table rows of the footprints at padded (1, 1) of levels lo, hi."""
    t: str
    """(N, 1) fraction towards level hi."""
    atlas: str
    """The pyramid (T, width), levels flat, finest first."""
    index: str
    """Its quad index table (`quad_rows`), (R, 4) int32."""
    index_rows: int
    """R, the index table's rows."""
    config: MaterialConfig
    """The pyramid's config: the type its tables are stored in (`texture_const`)."""
    table: str | None = None
    """The pyramid's quad table (`expand_table`), written by the first `footprint_texels`."""


def pyramid_footprint(g: GraphWriter, config: MaterialConfig, atlas: str, width: int, sigma: str,
                      finest_level: int = 0, prefix: str = "") -> Footprint:
    """sigma (N, 1) -> the `Footprint` of a trilinear lookup of the pyramid `atlas` (T, width), levels flat,
    finest first, from level ``finest_level`` on (a trimmed model: only the table rows move, so a query of
    level >= K reads the same texels with the same weights). `prefix` names a second pyramid's level-of-detail
    constants (`lod.level_rows`)."""
    tables, _ = trimmed_atlas(config, finest_level)
    rows, t = level_of_detail(g, sigma, config, finest_level, level_tables(config, finest_level), prefix)
    index = quad_rows(g, config.level_sizes(), finest_level, prefix)
    return Footprint(rows["size"], rows["coef"], rows["base"], t, atlas, index, len(tables.rows), config)


def footprint_rows(g: GraphWriter, fp: Footprint, uvw: str) -> tuple[str, str]:
    """uvw (N, 2) in [0, 1] at footprint `fp` -> the quad table's rows of levels lo, hi (N, 2), float (whole
    numbers), and the taps' weights (N, 8)."""
    both = g.op("MatMul", uvw, g.const(np.tile(np.eye(2, dtype=np.float32), (1, 2))))  # (N, 4) u v u v
    x = g.op("Sub", g.op("Mul", both, fp.size), g.scalar(0.5))  # (N, 4) texel coordinates per level
    x0 = g.op("Floor", x)
    spread = np.kron(np.eye(2, dtype=np.float32), np.ones((2, 1), np.float32))  # (4, 2): x0 + W y0
    line = g.op("MatMul", g.op("Mul", x0, fp.coef), g.const(spread))  # (N, 2)
    return g.op("Add", line, fp.bases), tap_weights(g, g.op("Sub", x, x0), 2, fp.t)


def footprint_read(g: GraphWriter, fp: Footprint, width: int, rows: str) -> str:
    """Quad table rows (N, 2) of `fp`'s levels lo, hi (`footprint_rows`) -> texels (N, 8 width)."""
    if fp.table is None:
        fp.table = expand_table(g, fp.atlas, fp.index, width)
    return _gather(g, fp.table, rows, 2, width, fp.config)


def footprint_texels(g: GraphWriter, fp: Footprint, width: int, uvw: str) -> tuple[str, str]:
    """uvw (N, 2) in [0, 1] read at footprint `fp` -> texels (N, 8 width), weights (N, 8)."""
    rows, weights = footprint_rows(g, fp, uvw)
    return footprint_read(g, fp, width, rows), weights


def pyramid_texels(g: GraphWriter, config: MaterialConfig, atlas: str, width: int, uvw: str,
                   sigma: str, finest_level: int = 0, prefix: str = "") -> tuple[str, str]:
    """Trilinear footprint: uvw (N, 2) in [0, 1], sigma (N, 1) -> texels (N, 8 width), weights (N, 8)
    (`pyramid_footprint`, then `footprint_texels`)."""
    fp = pyramid_footprint(g, config, atlas, width, sigma, finest_level, prefix)
    return footprint_texels(g, fp, width, uvw)


def texture_texels(g: GraphWriter, config: MaterialConfig, texture: str, size: int, width: int, uvw: str,
                   prefix: str) -> tuple[str, str]:
    """Bilinear footprint of one texture, (S * S, width) flat: uvw (N, 2) in [0, 1] -> texels
    (N, 4 width), weights (N, 4); its index table's vectors are named ``{prefix}quad.*`` (`quad_vectors`)."""
    tables = quad_atlas([size])
    _, _, w, base = tables.level_params[0]
    x = g.op("Sub", g.op("Mul", uvw, g.scalar(size)), g.scalar(0.5))  # (N, 2)
    x0 = g.op("Floor", x)
    line = g.op("MatMul", x0, g.const(np.asarray([[1.0], [w]])))  # (N, 1): x0 + W y0
    table = expand_table(g, texture, quad_rows(g, [size], 0, prefix), width)
    texels = _gather(g, table, g.op("Add", line, g.const([base])), 1, width, config)
    return texels, tap_weights(g, g.op("Sub", x, x0), 1, None)
