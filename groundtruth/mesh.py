"""Microgeometry as Mitsuba meshes: the tiled heightfield the query tracer uses, and the same
material as real displaced geometry on a surface for reference renders.

The heightfield is a regular triangle grid through the height samples (texel centres, periodic),
so the surface is the same piecewise-linear function in both uses. Texture coordinates are in tile
units (``uv = (x, y)``); the principled BSDF's bitmaps wrap with ``repeat``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from neumip.groundtruth.description import Microgeometry

log = logging.getLogger(__name__)


@dataclass
class TilingConfig:
    """How much tiled geometry surrounds the central tile the queries aim at."""

    max_zenith_deg: float = 85.0
    """Rays up to this zenith angle stay on geometry (margin = depth * tan of it)."""
    max_margin: float = 4.0
    """Cap on the margin around the central tile, in tiles (deeper materials lose grazing rays)."""


def margin_tiles(depth: float, resolution: int, config: TilingConfig) -> float:
    """Width in tiles of the geometry needed around the central tile for a material of `depth`."""
    need = depth * math.tan(math.radians(config.max_zenith_deg))
    if need > config.max_margin:
        log.warning(
            "depth %.3g needs a %.2f-tile margin for %g-degree rays; capped at %g tiles",
            depth, need, config.max_zenith_deg, config.max_margin,
        )
    return max(min(need, config.max_margin), 1.0 / resolution)


# --- heightfield geometry (numpy) ------------------------------------------------------------------


def sample_periodic(field: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """Bilinear periodic interpolation of an (R, R[, C]) field at tile coordinates: (len(ys), len(xs)[, C]).

    Sample ``field[row, col]`` sits at ``((col + .5) / R, (row + .5) / R)``.
    """
    res = field.shape[0]

    def weights(coords: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = coords * res - 0.5
        i0 = np.floor(t).astype(np.int64)
        return i0 % res, (i0 + 1) % res, t - i0

    c0, c1, fx = weights(xs)
    r0, r1, fy = weights(ys)
    extra = (None,) * (field.ndim - 2)
    fx = fx[(None, slice(None)) + extra]
    fy = fy[(slice(None), None) + extra]
    top = field[np.ix_(r0, c0)] * (1 - fx) + field[np.ix_(r0, c1)] * fx
    bottom = field[np.ix_(r1, c0)] * (1 - fx) + field[np.ix_(r1, c1)] * fx
    return top * (1 - fy) + bottom * fy


def height_gradient(height: np.ndarray) -> np.ndarray:
    """(R, R, 2) periodic central-difference gradient (dh/du, dh/dv) of an (R, R) height map in tile units."""
    res = height.shape[0]
    dx = (np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)) * (res / 2)
    dy = (np.roll(height, -1, axis=0) - np.roll(height, 1, axis=0)) * (res / 2)
    return np.stack([dx, dy], axis=2)


def grid_arrays(geo: Microgeometry, xs: np.ndarray, ys: np.ndarray) -> dict[str, np.ndarray]:
    """Vertex grid through the heightfield at tile coordinates xs (columns) and ys (rows).

    Returns positions (V, 3), texcoords (V, 2), normals (V, 3) or None, faces (F, 3) uint32 with
    ``V = len(xs) * len(ys)`` and ``F = 2 (len(xs) - 1)(len(ys) - 1)``; positions are in tile units.
    """
    nx, ny = len(xs), len(ys)
    z = sample_periodic(geo.height, xs, ys)  # (ny, nx)
    gx, gy = np.meshgrid(xs, ys)
    positions = np.stack([gx, gy, z], axis=2).reshape(-1, 3)
    normals = None
    if geo.normals == "smooth" and geo.height.shape[0] > 1:
        grad = sample_periodic(height_gradient(geo.height), xs, ys)  # (ny, nx, 2)
        n = np.concatenate([-grad, np.ones((ny, nx, 1))], axis=2)
        normals = (n / np.linalg.norm(n, axis=2, keepdims=True)).reshape(-1, 3)
    corner = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    faces = np.concatenate(
        [np.stack([corner, corner + 1, corner + nx + 1], 1), np.stack([corner, corner + nx + 1, corner + nx], 1)]
    )
    return {
        "positions": positions,
        "texcoords": positions[:, :2].copy(),
        "normals": normals,
        "faces": faces.astype(np.uint32),
    }


def tiled_coords(resolution: int, margin: float) -> np.ndarray:
    """Texel-centre coordinates covering ``[-margin, 1 + margin]`` (at least one texel beyond the tile)."""
    extra = math.ceil(margin * resolution) + 1
    return (np.arange(-extra, resolution + extra + 1) + 0.5) / resolution


def surface_coords(resolution: int, tiles: int) -> np.ndarray:
    """Coordinates covering exactly ``[0, tiles]``: the tile edges plus every texel centre between."""
    centres = (np.arange(tiles * resolution) + 0.5) / resolution
    return np.concatenate([[0.0], centres, [float(tiles)]])


# --- Mitsuba objects -------------------------------------------------------------------------------


def make_bsdf(mi, geo: Microgeometry, to_uv=None):
    """The material's Mitsuba BSDF: its homogeneous BSDF, or a principled BSDF driven by its maps
    (``to_uv``: an optional transform of the shape's uv before the maps are read)."""
    if geo.bsdf is not None:
        try:
            return mi.load_dict(geo.bsdf)
        except Exception as exc:  # Mitsuba reports plugin errors as RuntimeError / TypeError
            raise ValueError(f"[bsdf] is not a valid Mitsuba BSDF: {exc}") from None

    def texture(arr: np.ndarray):
        if arr.size == arr.shape[-1] or arr.size == 1:  # a constant map
            value = arr.reshape(-1)
            return {"type": "rgb", "value": value.tolist()} if value.size == 3 else float(value[0])
        data = arr if arr.ndim == 3 else arr[:, :, None]
        bitmap = {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(data, dtype=np.float32)),
                  "raw": True, "wrap_mode": "repeat"}
        if to_uv is not None:
            bitmap["to_uv"] = to_uv
        return bitmap

    return mi.load_dict({
        "type": "principled",
        "base_color": texture(geo.base_color),
        "roughness": texture(geo.roughness),
        "metallic": texture(geo.metallic),
        "specular": geo.specular,
    })


