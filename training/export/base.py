"""ONNX stages of the classical base (`MaterialConfig.base`), written as `training/model/base.py` computes them: the base
maps' lookup once per query group (`read_base`: only the channels that vary between texels; the horizons in a
table of their own), the horizon's sine towards each light (`horizon_sine`: the two azimuths around it), the
decoder's inputs in the base normal's frame (`frame_inputs`, `MaterialConfig.local_frame`), the BSDF per light
(`base_answer`) and the decoder's correction of it (`corrected`); and the small vector helpers the export's other
stages share (`dot`, `lift`, `half_direction`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from onnx import TensorProto

from neumip.core import weights as W
from neumip.core.config import (BASE_ALPHA2_FLOOR, BASE_AZIMUTH_FLOOR, BASE_AZIMUTH_KERNEL, BASE_CHANNELS,
                                BASE_COS_FLOOR, BASE_HORIZONS, BASE_LOG_CEILING, BASE_OUTPUTS, BASE_SHADOW_SOFTNESS,
                                BASE_WI_FLOOR, HALF_FLOOR, MaterialConfig)
from neumip.training.export.lod import BASE_PREFIX
from neumip.training.export.lookup import (expand_table, footprint_read, footprint_rows, pyramid_footprint, read_rows,
                                          stored_texture, texture_const)
from neumip.training.export.onnx_graph import GraphWriter


def half_direction(g: GraphWriter, wi3: str, wo3: str) -> str:
    """(M, 3) unit wi, wo -> (M, 3) h = (wi + wo) / sqrt(max(|wi + wo|^2, HALF_FLOOR)) (`base.half_direction`)."""
    total = g.op("Add", wi3, wo3)
    return g.op("Div", total, g.op("Sqrt", g.op("Max", dot(g, total, total), g.scalar(HALF_FLOOR))))


def dot(g: GraphWriter, a: str, b: str) -> str:
    """(M, 3), (M, 3) -> (M, 1) a . b (summed by a MatMul with ones: one order per row)."""
    return g.op("MatMul", g.op("Mul", a, b), g.const(np.ones((3, 1), np.float32)))


def lift(g: GraphWriter, w: str) -> str:
    """(M, 2) x, y of unit vectors -> (M, 3) with z = sqrt(max(1 - x^2 - y^2, 0))."""
    r2 = g.op("MatMul", g.op("Mul", w, w), g.const(np.ones((2, 1), np.float32)))
    return g.op("Concat", w, g.op("Sqrt", g.op("Max", g.op("Sub", g.scalar(1.0), r2), g.scalar(0.0))), axis=1)


MAP_CHANNELS = BASE_CHANNELS - BASE_HORIZONS
"""The base pyramid's channels that the BSDF reads once per group (colours, F0, slopes, alpha^2); the
horizons after them are read per light."""


@dataclass(frozen=True)
class BaseRead:
    """The base pyramid read once per query group (`read_base`)."""

    maps: str
    """(N, MAP_CHANNELS) the BSDF's maps at the group's footprint."""
    rows: str
    """(N, 2) the footprint's quad rows of levels lo, hi (float), where `horizon_sine` reads per light."""
    taps: str
    """(N, 8) the footprint's tap weights."""
    horizons: str
    """(R BASE_HORIZONS, 4) horizon table: row r BASE_HORIZONS + j holds azimuth j's sine at quad row r's 4 taps, in the
    textures' type (`lookup.texture_const`)."""
    config: MaterialConfig
    """The base pyramid's config (`MaterialConfig.base_pyramid`)."""


BASE_VARYING = "base_maps.varying"
"""Weights-dict key (V,) int64 of the map channels (of `MAP_CHANNELS`) that vary between the base atlas' texels; the
file stores those and the horizons only (`read_base`). A weights dict may give it (read back from a model, or kept
by `neumip trim`, whose coarse levels alone may make more channels look constant); otherwise it comes from the atlas."""
BASE_PLACE = "base_maps.place"
"""The initializer (V, MAP_CHANNELS) 0/1: stored column i is map channel j (absent where no channel varies)."""
BASE_CONSTANT = "base_maps.constant"
"""The initializer (1, MAP_CHANNELS): each constant map channel's value (0 at the varying ones)."""


