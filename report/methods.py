"""The methods the report compares, each as a Mitsuba scene of the same view.

- ``R``: the real displaced microgeometry (instances of one tile block), stock ``path``.
- ``N``: the neural material (``<name>.onnx``: the shipped ones are what ``neumip fit`` makes), ``neumip_path``.
- ``N0``: the same trained without the parallax stages (``<name>_nooffset.onnx``), ``neumip_path``.
- ``Nmaps``: a second model judged beside N (``<name>_maps.onnx``, e.g. a map-informed model beside a paper's
  model of the same data), ``neumip_path``.
- ``Nmaps0``: the same trained without the parallax stages (``<name>_maps_nooffset.onnx``), ``neumip_path``.
  A neural method is compared wherever its model file is in the models folder; another is one more
  entry of :data:`NEURAL_MODELS` (and, when it is judged like N, of :data:`NO_OFFSET`).
- ``C``: the classical material: the generator's principled BSDF with full-resolution albedo,
  roughness and metallic bitmaps, and a normal map derived from the height, stock ``path``.
- ``Cmip``: the same with every map pre-filtered to the footprint's level (see :func:`mip_maps`).

Every scene has the same camera and emitters (:mod:`.views`); the flat methods use a ``rectangle``
of half-size ``S`` (an integer, so its tile coordinates ``uv * 2S = x + S`` equal the world's mod 1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from neumip.core.errors import NeumipError
from neumip.groundtruth.description import Microgeometry
from neumip.groundtruth.mesh import block_origins, height_gradient, make_bsdf, reference_instances

from neumip.report.views import Film, View, camera_distance, distance_to_polygon, emitter_dicts, sensor_dict, visible_corners

NEURAL_MODELS = {"N": "{name}", "N0": "{name}_nooffset", "Nmaps": "{name}_maps", "Nmaps0": "{name}_maps_nooffset"}
"""Neural methods and the model file each is rendered from (``<models>/<file>.onnx``; ``N`` is required)."""
NEURAL = tuple(NEURAL_MODELS)
NO_OFFSET = {"N": "N0", "Nmaps": "Nmaps0"}
"""The neural methods the report judges (verdicts, time to error, close-up checks), each with its
ablation without the offset (compared, and used for the offset's gain, not judged itself)."""
JUDGED = tuple(NO_OFFSET)
METHODS = ("R", *NEURAL, "C", "Cmip")
COMPARED = METHODS[1:]
"""The methods scored against the reference R."""
MAX_DEPTH = 5
"""Path length of every method: up to 4 surface interactions, as the ground-truth tracer's paths."""


class MissingModelError(NeumipError, FileNotFoundError):
    """A material to report on has no neural model in the models folder."""


def neural_models(name: str, models: Path) -> dict[str, Path]:
    """``{method: model file}`` of the neural methods whose file exists in ``models`` for material
    ``name``; a missing ``N`` model raises :class:`MissingModelError`."""
    files = {m: Path(models) / f"{pattern.format(name=name)}.onnx" for m, pattern in NEURAL_MODELS.items()}
    if not files["N"].is_file():
        raise MissingModelError(f"no model {files['N']} for material {name!r} (models are found by the "
                                f"description's name: train one with `neumip train ... -o {files['N']}`)")
    return {m: f for m, f in files.items() if f.is_file()}


@dataclass(frozen=True)
class SceneSpec:
    """What a method's scene of one view is built from."""

    view: View
    film: Film
    resolution: int
    """Texels per tile of the material's maps: the unit of the view's footprint."""
    max_instances: int = 48
    """The reference block grows (powers of two, within ``max_block_vertices``) until at most this
    many instances cover the view: every live instance adds to the cost of every render in the
    process (drjit's virtual calls dispatch over all of them)."""
    max_block_vertices: int = 1 << 22
    """Largest reference block, in vertices (4 M: 8 x 8 tiles of a 256^2 heightfield)."""

    @property
    def distance(self) -> float:
        return camera_distance(self.view, self.film, self.resolution)

    def corners(self) -> np.ndarray:
        return visible_corners(self.view, self.film, self.distance)

    def half_size(self, margin: float) -> int:
        return int(math.ceil(np.abs(self.corners()).max() + margin))

    def blocks(self, margin: float, height_resolution: int) -> tuple[int, np.ndarray]:
        """``(block, origins)``: reference blocks that reach within ``margin`` of the visible plane."""
        corners = self.corners()
        max_block = 1 << max(0, int(math.log2(math.sqrt(self.max_block_vertices) / height_resolution)))
        for block in (1 << k for k in range(int(math.log2(max_block)) + 1)):
            origins = block_origins(corners.min(0) - margin, corners.max(0) + margin, block)
            near = distance_to_polygon(origins + block / 2, corners) <= block / math.sqrt(2) + margin
            origins = origins[near]
            if len(origins) <= self.max_instances or block == max_block:
                return block, origins
        raise AssertionError("unreachable")


def reference_margin(geo: Microgeometry, view: View) -> float:
    """Geometry (tiles) beyond the visible region: parallax and shadows of the deepest groove, and one tile."""
    reach = geo.depth * math.tan(math.radians(min(max(view.theta, view.light_zenith), 88.0)))
    return 1.0 + reach


def _base(mi, spec: SceneSpec, integrator: str) -> dict:
    return {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": MAX_DEPTH},
        "sensor": sensor_dict(mi, spec.view, spec.film, spec.distance),
        **emitter_dicts(spec.view),
    }


def _rectangle(mi, half: int, bsdf) -> dict:
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([half, half, 1.0]), "bsdf": bsdf}


