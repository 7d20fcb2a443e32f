"""The report's views: an oblique plane seen by a perspective camera, lit by a directional light
plus a dim constant environment, at distances chosen for a pixel footprint.

World frame: the material plane is ``z = 0`` with **one tile per world unit**, tile coordinates
``(u, v) = (x, y)`` (the material repeats with period 1). The camera looks at the origin from zenith
``theta`` in the ``y-z`` plane (it sees the plane receding along +y). Every distance is rendered under
each light of :data:`LIGHTS`: high, from the side, and from in front of the viewer (beyond the
plane's centre, lighting it towards the camera).

Footprint. A pixel's footprint (std) is ``filter_std`` (0.5 px for the film's default Gaussian
filter) times the larger uv length of one pixel step; `neumip_path` queries one sample's share of it
(``sample_footprint(spp)``: all of it at 1 spp, 1/8 from 64 spp). At the image centre the step is
``distance * pixel_angle / cos(theta)`` tiles along the receding axis, so a view for level ``L`` of a
material whose maps have ``R`` texels per tile (its description's ``resolution``, whatever model is
judged) puts the camera at the distance where the pixel footprint is ``2^L / R`` tiles (``2^L`` map
texels; what a 1-spp render queries). The footprint grows towards the top of the image
(perspective); the vertical field of view is kept small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FILTER_STD_PX = 0.5
"""Std (pixels) of Mitsuba's default Gaussian reconstruction filter: the footprint of a pixel."""


@dataclass(frozen=True)
class Light:
    """A directional light of the views."""

    name: str
    """Identifier (a suffix of the view names)."""
    zenith: float
    """Zenith angle, degrees."""
    azimuth: float
    """Azimuth from the direction towards the camera, degrees (90: from the side; above 90: in front
    of the viewer, lighting the plane towards the camera)."""


LIGHTS = (Light("high", 20.0, 45.0), Light("side", 60.0, 90.0), Light("front", 50.0, 135.0))
"""The lights of every distance view: nearly overhead, from the side, and from in front of the viewer
(the set-up under which one material's verdict flipped in issue 24)."""
LADDER_LIGHT = "side"
"""The light whose distance views also get spp ladders (error against time); the others are scored
at equal spp."""
LEVELS = (0, 2, 4, 6, 8)
"""Footprints of the distance views: 1, 4, 16, 64 and 256 map texels at the image centre."""


@dataclass(frozen=True)
class View:
    """One camera and light set-up of the report."""

    name: str
    """Identifier (results.json key)."""
    theta: float
    """Camera zenith angle in degrees (0: looking straight down)."""
    level: float
    """Level of detail at the image centre: the footprint covers 2^level texels of the material's maps."""
    light_zenith: float = 60.0
    """Zenith angle of the directional light, degrees."""
    light_azimuth: float = 90.0
    """Azimuth of the light from the view direction, degrees (90: from the side)."""
    fov: float = 10.0
    """Vertical field of view, degrees."""
    ladder: bool = False
    """Render an spp ladder (error against time) for this view."""
    light: str = "side"
    """Name of the light (:data:`LIGHTS`), or of the view's own light set-up."""

    @property
    def footprint_texels(self) -> float:
        return 2.0**self.level


def distance_view(level: int, light: Light) -> View:
    return View(f"level{level}_{light.name}", 55.0, level, light.zenith, light.azimuth,
                ladder=light.name == LADDER_LIGHT, light=light.name)


DISTANCE_VIEWS = tuple(distance_view(lv, light) for light in LIGHTS for lv in LEVELS)
"""An oblique plane (55 degrees) at every footprint of :data:`LEVELS`, under every light."""
EXTRA_VIEWS = (
    View("grazing75", 75.0, 2, fov=6.0),
    View("grazing85", 85.0, 2, fov=4.0),
    View("low_light", 55.0, 2, light_zenith=85.0, light="low"),
)
"""Grazing views (side light) and a light 5 degrees above the horizon (footprint of 4 map texels)."""
VIEWS = DISTANCE_VIEWS + EXTRA_VIEWS


@dataclass(frozen=True)
class Film:
    """Image size."""

    width: int
    height: int


def film_for_tiles(view: View, film: Film, resolution: int, max_tiles: float) -> Film:
    """``film``, or a smaller one of the same shape where the view would show more than ``max_tiles``
    tiles at its footprint (about ``pixels x (2 sigma)^2 / cos(theta)``): the real geometry's cost
    grows with the tiles it must build (far views of fine maps)."""
    step = 2.0 * view.footprint_texels / resolution  # tiles per pixel step at the centre
    tiles = film.width * film.height * step * step / math.cos(math.radians(view.theta))
    if tiles <= max_tiles:
        return film
    shrink = math.sqrt(max_tiles / tiles)
    return Film(max(8, round(film.width * shrink)), max(6, round(film.height * shrink)))


