"""Every field of a first-hit query against geometry worked out independently of the integrator.

A point light and a camera at known places, one neural shape (rectangle, sphere, or one face of a
cube seen head-on), `max_depth` 2: the evaluator gets one buffer of query groups (the light's
direction and the sampled direction, at hits where both count) and one of single queries (the one
that counts, elsewhere): one row per hit in all. From each row's (u, v) the test rebuilds the surface
point and the contract's frame (x along +u, y along +v, z the outward normal) - analytically for the
sphere, from three ray casts for a planar face - and checks that ``wo`` points at the camera, ``wi``
of the light block at the light, exactly the hits whose tangent plane faces the light are lit, and
sigma is the pixel footprint's std on the surface. A swap of wi and wo, a mirrored frame, a wrong
(u, v) or uv_scale, or a wrong sigma each fail it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.client.mitsuba.bsdf import mi
from neumip.core.contract import sample_footprint
from neumip.client.mitsuba.render import RenderConfig, render_scene

from .recording import Recording

WIDTH, FOV, UV_SCALE = 24, 30.0, 3.0
PIXEL_ANGLE = 2 * math.tan(math.radians(FOV / 2)) / WIDTH
"""Pixel spacing (radians, at the image centre)."""
FILTER_STD = 0.5
"""Std in pixels of hdrfilm's default gaussian reconstruction filter."""
SPP = 2
TOL = 2e-3


def _unit(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def scene_dict(shape: dict, camera, up, light) -> dict:
    return {
        "type": "scene",
        "integrator": {"type": "neumip_path", "max_depth": 2},
        "sensor": {
            "type": "perspective", "fov": FOV,
            "to_world": mi.ScalarTransform4f().look_at(origin=camera, target=[0, 0, 0], up=up),
            "film": {"type": "hdrfilm", "width": WIDTH, "height": WIDTH},
        },
        "light": {"type": "point", "position": light, "intensity": {"type": "rgb", "value": 10.0}},
        "shape": {**shape, "bsdf": {"type": "neumip", "material": "rand16", "uv_scale": UV_SCALE}},
    }


def sphere_geometry(u: np.ndarray, v: np.ndarray):
    """Unit sphere at the origin (Mitsuba: u = phi / 2 pi, v = theta / pi): p, x, y, z per row."""
    phi, theta = 2 * np.pi * u, np.pi * v
    p = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    x = np.stack([-np.sin(phi), np.cos(phi), 0 * phi], axis=1)  # dp/du direction
    y = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), -np.sin(theta)], axis=1)
    return p, x, y, p.copy(), 2 * np.pi * np.sin(theta), np.full_like(u, np.pi)


def planar_geometry(scene: mi.Scene, camera, targets):
    """A planar face through three ray casts from ``camera`` at ``targets``: (u, v) -> p, x, y, z."""
    o = mi.Point3f(*[np.full(3, float(c), dtype=np.float32) for c in camera])
    d = _unit(np.asarray(targets, dtype=np.float64) - np.asarray(camera, dtype=np.float64))
    si = scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(*[d[:, k].astype(np.float32) for k in range(3)])))
    assert np.all(si.is_valid().numpy())
    uv1 = np.stack([si.uv.x.numpy(), si.uv.y.numpy(), np.ones(3)], axis=1)
    p3 = np.stack([si.p.x.numpy(), si.p.y.numpy(), si.p.z.numpy()], axis=1)
    m = np.linalg.solve(uv1.astype(np.float64), p3.astype(np.float64))  # p = [u, v, 1] @ m
    dp_du, dp_dv = m[0], m[1]
    assert abs(np.dot(_unit(dp_du), _unit(dp_dv))) < 1e-4  # these faces are rectangular in uv
    z = _unit(np.cross(dp_du, dp_dv))
    z = z if np.dot(z, np.asarray(camera) - m[2]) > 0 else -z

    def geometry(u, v):
        p = np.stack([u, v, np.ones_like(u)], axis=1) @ m
        n = len(u)
        return (p, np.tile(_unit(dp_du), (n, 1)), np.tile(_unit(dp_dv), (n, 1)), np.tile(z, (n, 1)),
                np.full(n, np.linalg.norm(dp_du)), np.full(n, np.linalg.norm(dp_dv)))

    return geometry


def local(w, x, y, z) -> np.ndarray:
    """World directions (n, 3) -> contract frame (n, 3)."""
    return np.stack([(w * x).sum(1), (w * y).sum(1), (w * z).sum(1)], axis=1)