def base_layout(weights: dict, config: MaterialConfig) -> tuple[list[int], np.ndarray]:
    """The base atlas' varying map channels (``weights[BASE_VARYING]`` where given, else those not the same in every
    texel of the atlas as stored) and the (1, MAP_CHANNELS) row of the constant ones' values (0 at the varying)."""
    atlas = stored_texture(weights[W.BASE], config)
    if BASE_VARYING in weights:
        varying = [int(c) for c in np.asarray(weights[BASE_VARYING]).ravel()]
    else:
        varying = [c for c in range(MAP_CHANNELS) if not np.all(atlas[:, c] == atlas[0, c])]
    constants = np.where(np.isin(np.arange(MAP_CHANNELS), varying), 0.0, atlas[0, :MAP_CHANNELS])[None]
    return varying, constants.astype(np.float32)


def base_from_stored(stored: np.ndarray, place: np.ndarray | None, constants: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The base atlas as the file stores it (T, V + BASE_HORIZONS), its `BASE_PLACE` (None: V = 0) and
    `BASE_CONSTANT` -> the whole atlas (T, BASE_CHANNELS) and its varying channels (V,) (`read_base`'s inverse)."""
    varying = np.zeros(0, np.int64) if place is None else np.argmax(place, axis=1).astype(np.int64)
    if place is not None and not np.array_equal(place, np.eye(MAP_CHANNELS, dtype=place.dtype)[varying]):
        raise ValueError(f"{BASE_PLACE} is not a placement of map channels")
    if stored.shape[1] != len(varying) + BASE_HORIZONS or constants.shape != (1, MAP_CHANNELS):
        raise ValueError(f"base atlas of {stored.shape[1]} columns for {len(varying)} varying channels, constants of "
                         f"shape {constants.shape}")
    atlas = np.empty((stored.shape[0], BASE_CHANNELS), np.float32)
    atlas[:, :MAP_CHANNELS] = constants
    atlas[:, varying] = stored[:, :len(varying)]
    atlas[:, MAP_CHANNELS:] = stored[:, len(varying):]
    return atlas, varying


def read_base(g: GraphWriter, config: MaterialConfig, weights: dict, uv: str, sigma: str,
              finest_level: int = 0) -> BaseRead:
    """The base pyramid's trilinear footprint at uv (N, 2) in [0, 1), sigma (N, 1): the maps, and where the
    horizons are read per light. ``finest_level``: the finest level ``weights["base_maps"]`` holds (a
    trimmed model, `lod.pyramid_finest_level`).

    A map channel that is the same in every texel (F0 of a material without metal, the colour of a plain
    one) is a constant of the graph (`BASE_CONSTANT`), neither stored per texel nor read: the file's atlas holds
    the varying channels and the horizons (`base_layout`; `base_from_stored` puts the whole atlas back together)."""
    base = config.base_pyramid()
    varying, constants = base_layout(weights, config)
    width = len(varying)
    atlas = stored_texture(weights[W.BASE], config)[:, varying + list(range(MAP_CHANNELS, BASE_CHANNELS))]
    stored = texture_const(g, np.ascontiguousarray(atlas), W.BASE, config)  # (T, V + H)
    atlas_read = g.op("Slice", stored, g.const([0], np.int64), g.const([width], np.int64), g.const([1], np.int64)) \
        if width else stored  # (T, V)
    fp = pyramid_footprint(g, base, atlas_read, width, sigma, finest_level, BASE_PREFIX)
    rows, taps = footprint_rows(g, fp, uv)  # (N, 2), (N, 8)
    if varying:
        fp.table = expand_table(g, fp.atlas, fp.index, width)
        texels = footprint_read(g, fp, width, rows)  # (N, 8 V)
        spread = np.kron(np.eye(8, dtype=np.float32), np.ones((1, width), np.float32))  # (8, 8 V)
        weighted = g.op("Mul", texels, g.op("MatMul", taps, g.const(spread)))
        summed = g.op("MatMul", weighted, g.const(np.tile(np.eye(width, dtype=np.float32), (8, 1))))
        place = np.eye(MAP_CHANNELS, dtype=np.float32)[varying]  # (V, MAP_CHANNELS)
        maps = g.op("Add", g.op("MatMul", summed, g.const(place, name=BASE_PLACE)), g.const(constants, name=BASE_CONSTANT))
    else:
        maps = g.op("Add", g.op("MatMul", taps, g.const(np.zeros((8, MAP_CHANNELS), np.float32))),
                    g.const(constants, name=BASE_CONSTANT))
    return BaseRead(maps, rows, taps, _horizon_table(g, stored, width, fp.index, fp.index_rows), base)


def _horizon_table(g: GraphWriter, atlas: str, first: int, index: str, rows: int) -> str:
    """Constant subgraph: the base atlas as stored (T, V + BASE_HORIZONS, the horizons from column `first` on) and its
    quad index table (R, 4) -> (R BASE_HORIZONS, 4) the horizons' quad table, one row per quad row and azimuth
    (`BaseRead.horizons`)."""
    if rows * BASE_HORIZONS >= 2**24:
        raise ValueError(f"{rows} base table rows: the horizons' float32 row arithmetic is exact only below "
                         f"2^24 / {BASE_HORIZONS}")
    columns = g.const(np.arange(first, first + BASE_HORIZONS), np.int64)
    flat = g.shape(g.op("Gather", atlas, columns, axis=1), [-1])  # (T BASE_HORIZONS,): texel t, azimuth j at t H + j
    texel = g.op("Cast", g.shape(index, [-1, 1, 4]), to=TensorProto.INT64)  # (R, 1, 4)
    azimuths = g.const(np.arange(BASE_HORIZONS).reshape(1, -1, 1), np.int64)  # (1, H, 1)
    entries = g.op("Add", g.op("Mul", texel, g.const([BASE_HORIZONS], np.int64)), azimuths)  # (R, H, 4)
    return g.op("Gather", flat, g.shape(entries, [-1, 4]), axis=0)


def horizon_sine(g: GraphWriter, read: BaseRead, rows: str, taps: str, wi: str) -> str:
    """The sine of the horizon's elevation towards each light, as `base.visibility` interpolates it: (M, 2)
    quad rows and (M, 8) tap weights of the base footprint, (M, 2) wi -> (M, 1).

    Of the BASE_HORIZONS azimuths' weights max(cos(phi - phi_j) - cos(45 deg), 0) only the two azimuths
    around wi's can be nonzero (j0 = floor(phi / 45 deg) and j0 + 1), so only their columns are read, per
    light: 16 texels, not the 64 of all eight azimuths at the footprint's 8 taps."""
    if BASE_HORIZONS != 8:
        raise ValueError("the octant arithmetic below assumes 8 horizon azimuths")
    x, y = g.pick(wi, 2, [0]), g.pick(wi, 2, [1])
    below = g.op("Less", y, g.scalar(0.0))  # phi in [180, 360): turn by 180 degrees
    x1, y1 = g.op("Where", below, g.op("Neg", x), x), g.op("Where", below, g.op("Neg", y), y)
    left = g.op("LessOrEqual", x1, g.scalar(0.0))  # phi in [90, 180]: turn by -90 degrees
    x2, y2 = g.op("Where", left, y1, x1), g.op("Where", left, g.op("Neg", x1), y1)
    upper = g.op("GreaterOrEqual", y2, x2)  # phi in [45, 90]

    def count(b: str, k: float) -> str:
        return g.op("Mul", g.op("Cast", b, to=TensorProto.FLOAT), g.scalar(k))

    j0 = g.op("Add", g.op("Add", count(below, 4.0), count(left, 2.0)), count(upper, 1.0))  # (M, 1) in 0..7
    j1 = g.op("Sub", g.op("Add", j0, g.scalar(1.0)), count(g.op("GreaterOrEqual", j0, g.scalar(7.0)), 8.0))
    pair = g.op("Concat", j0, j1, axis=1)  # (M, 2)
    # cos(phi - phi_j) for j0, j1: phi turned by the octant's quarter turns is in [0, 90], phi_j0 in it is 45 upper
    diagonal = g.op("Mul", g.op("Add", x2, y2), g.scalar(math.sqrt(0.5)))
    r2 = g.op("MatMul", g.op("Mul", wi, wi), g.const(np.ones((2, 1), np.float32)))
    r = g.op("Sqrt", g.op("Max", r2, g.scalar(BASE_AZIMUTH_FLOOR * BASE_AZIMUTH_FLOOR)))
    cosines = [g.op("Div", g.op("Where", upper, diagonal, x2), r), g.op("Div", g.op("Where", upper, y2, diagonal), r)]
    kernel = g.op("Max", g.op("Sub", g.op("Concat", *cosines, axis=1), g.scalar(BASE_AZIMUTH_KERNEL)), g.scalar(0.0))
    total = g.op("MatMul", kernel, g.const(np.ones((2, 1), np.float32)))
    weight = g.op("Div", kernel, g.op("Max", total, g.scalar(BASE_AZIMUTH_FLOOR)))  # (M, 2)
    # table rows (M, 4): (lo, j0), (lo, j1), (hi, j0), (hi, j1); each holds 4 taps
    at = np.array([[8.0, 8.0, 0.0, 0.0], [0.0, 0.0, 8.0, 8.0]], np.float32)
    of = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 1.0]], np.float32)
    line = g.op("Add", g.op("MatMul", rows, g.const(at)), g.op("MatMul", pair, g.const(of)))
    texels = g.shape(read_rows(g, read.horizons, line, read.config), [-1, 16])
    spread = np.zeros((8, 16), np.float32)  # tap weight (level l, tap t) -> columns (l, a, t) for a = j0, j1
    pick = np.zeros((16, 2), np.float32)  # columns (l, a, t) -> azimuth a
    for level in range(2):
        for a in range(2):
            for t in range(4):
                spread[4 * level + t, 8 * level + 4 * a + t] = 1.0
                pick[8 * level + 4 * a + t, a] = 1.0
    sines = g.op("MatMul", g.op("Mul", texels, g.op("MatMul", taps, g.const(spread))), g.const(pick))  # (M, 2)
    return g.op("MatMul", g.op("Mul", weight, sines), g.const(np.ones((2, 1), np.float32)))


