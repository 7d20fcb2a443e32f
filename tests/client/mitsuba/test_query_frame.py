"""`query_frame` on hand-made interactions: x along +u, y on the +v side, also where dp_du and
dp_dv are not orthogonal, where y = n x dp_du points to -v, and where dp_du vanishes."""

from __future__ import annotations

import numpy as np

from neumip.client.mitsuba.bsdf import dr, mi
from neumip.client.mitsuba.shading import query_frame, to_query


def interaction(dp_du, dp_dv, n=(0.0, 0.0, 1.0)) -> mi.SurfaceInteraction3f:
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.dp_du, si.dp_dv = mi.Vector3f(*map(float, dp_du)), mi.Vector3f(*map(float, dp_dv))
    si.n = mi.Normal3f(*map(float, n))
    si.sh_frame = mi.Frame3f(si.n)  # an arbitrary tangent frame, as Mitsuba's may be
    return si


def axes(frame: mi.Frame3f) -> np.ndarray:
    return np.array([[c[0] for c in (axis.x, axis.y, axis.z)] for axis in (frame.s, frame.t, frame.n)])


def test_orthogonal_uv_gives_the_uv_axes():
    for dp_dv in ((0.0, 3.0, 0.0), (0.0, -3.0, 0.0)):  # right- and left-handed parametrizations
        frame = axes(query_frame(interaction((2.0, 0.0, 0.0), dp_dv)))
        np.testing.assert_allclose(frame, [[1, 0, 0], [0, np.sign(dp_dv[1]), 0], [0, 0, 1]], atol=1e-6)


def test_skewed_uv_keeps_x_on_u_and_y_on_the_plus_v_side():
    dp_du, dp_dv = np.array([1.0, 0.0, 0.3]), np.array([-0.8, -0.5, 0.0])  # skewed, not in the plane
    s, t, n = axes(query_frame(interaction(dp_du, dp_dv)))
    np.testing.assert_allclose(s, [1, 0, 0], atol=1e-6)  # dp_du projected onto the tangent plane
    np.testing.assert_allclose(n, [0, 0, 1], atol=1e-6)
    assert abs(np.dot(s, t)) < 1e-6 and np.dot(t, dp_dv) > 0


def test_vanishing_dp_du_falls_back_to_the_shading_frame():
    si = interaction((0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    s, t, _ = axes(query_frame(si))
    np.testing.assert_allclose(s, [si.sh_frame.s.x[0], si.sh_frame.s.y[0], si.sh_frame.s.z[0]], atol=1e-6)
    assert t[1] > 0


def test_to_query_keeps_the_cosine_and_maps_through_world():
    si = interaction((0.0, 2.0, 0.0), (-1.0, 0.0, 0.0))  # x = +y world, y = -x world
    w_world = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
    w_local = si.sh_frame.to_local(mi.Vector3f(*map(float, w_world)))
    q = to_query(si, query_frame(si), w_local)
    np.testing.assert_allclose([q.x[0], q.y[0], q.z[0]], [w_world[1], -w_world[0], w_world[2]], atol=1e-6)