def check_first_hit_queries(model_dir, shape, camera, up, light, geometry):
    scene = mi.load_dict(scene_dict(shape, camera, up, light))
    if geometry is None:
        axis = _unit(np.asarray(camera, dtype=np.float64)) * 0.999  # just inside the face
        side = _unit(np.cross(axis, up)) * 0.4
        geometry = planar_geometry(scene, camera, [axis, axis + side, axis + np.cross(axis, side) / 0.999])
    evaluator = Recording(model_dir)
    render_scene(scene, evaluator, RenderConfig(spp=SPP, seed=3))
    # one call of query groups (hits where the light and the sampled direction both count), and one
    # of single queries (hits where one of them does) if there are such hits
    groups = [c for c in evaluator.calls if c.shape[1] == C.group_width(2)]
    singles = [c for c in evaluator.calls if c.shape[1] == C.QUERY_DIM]
    assert len(groups) == 1 and len(singles) <= 1 and len(evaluator.calls) == len(groups) + len(singles)
    rows = np.concatenate([groups[0][:, :C.QUERY_DIM], *singles])  # one row per hit
    u, v = rows[:, C.U] / UV_SCALE, rows[:, C.V] / UV_SCALE
    p, x, y, z, len_u, len_v = geometry(u.astype(np.float64), v.astype(np.float64))

    # wo: towards the camera, in the contract's frame (a mirrored y or a swapped wi/wo fails here)
    wo = local(_unit(np.asarray(camera) - p), x, y, z)
    assert np.all(wo[:, 2] > 0)
    np.testing.assert_allclose(rows[:, [C.WO_X, C.WO_Y]], wo[:, :2], atol=TOL)

    # wi: a group's first wi points at the light, and so does a single query's where the hit is lit;
    # lit = the tangent plane faces the light
    wi = local(_unit(np.asarray(light) - p), x, y, z)
    lit = np.all(np.abs(rows[:, [C.WI_X, C.WI_Y]] - wi[:, :2]) < TOL, axis=1)
    assert lit[: len(groups[0])].all() and lit.sum() > 0.2 * len(rows)
    assert np.all(wi[lit, 2] > 0)
    near = np.abs(wi[:, 2]) <= 0.01  # grazing the tangent plane: either way
    assert np.array_equal(lit[~near], wi[~near, 2] > 0)
    sampled = np.concatenate([groups[0][:, C.QUERY_DIM:], rows[~lit][:, [C.WI_X, C.WI_Y]]])
    assert np.all(np.abs(sampled - np.concatenate([wi[: len(groups[0])], wi[~lit]])[:, :2]) >= TOL,
                  axis=1).mean() > 0.95  # the sampled directions are not the light's
    assert np.all((sampled**2).sum(1) <= 1 + C.DIRECTION_TOLERANCE)

    # sigma: one sample's share of the std of the pixel's footprint on the surface, in tiles: between the head-on size on
    # the longer uv axis and the foreshortened size on the shorter one (an off-axis pixel subtends
    # down to cos^2 of the half-diagonal, 0.87, of the central pixel's angle)
    distance = np.linalg.norm(np.asarray(camera) - p, axis=1)
    head_on = UV_SCALE * FILTER_STD * sample_footprint(SPP) * PIXEL_ANGLE * distance
    sigma = rows[:, C.SIGMA]
    assert np.all(sigma >= 0.85 * head_on / np.maximum(len_u, len_v))
    facing = wo[:, 2] > 0.25  # nearer the silhouette the tangent plane and the surface part ways
    assert np.all((sigma <= 1.02 * head_on / np.minimum(len_u, len_v) / wo[:, 2])[facing])
    return rows


def test_rectangle(model_dir):
    check_first_hit_queries(model_dir, {"type": "rectangle"}, [0.4, -0.3, 3.5], [0, 1, 0], [-1.5, 1.0, 2.0], None)


def test_sphere(model_dir):
    rows = check_first_hit_queries(
        model_dir, {"type": "sphere"}, [0.3, 4.0, 0.2], [0, 0, 1], [-2.0, 3.0, 1.5], sphere_geometry
    )
    # the sphere's footprint grows towards the silhouette
    assert np.corrcoef(rows[:, C.SIGMA], 1 / np.sqrt(1 - rows[:, C.WO_X] ** 2 - rows[:, C.WO_Y] ** 2))[0, 1] > 0.5


CUBE_VIEWS = [([0, 0, 4], [0, 1, 0]), ([0, 0, -4], [0, 1, 0]), ([4, 0, 0], [0, 1, 0]),
              ([-4, 0, 0], [0, 1, 0]), ([0, 4, 0], [0, 0, 1]), ([0, -4, 0], [0, 0, 1])]


@pytest.mark.parametrize(("camera", "up"), CUBE_VIEWS, ids=["+z", "-z", "+x", "-x", "+y", "-y"])
def test_cube_face(model_dir, camera, up):
    camera = np.asarray(camera, dtype=np.float64)
    light = 0.8 * camera + 1.5 * _unit(np.cross(camera, up)) + 0.7 * np.asarray(up)
    check_first_hit_queries(model_dir, {"type": "cube"}, camera.tolist(), up, light.tolist(), None)