def base_normal(g: GraphWriter, maps: str) -> str:
    """maps (M, MAP_CHANNELS) -> (M, 3) the base's normal normalize(-dh/du, -dh/dv, 1)."""
    to_normal = np.zeros((MAP_CHANNELS, 3), np.float32)
    to_normal[6, 0] = to_normal[7, 1] = -1.0
    n = g.op("Add", g.op("MatMul", maps, g.const(to_normal)), g.const(np.array([[0.0, 0.0, 1.0]], np.float32)))
    return g.op("Div", n, g.op("Sqrt", dot(g, n, n)))


def frame_inputs(g: GraphWriter, n: str, wi: str, wo: str) -> str:
    """The base's normal (M, 3) (`base_normal`), wi, wo (M, 2) -> (M, 6) wi and wo in its frame, as
    `base.frame_inputs` computes them."""
    nx, ny, nz = (g.pick(n, 3, [i]) for i in range(3))
    a = g.op("Div", g.scalar(1.0), g.op("Add", nz, g.scalar(1.0)))
    cross = g.op("Mul", g.op("Mul", g.op("Neg", nx), ny), a)
    t = g.op("Concat", g.op("Sub", g.scalar(1.0), g.op("Mul", g.op("Mul", nx, nx), a)), cross, g.op("Neg", nx), axis=1)
    b = g.op("Concat", cross, g.op("Sub", g.scalar(1.0), g.op("Mul", g.op("Mul", ny, ny), a)), g.op("Neg", ny), axis=1)
    return g.op("Concat", *(dot(g, w, f) for w in (lift(g, wi), lift(g, wo)) for f in (t, b, n)), axis=1)


