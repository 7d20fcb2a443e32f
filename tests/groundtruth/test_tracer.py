"""Known-answer tests of the MBTF path tracer: Lambertian a/pi, glossy plane vs Mitsuba's own BSDF,
a tall wall's shadow and its Gaussian average, agreement with Mitsuba's stock path tracer."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core.contract import random_queries
from neumip.groundtruth.description import MaterialDescription, find_description, resolve
from neumip.groundtruth.tracer import QueryTracer, TracerConfig

from .conftest import diffuse, height_description, wall_height


def tile_queries(n: int, seed: int, max_theta_deg: float = 80.0) -> np.ndarray:
    """(n, 7) random queries over all positions, footprints and directions up to `max_theta_deg`."""
    return random_queries(n, seed, max_zenith_deg=max_theta_deg)


# --- flat Lambertian plane: a / pi for every query -------------------------------------------------


def test_flat_lambertian_library_material_answers_albedo_over_pi():
    tracer = QueryTracer(resolve(find_description("flat")))
    rgb = tracer.estimate(tile_queries(4000, 0), spp=4, seed=1)
    np.testing.assert_allclose(rgb, 0.5 / math.pi, rtol=2e-4)


def test_flat_lambertian_heightfield_mesh_answers_albedo_over_pi(tmp_path):
    """The same through a tiled heightfield mesh (constant height), with large sigma and u far from the tile."""
    desc = height_description(tmp_path, np.zeros((16, 16)), bsdf=diffuse(0.8), height_scale=0.1)
    rgb = QueryTracer(resolve(desc)).estimate(tile_queries(4000, 1, 84.0), spp=4, seed=2)
    np.testing.assert_allclose(rgb, 0.8 / math.pi, rtol=2e-4)


def test_lambertian_needs_unit_irradiance_on_the_plane():
    """Guard against the perpendicular-irradiance convention: the answer does not fall with cos(theta_i)."""
    tracer = QueryTracer(resolve(find_description("flat")))
    s = math.sin(math.radians(75))
    q = C.pack_queries([0.3], [0.6], [0.0], np.array([[s, 0.0]]), np.array([[0.0, 0.0]]))
    assert tracer.estimate(q, 1, 0)[0, 0] == pytest.approx(0.5 / math.pi, rel=1e-4)


# --- flat glossy plane: Mitsuba's own eval / cos(theta_i) ------------------------------------------

GLOSSY = {"type": "roughconductor", "material": "Au", "distribution": "ggx", "alpha_u": 0.08, "alpha_v": 0.35}
"""Anisotropic on purpose: the answer depends on the local frame's x axis following +u."""


def mitsuba_brdf(mi, bsdf_dict: dict, queries: np.ndarray) -> np.ndarray:
    """(N, 3) BSDF eval / cos(theta_i) of a standalone Mitsuba BSDF in the frame n = +z, s = +x."""
    bsdf = mi.load_dict(bsdf_dict)
    wi = np.stack([queries[:, C.WI_X], queries[:, C.WI_Y], C.direction_z(queries[:, C.WI_X], queries[:, C.WI_Y])])
    wo = np.stack([queries[:, C.WO_X], queries[:, C.WO_Y], C.direction_z(queries[:, C.WO_X], queries[:, C.WO_Y])])
    si = mi.SurfaceInteraction3f()
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.wi = mi.Vector3f(wo)  # Mitsuba's si.wi points to the viewer: the BTF's wo
    value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wi))
    return np.stack([value.x.numpy(), value.y.numpy(), value.z.numpy()], axis=1) / wi[2][:, None]


def test_glossy_plane_matches_mitsubas_bsdf(mi):
    desc = MaterialDescription.from_dict({"name": "glossy", "resolution": 1, "bsdf": GLOSSY})
    queries = tile_queries(3000, 3, 70.0)
    rgb = QueryTracer(resolve(desc)).estimate(queries, spp=2, seed=4)
    expected = mitsuba_brdf(mi, GLOSSY, queries)
    assert expected.max() > 10 * np.median(expected)  # a real specular lobe is in the sample
    np.testing.assert_allclose(rgb, expected, rtol=1e-3, atol=1e-5)
    # and the test can fail: the frame rotated by 90 degrees (x along +v) gives other answers
    rotated = queries.copy()
    rotated[:, [C.WI_X, C.WI_Y, C.WO_X, C.WO_Y]] = queries[:, [C.WI_Y, C.WI_X, C.WO_Y, C.WO_X]]
    assert np.abs(mitsuba_brdf(mi, GLOSSY, rotated) - expected).max() > 0.1 * expected.max()


# --- a tall wall: shadow, light from the front, Gaussian average -----------------------------------

RES, LO, HI, WALL = 64, 28, 36, 0.25
"""Wall over u in [28/64, 36/64), 0.25 tile tall; floor albedo 0.8."""
ALBEDO = 0.8
THETA = math.radians(60)  # shadow length 0.25 tan 60 = 0.43 tile