def make_mesh(mi, name: str, arrays: dict[str, np.ndarray], bsdf):
    """A Mitsuba mesh from :func:`grid_arrays` output (positions in scene units), with `bsdf` attached."""
    positions, faces, normals = arrays["positions"], arrays["faces"], arrays["normals"]
    mesh = mi.Mesh(
        name, positions.shape[0], faces.shape[0],
        has_vertex_normals=normals is not None, has_vertex_texcoords=True,
    )
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.astype(np.float32).ravel())
    params["vertex_texcoords"] = mi.Float(arrays["texcoords"].astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    if normals is not None:
        params["vertex_normals"] = mi.Float(normals.astype(np.float32).ravel())
    params.update()
    mesh.set_bsdf(bsdf)
    return mesh


def query_scene(mi, geo: Microgeometry, config: TilingConfig | None = None):
    """The scene the query tracer traces: the central tile plus a margin of tiled heightfield.

    Returns ``(scene, margin_in_tiles)``. No emitter: the tracer handles its distant light itself.
    """
    config = config or TilingConfig()
    res = geo.height.shape[0]
    margin = margin_tiles(geo.depth, res, config)
    coords = tiled_coords(res, margin)
    arrays = grid_arrays(geo, coords, coords)
    mesh = make_mesh(mi, "microgeometry", arrays, make_bsdf(mi, geo))
    log.info("query scene: %d triangles, margin %.2f tiles, depth %.4g", arrays["faces"].shape[0], margin, geo.depth)
    return mi.load_dict({"type": "scene", "microgeometry": mesh}), margin


def reference_surface(mi, geo: Microgeometry, tiles: int, to_world=None):
    """The material as real displaced geometry, for reference renders: a Mitsuba mesh shaped like
    Mitsuba's ``rectangle`` (``[-1, 1]^2`` in its local xy plane, normal +z), transformed by `to_world`.

    It holds ``tiles x tiles`` tiles; its texture coordinates are in tile units (``uv = tiles *``
    the rectangle's uv), so a neural material on a ``rectangle`` with uv scaled by `tiles` lines up.
    The microgeometry lies below the rectangle (the reference plane is its top), scaled with it.
    """
    coords = surface_coords(geo.height.shape[0], tiles)
    arrays = grid_arrays(geo, coords, coords)
    scale = 2.0 / tiles
    local = arrays["positions"] * scale - np.array([1.0, 1.0, 0.0])
    if to_world is None:
        to_world = mi.ScalarTransform4f()
    to_world = mi.ScalarTransform4f(to_world)
    matrix = np.array(to_world.matrix, dtype=np.float64)
    arrays["positions"] = local @ matrix[:3, :3].T + matrix[:3, 3]
    if arrays["normals"] is not None:
        normals = arrays["normals"] @ np.linalg.inv(matrix[:3, :3])  # inverse transpose
        arrays["normals"] = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    log.info("reference surface: %d x %d tiles, %d triangles", tiles, tiles, arrays["faces"].shape[0])
    return make_mesh(mi, "reference_surface", arrays, make_bsdf(mi, geo))


def reference_block(mi, geo: Microgeometry, block: int):
    """One ``block x block`` tile block of the displaced geometry as a Mitsuba ``shapegroup`` dictionary
    (a dictionary: an instance finds a group by its key only while the scene is loaded).

    In the block's own frame the geometry spans ``[0, block]^2`` in xy (tile units, uv = xy) and lies
    below ``z = 0``; :func:`reference_instances` places copies of it.
    """
    coords = surface_coords(geo.height.shape[0], block)
    arrays = grid_arrays(geo, coords, coords)
    mesh = make_mesh(mi, "reference_block", arrays, make_bsdf(mi, geo))
    log.info("reference block: %d x %d tiles, %d triangles", block, block, arrays["faces"].shape[0])
    return {"type": "shapegroup", "block": mesh}


def reference_instances(mi, geo: Microgeometry, origins: np.ndarray, block: int, to_world=None) -> dict:
    """The material as real displaced geometry built from instances of one tile block.

    ``origins`` (K, 2) are integer tile coordinates of the blocks' corners; the geometry is in tile
    units, mapped to the scene by ``to_world``. Returns scene-dictionary entries: the ``shapegroup``
    (id ``reference_block``) and one ``instance`` per origin referring to it by id (Mitsuba's
    instances must reference the group through ``{"type": "ref"}``). Memory grows with the block,
    not with the number of tiles, so views of thousands of tiles render in seconds.
    """
    origins = np.asarray(origins, dtype=np.int64).reshape(-1, 2)
    base = mi.ScalarTransform4f(to_world) if to_world is not None else mi.ScalarTransform4f()
    entries = {"reference_block": reference_block(mi, geo, block)}
    for k, (x, y) in enumerate(origins.tolist()):
        entries[f"reference_{k}"] = {
            "type": "instance",
            "shapegroup": {"type": "ref", "id": "reference_block"},
            "to_world": base @ mi.ScalarTransform4f().translate([float(x), float(y), 0.0]),
        }
    log.info("reference instances: %d blocks of %d x %d tiles", len(origins), block, block)
    return entries


def block_origins(lo: np.ndarray, hi: np.ndarray, block: int) -> np.ndarray:
    """(K, 2) corners of the ``block``-sized blocks covering the xy box ``[lo, hi]`` (tile units)."""
    start = np.floor(np.asarray(lo) / block).astype(np.int64)
    stop = np.ceil(np.asarray(hi) / block).astype(np.int64)
    xs = np.arange(start[0], stop[0]) * block
    ys = np.arange(start[1], stop[1]) * block
    gx, gy = np.meshgrid(xs, ys)
    return np.stack([gx.ravel(), gy.ravel()], axis=1)