def _visibility(g: GraphWriter, wi_z: str, horizon: str) -> str:
    """wi_z, the horizon's sine towards wi (M, 1) -> (M, 1) the visibility V(wi), `base.visibility`."""
    lit = g.op("Add", g.op("Div", g.op("Sub", wi_z, horizon), g.scalar(BASE_SHADOW_SOFTNESS)), g.scalar(0.5))
    return g.op("Min", g.op("Max", lit, g.scalar(0.0)), g.scalar(1.0))


def light_visibility(g: GraphWriter, horizon: str, wi: str) -> str:
    """The horizon's sine towards wi (M, 1) (`horizon_sine`), wi (M, 2) -> (M, 1) the base's visibility of the light,
    as `base.light_visibility` computes it (the decoder's input with `MaterialConfig.visibility_input`)."""
    return _visibility(g, g.op("MatMul", lift(g, wi), g.const(np.array([[0.0], [0.0], [1.0]], np.float32))), horizon)


def base_answer(g: GraphWriter, maps: str, horizon: str | None, wi: str, wo: str, n: str | None = None,
                terminator: str = "all", lit: str | None = None) -> str:
    """maps (M, MAP_CHANNELS), the horizon's sine towards wi (M, 1) (`horizon_sine`), wi, wo (M, 2) -> (M, 3): the
    base's answer, as `base.base_answer` computes it. `lit`: its visibility of the light where the decoder's input
    computed it (`light_visibility`; `horizon` is then not read)."""
    def columns(lo: int, hi: int) -> str:
        return g.pick(maps, MAP_CHANNELS, list(range(lo, hi)))

    def clamp_low(x: str, low: float) -> str:
        return g.op("Max", x, g.scalar(low))

    wi3, wo3 = lift(g, wi), lift(g, wo)
    n = n or base_normal(g, maps)  # (given where the local frame computed it)
    h = half_direction(g, wi3, wo3)
    alpha2 = clamp_low(columns(8, 9), BASE_ALPHA2_FLOOR)
    cos_i, cos_o, cos_h = (clamp_low(dot(g, n, w), 0.0) for w in (wi3, wo3, h))
    d = g.op("Add", g.op("Mul", g.op("Mul", cos_h, cos_h), g.op("Sub", alpha2, g.scalar(1.0))), g.scalar(1.0))
    distribution = g.op("Div", alpha2, g.op("Mul", g.op("Mul", d, d), g.scalar(math.pi)))

    def smith_g1(c: str) -> str:
        root = g.op("Sqrt", g.op("Add", alpha2, g.op("Mul", g.op("Sub", g.scalar(1.0), alpha2), g.op("Mul", c, c))))
        return g.op("Div", g.op("Mul", c, g.scalar(2.0)), g.op("Add", c, root))

    f0 = columns(3, 6)
    s = g.op("Sub", g.scalar(1.0), g.op("Min", clamp_low(dot(g, h, wi3), 0.0), g.scalar(1.0)))
    s2 = g.op("Mul", s, s)
    schlick = g.op("Mul", g.op("Mul", s2, s2), s)
    fresnel = g.op("Add", f0, g.op("Mul", g.op("Sub", g.scalar(1.0), f0), schlick))
    masking = g.op("Mul", g.op("Mul", distribution, smith_g1(cos_i)), smith_g1(cos_o))
    specular = g.op("Div", g.op("Mul", masking, fresnel), g.op("Mul", clamp_low(cos_o, BASE_COS_FLOOR), g.scalar(4.0)))
    diffuse = g.op("Mul", columns(0, 3), g.op("Div", cos_i, g.scalar(math.pi)))
    z = g.const(np.array([[0.0], [0.0], [1.0]], np.float32))
    wi_z = g.op("MatMul", wi3, z)
    if terminator != "none":  # S(g) (`MaterialConfig.terminator`), written before V: the node order of older files
        s_g = g.op("Min", g.op("Div", wi_z, clamp_low(g.op("Mul", cos_i, g.op("MatMul", n, z)), BASE_COS_FLOOR)),
                   g.scalar(1.0))
        soften = g.op("Mul", s_g, g.op("Sub", g.op("Add", g.scalar(1.0), s_g), g.op("Mul", s_g, s_g)))
    lit = lit or _visibility(g, wi_z, horizon)
    if terminator == "all":
        reflected = g.op("Mul", g.op("Add", diffuse, specular), soften)
    elif terminator == "specular":
        reflected = g.op("Add", diffuse, g.op("Mul", specular, soften))
    else:
        reflected = g.op("Add", diffuse, specular)
    return g.op("Div", g.op("Mul", reflected, lit), clamp_low(wi_z, BASE_WI_FLOOR))


def corrected(g: GraphWriter, base: str, out: str) -> str:
    """base (M, 3), decoder output (M, BASE_OUTPUTS) -> base * exp(min(c, ceiling)) + a (`base.corrected`)."""
    log_part = np.zeros((BASE_OUTPUTS, 3), np.float32)
    log_part[:3] = np.eye(3)
    add_part = np.zeros((BASE_OUTPUTS, 3), np.float32)
    add_part[3:] = np.eye(3)
    c = g.op("Min", g.op("MatMul", out, g.const(log_part)), g.scalar(BASE_LOG_CEILING))
    return g.op("Add", g.op("Mul", base, g.op("Exp", c)), g.op("MatMul", out, g.const(add_part)))