def pixel_angle(view: View, film: Film) -> float:
    """Angle (radians) subtended by one pixel at the image centre."""
    return 2 * math.tan(math.radians(view.fov) / 2) / film.height


def lights_of(views) -> list[str]:
    """Names of the lights of ``views``' distance views, in :data:`LIGHTS` order."""
    present = {v.light for v in views}
    return [light.name for light in LIGHTS if light.name in present]


def camera_distance(view: View, film: Film, resolution: int) -> float:
    """Distance (tiles) from the camera to the plane's centre for the view's footprint level, the
    footprint counted in texels of a ``resolution``-texel map."""
    sigma = view.footprint_texels / resolution
    return sigma * math.cos(math.radians(view.theta)) / (FILTER_STD_PX * pixel_angle(view, film))


def camera_origin(view: View, distance: float) -> np.ndarray:
    t = math.radians(view.theta)
    return np.array([0.0, -distance * math.sin(t), distance * math.cos(t)])


def light_direction(view: View) -> np.ndarray:
    """Unit vector **towards** the light (world)."""
    z, a = math.radians(view.light_zenith), math.radians(view.light_azimuth)
    # azimuth measured from the direction towards the camera (-y), rotating towards +x
    return np.array([math.sin(z) * math.sin(a), -math.sin(z) * math.cos(a), math.cos(z)])


def sensor_dict(mi, view: View, film: Film, distance: float, spp: int = 1) -> dict:
    origin = camera_origin(view, distance)
    return {
        "type": "perspective",
        "fov": view.fov,
        "fov_axis": "y",
        "near_clip": max(1e-3, distance * 1e-3),
        "far_clip": distance * 1e4,
        "to_world": mi.ScalarTransform4f().look_at(origin=origin.tolist(), target=[0, 0, 0], up=[0, 0, 1]),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {"type": "hdrfilm", "width": film.width, "height": film.height, "pixel_format": "rgb"},
    }


ENV_RADIANCE = 0.05
"""Radiance of the dim constant environment (the directional light gives unit irradiance)."""
HORIZON_SUN_DIRECTION = (-0.5, 0.3, -0.6)
"""The light of the stability section's plane out to the horizon (`stability.horizon_scene`), beside `LIGHTS`:
its direction in that scene's world (from the light), with irradiance `HORIZON_SUN_IRRADIANCE`."""
HORIZON_SUN_IRRADIANCE = 1.3
"""The horizon scene's sun's irradiance (a plane facing it)."""


def emitter_dicts(view: View) -> dict:
    """A directional light giving **unit irradiance on the plane** plus the dim environment.

    A light sample picks one of them in proportion to the irradiance it gives the plane (1 and pi ENV_RADIANCE;
    pbrt's power light distribution). Mitsuba's default picks each with probability 1/2: half the samples went to an
    environment that gives 0.16 of the light, and the other half counted the sun twice (report/README.md)."""
    wi = light_direction(view)
    cos_i = max(float(wi[2]), 1e-3)
    return {
        "sun": {"type": "directional", "direction": (-wi).tolist(), "irradiance": {"type": "rgb", "value": 1.0 / cos_i},
                "sampling_weight": 1.0},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": ENV_RADIANCE},
                "sampling_weight": math.pi * ENV_RADIANCE},
    }


def visible_corners(view: View, film: Film, distance: float) -> np.ndarray:
    """(4, 2) xy points (tile units) where the image's corner rays meet the plane, in convex order.

    Raises ValueError if a corner ray misses the plane (the view reaches the horizon).
    """
    origin = camera_origin(view, distance)
    forward = -origin / np.linalg.norm(origin)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    th = math.tan(math.radians(view.fov) / 2)
    tw = th * film.width / film.height
    points = []
    for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        d = forward + sx * tw * right + sy * th * up
        if d[2] >= -1e-6:
            raise ValueError(f"view {view.name}: the image reaches the horizon")
        points.append(origin[:2] + d[:2] * (-origin[2] / d[2]))
    return np.array(points)


def distance_to_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(K,) distances of (K, 2) points to a convex (M, 2) polygon (0 inside)."""
    edges = np.roll(polygon, -1, axis=0) - polygon  # (M, 2)
    rel = points[:, None, :] - polygon[None]  # (K, M, 2)
    cross = edges[None, :, 0] * rel[..., 1] - edges[None, :, 1] * rel[..., 0]
    inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)
    t = np.clip(np.sum(rel * edges[None], axis=2) / np.sum(edges * edges, axis=1)[None], 0.0, 1.0)
    nearest = polygon[None] + t[..., None] * edges[None]
    dist = np.linalg.norm(points[:, None, :] - nearest, axis=2).min(axis=1)
    return np.where(inside, 0.0, dist)