def reference_scene(mi, spec: SceneSpec, geo: Microgeometry) -> dict:
    """R: instances of one block covering the visible plane plus a margin (a material without a
    heightfield: the plane itself, with the generator's BSDF)."""
    if geo.height.shape[0] == 1:
        half = spec.half_size(2.0)
        to_uv = mi.ScalarTransform4f().scale([2.0 * half, 2.0 * half, 1.0])
        return {**_base(mi, spec, "path"), "plane": _rectangle(mi, half, make_bsdf(mi, geo, to_uv=to_uv))}
    block, origins = spec.blocks(reference_margin(geo, spec.view), geo.height.shape[0])
    scene = _base(mi, spec, "path")
    scene.update(reference_instances(mi, geo, origins, block))
    return scene


def neural_scene(mi, spec: SceneSpec, model: str, margin: float = 2.0) -> dict:
    """N / N0: a rectangle with the `neumip` BSDF of ``model``, rendered by `neumip_path`."""
    half = spec.half_size(margin)
    scene = _base(mi, spec, "neumip_path")
    scene["plane"] = _rectangle(mi, half, {"type": "neumip", "material": model, "uv_scale": 2.0 * half})
    return scene


def classical_scene(mi, spec: SceneSpec, geo: Microgeometry, mip_level: int | None = None, margin: float = 2.0) -> dict:
    """C (``mip_level`` None) or Cmip: principled maps + a normal map from the height, stock `path`."""
    half = spec.half_size(margin)
    if mip_level:
        geo = mip_maps(geo, mip_level)
    scene = _base(mi, spec, "path")
    scene["plane"] = _rectangle(mi, half, classical_bsdf(mi, geo, 2.0 * half))
    return scene


def classical_bsdf(mi, geo: Microgeometry, uv_scale: float):
    """The generator's BSDF with its maps repeated ``uv_scale`` times, wrapped in a normal map."""
    to_uv = mi.ScalarTransform4f().scale([uv_scale, uv_scale, 1.0])
    bsdf = make_bsdf(mi, geo, to_uv=to_uv)
    if geo.height.shape[0] == 1 or not np.any(geo.height):
        return bsdf
    normals = tangent_normals(geo.height)
    return mi.load_dict({
        "type": "normalmap",
        "normalmap": {"type": "bitmap", "data": mi.TensorXf(normals * 0.5 + 0.5), "raw": True,
                      "wrap_mode": "repeat", "to_uv": to_uv},
        "bsdf": bsdf,
    })


def tangent_normals(height: np.ndarray) -> np.ndarray:
    """(R, R) heights (tile units) -> (R, R, 3) unit normals in tangent space (x along +u, y along +v)."""
    grad = height_gradient(height)
    n = np.concatenate([-grad, np.ones(height.shape + (1,))], axis=2)
    return (n / np.linalg.norm(n, axis=2, keepdims=True)).astype(np.float32)


def box_down(arr: np.ndarray, k: int) -> np.ndarray:
    """Average ``2^k x 2^k`` blocks of an (H, W[, C]) periodic map (a map smaller than that: its mean)."""
    f = 1 << k
    h, w = arr.shape[:2]
    if h < f or w < f:
        return arr.mean(axis=(0, 1), keepdims=True)
    return arr.reshape(h // f, f, w // f, f, *arr.shape[2:]).mean(axis=(1, 3))


def mip_level_for(spec: SceneSpec, map_resolution: int) -> int:
    """Mip level of a ``map_resolution``-texel map for the view's centre: one texel per pixel step.

    The pixel step is ``sigma / filter_std = 2 sigma`` tiles (the texel = pixel rule of trilinear
    mip-mapping), so the level is ``log2(2 sigma * map_resolution)``, rounded, clamped to the map.
    """
    sigma = spec.view.footprint_texels / spec.resolution
    level = round(math.log2(max(2 * sigma * map_resolution, 1.0)))
    return int(min(max(level, 0), int(math.log2(map_resolution))))


def mip_maps(geo: Microgeometry, level: int) -> Microgeometry:
    """The material with every map box-averaged by ``2^level``: albedo, roughness, metallic and the
    height (whose normal map then comes from the averaged height, by finite differences at the
    coarse texel size: averaged slopes, so grooves flatten, as in a mip-mapped normal map)."""
    out = replace(
        geo,
        base_color=box_down(geo.base_color, level),
        roughness=box_down(geo.roughness, level),
        metallic=box_down(geo.metallic, level),
    )
    if geo.height.shape[0] > 1:
        out = replace(out, height=box_down(geo.height, level))
    return out