@pytest.fixture(scope="module")
def wall_tracer(tmp_path_factory):
    folder = tmp_path_factory.mktemp("wall")
    desc = height_description(
        folder, wall_height(RES, LO, HI), bsdf=diffuse(ALBEDO), height_scale=WALL, normals="flat"
    )
    return QueryTracer(resolve(desc))


def wall_queries(u: np.ndarray, sigma: float, light_x: float) -> np.ndarray:
    """Queries looking straight down at (u, 0.5), light from +x (light_x > 0) or -x at 60 degrees."""
    n = len(u)
    wi = np.tile([light_x * math.sin(THETA), 0.0], (n, 1))
    return C.pack_queries(u, np.full(n, 0.5), np.full(n, sigma), wi, np.zeros((n, 2)))


def test_wall_casts_a_shadow_behind_it(wall_tracer):
    u = np.array([0.2, 0.3, 0.4])  # left of the wall, within its shadow for light from +x
    lit_value = ALBEDO / math.pi
    behind = wall_tracer.estimate(wall_queries(u, 0.0, +1.0), spp=64, seed=1)
    front = wall_tracer.estimate(wall_queries(u, 0.0, -1.0), spp=64, seed=1)
    assert (behind.max(axis=1) < 0.15 * lit_value).all()  # only light bounced off other walls
    assert (front.min(axis=1) > 0.95 * lit_value).all()  # direct light (+ a little from the wall)
    far = wall_tracer.estimate(wall_queries(np.array([0.8]), 0.0, +1.0), spp=64, seed=1)
    assert far[0, 0] > 0.95 * lit_value  # right of the wall the light from +x is unobstructed


def test_wide_sigma_is_the_gaussian_average_of_the_btf(wall_tracer):
    sigma = 0.08
    # the BTF profile across the wall (invariant along v), finely sampled
    xs = (np.arange(256) + 0.5) / 256
    profile = wall_tracer.estimate(wall_queries(xs, 0.0, +1.0), spp=32, seed=2)[:, 0]
    centres = np.array([0.15, 0.45, 0.65])
    d = xs[None, :] - centres[:, None]
    d -= np.round(d)  # periodic distance
    weights = np.exp(-0.5 * (d / sigma) ** 2)
    expected = (weights * profile).sum(axis=1) / weights.sum(axis=1)
    samples = wall_tracer.samples(wall_queries(centres, sigma, +1.0), spp=4096, seed=3)[:, :, 0]
    measured = samples.mean(axis=1)
    stderr = samples.std(axis=1) / math.sqrt(samples.shape[1])
    assert (np.abs(measured - expected) < 4 * stderr + 0.004).all(), (measured, expected, stderr)
    # a wide footprint mixes the shadow with the lit floor: strictly between the two
    assert profile.min() < measured.min() and measured.max() < profile.max()


# --- tracer properties -----------------------------------------------------------------------------


def small_yarn():
    desc = find_description("yarn")
    desc.resolution = 32
    return resolve(desc)


@pytest.fixture(scope="module")
def yarn_tracer():
    return QueryTracer(small_yarn(), TracerConfig(lanes=5000))


def test_same_seed_same_answers_independent_of_pass_size(yarn_tracer):
    queries = tile_queries(3000, 5)
    a = yarn_tracer.estimate(queries, spp=4, seed=9)  # 1250 queries per pass
    wide = QueryTracer(small_yarn(), TracerConfig(lanes=1 << 20))  # one pass
    np.testing.assert_array_equal(a, wide.estimate(queries, spp=4, seed=9))
    assert np.abs(a - yarn_tracer.estimate(queries, spp=4, seed=10)).max() > 1e-3


def test_non_flat_answers_are_finite_and_non_negative(yarn_tracer):
    rgb = yarn_tracer.estimate(tile_queries(2000, 6, 89.0), spp=2, seed=0)
    assert np.isfinite(rgb).all() and rgb.min() >= 0 and rgb.mean() > 0.01


def test_bad_queries_are_rejected(yarn_tracer):
    with pytest.raises(C.QueryError):
        yarn_tracer.estimate(np.zeros((3, 6), np.float32), spp=1, seed=0)
    with pytest.raises(ValueError, match="spp"):
        yarn_tracer.estimate(tile_queries(2, 0), spp=0, seed=0)


def test_huge_sigma_is_the_tile_average_and_negative_sigma_the_btf(wall_tracer):
    xs = (np.arange(256) + 0.5) / 256
    tile_mean = wall_tracer.estimate(wall_queries(xs, 0.0, +1.0), spp=32, seed=4)[:, 0].mean()
    samples = wall_tracer.samples(wall_queries(np.array([0.3, 12345.6]), 1e6, +1.0), spp=4096, seed=5)[:, :, 0]
    stderr = samples.std(axis=1) / math.sqrt(samples.shape[1])
    assert (np.abs(samples.mean(axis=1) - tile_mean) < 4 * stderr + 0.002).all()
    at = np.array([0.3, 0.7])
    np.testing.assert_array_equal(
        wall_tracer.estimate(wall_queries(at, -1.0, 1.0), 8, 6), wall_tracer.estimate(wall_queries(at, 0.0, 1.0), 8, 6)
    )
