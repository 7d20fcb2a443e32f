"""Heightfield meshes: the tiled query scene and the displaced reference surface; the tracer agrees
with Mitsuba's stock path tracer rendering that surface."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.groundtruth import mesh
from neumip.groundtruth.description import find_description, resolve
from neumip.groundtruth.tracer import QueryTracer, TracerConfig

from .conftest import diffuse, height_description

RES = 16


def egg_crate(resolution: int) -> np.ndarray:
    """(R, R) periodic bumps, in [0, 1]."""
    c = (np.arange(resolution) + 0.5) / resolution
    return 0.5 + 0.25 * (np.cos(2 * np.pi * c)[None, :] + np.cos(4 * np.pi * c)[:, None])


@pytest.fixture(scope="module")
def geo(tmp_path_factory):
    folder = tmp_path_factory.mktemp("egg")
    return resolve(height_description(folder, egg_crate(RES), bsdf=diffuse(0.9), height_scale=0.4, normals="flat"))


def test_grid_passes_through_the_height_samples(geo):
    coords = mesh.tiled_coords(RES, 0.3)
    arrays = mesh.grid_arrays(geo, coords, coords)
    z = arrays["positions"][:, 2].reshape(len(coords), len(coords))
    inside = np.flatnonzero((coords > 0) & (coords < 1))
    np.testing.assert_allclose(z[np.ix_(inside, inside)], geo.height, atol=1e-7)
    assert coords[0] <= -0.3 and coords[-1] >= 1.3  # the margin is covered
    assert arrays["faces"].shape[0] == 2 * (len(coords) - 1) ** 2
    np.testing.assert_array_equal(arrays["texcoords"], arrays["positions"][:, :2])


def test_smooth_normals_follow_the_slope(tmp_path):
    ramp = np.sin(2 * np.pi * (np.arange(32) + 0.5) / 32)[None, :].repeat(32, 0)
    g = resolve(height_description(tmp_path, ramp, height_scale=0.1))
    xs = np.array([0.0, 0.25, 0.5])
    arrays = mesh.grid_arrays(g, xs, xs)
    n = arrays["normals"].reshape(3, 3, 3)
    np.testing.assert_allclose(np.linalg.norm(n, axis=2), 1, atol=1e-6)
    # dh/du = 0.1 * 2 pi cos(2 pi u): the normal leans against the slope along x only
    slope = 0.1 * 2 * np.pi * np.cos(2 * np.pi * xs)
    np.testing.assert_allclose(-n[1, :, 0] / n[1, :, 2], slope, rtol=0.02, atol=1e-3)
    np.testing.assert_allclose(n[:, :, 1], 0, atol=1e-7)


def test_margin_grows_with_depth_and_is_capped():
    cfg = mesh.TilingConfig(max_zenith_deg=80, max_margin=2)
    assert mesh.margin_tiles(0.1, 64, cfg) == pytest.approx(0.1 * math.tan(math.radians(80)))
    assert mesh.margin_tiles(5.0, 64, cfg) == 2
    assert mesh.margin_tiles(0.0, 64, cfg) == 1 / 64


def test_reference_surface_is_the_displaced_rectangle(mi, geo):
    tiles = 3
    to_world = mi.ScalarTransform4f().translate([0, 0, 2]).scale([4, 4, 4])
    surface = mesh.reference_surface(mi, geo, tiles, to_world)
    box = surface.bbox()
    np.testing.assert_allclose([box.min.x, box.min.y, box.max.x, box.max.y], [-4, -4, 4, 4], atol=1e-5)
    assert box.max.z == pytest.approx(2, abs=1e-5)  # the rectangle is the top of the microgeometry
    assert box.min.z == pytest.approx(2 - 4 * (2 / tiles) * geo.depth, rel=1e-3)
    uv = np.array(surface.vertex_texcoords_buffer()).reshape(-1, 2)
    assert uv.min() == 0 and uv.max() == pytest.approx(tiles)


def stock_render_mean(mi, geo, wi: np.ndarray, max_depth: int, spp: int) -> float:
    """Mean radiance of Mitsuba's `path` integrator looking straight down at the central 3 x 3 tiles
    of a 9 x 9-tile reference surface, lit by a `directional` emitter with unit irradiance on the plane."""
    tiles = 9
    to_world = mi.ScalarTransform4f().translate([tiles / 2, tiles / 2, 0]).scale([tiles / 2, tiles / 2, tiles / 2])
    camera = mi.ScalarTransform4f().look_at(origin=[4.5, 4.5, 1], target=[4.5, 4.5, 0], up=[0, 1, 0])
    wi3 = np.array([wi[0], wi[1], math.sqrt(1 - wi[0] ** 2 - wi[1] ** 2)])
    scene = mi.load_dict({
        "type": "scene",
        "surface": mesh.reference_surface(mi, geo, tiles, to_world),
        "light": {"type": "directional", "direction": (-wi3).tolist(), "irradiance": 1 / wi3[2]},
        "integrator": {"type": "path", "max_depth": max_depth + 1, "rr_depth": 100},
        "sensor": {
            "type": "orthographic",
            "to_world": camera @ mi.ScalarTransform4f().scale([1.5, 1.5, 1]),
            "film": {"type": "hdrfilm", "width": 48, "height": 48, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp},
        },
    })
    return float(np.mean(np.array(mi.render(scene, seed=1))[:, :, :3]))


def test_tracer_agrees_with_mitsubas_path_tracer(mi, geo):
    """Multiple bounces on a deep, bright heightfield: the tile average of BTF(u, wi, wo = +z)
    equals the stock integrator's mean radiance over whole tiles."""
    wi = np.array([math.sin(math.radians(50)) * 0.8, math.sin(math.radians(50)) * 0.6])
    n = 20_000
    rng = np.random.default_rng(0)
    queries = C.pack_queries(rng.random(n), rng.random(n), np.zeros(n), np.tile(wi, (n, 1)), np.zeros((n, 2)))
    depth = 4
    samples = QueryTracer(geo, TracerConfig(max_depth=depth)).samples(queries, spp=8, seed=0)
    ours = samples.mean()
    theirs = stock_render_mean(mi, geo, wi, depth, spp=128)
    direct = QueryTracer(geo, TracerConfig(max_depth=1)).estimate(queries, spp=1, seed=0).mean()
    assert ours > 1.1 * direct  # interreflection matters here, so the comparison tests it
    assert ours == pytest.approx(theirs, rel=0.02)


def stock_path_samples(mi, geo, u: np.ndarray, v: np.ndarray, wi: np.ndarray, wo: np.ndarray, max_depth: int,
                       spp: int) -> np.ndarray:
    """(N, spp) red-channel samples of Mitsuba's `path` integrator for rays along -wo through
    (u, v) on the reference plane of the central tile of a 9 x 9-tile reference surface."""
    tiles = 9
    to_world = mi.ScalarTransform4f().translate([tiles / 2, tiles / 2, 0]).scale([tiles / 2, tiles / 2, tiles / 2])
    wi3 = [float(wi[0]), float(wi[1]), math.sqrt(1 - wi @ wi)]
    scene = mi.load_dict({
        "type": "scene",
        "surface": mesh.reference_surface(mi, geo, tiles, to_world),
        "light": {"type": "directional", "direction": [-x for x in wi3], "irradiance": 1 / wi3[2]},
    })
    integrator = mi.load_dict({"type": "path", "max_depth": max_depth + 1, "rr_depth": 100})
    down = mi.Vector3f(-float(wo[0]), -float(wo[1]), -math.sqrt(1 - wo @ wo))
    aim = mi.Point3f(mi.Float(np.repeat(4 + u, spp)), mi.Float(np.repeat(4 + v, spp)), 0.0)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, len(u) * spp)
    value, _, _ = integrator.sample(scene, sampler, mi.RayDifferential3f(mi.Ray3f(aim - down, down)))
    return np.array(value.x.numpy()).reshape(len(u), spp)


@pytest.fixture(scope="module")
def yarn():
    desc = find_description("yarn")
    desc.resolution = 64
    return resolve(desc)


@pytest.mark.parametrize("material", ["geo", "yarn"])
def test_each_query_agrees_with_mitsubas_path_tracer_at_oblique_angles(mi, material, request):
    """Per query, oblique light and view: parallax, the reference plane at the top of the
    microgeometry, the wi/wo conventions and (yarn) the textured principled BSDF with smooth
    normals all match a stock path tracer on real geometry."""
    geo = request.getfixturevalue(material)
    n, spp, depth = 48, 1024, 4
    rng = np.random.default_rng(1)
    u, v = rng.random(n), rng.random(n)
    wi, wo = np.array([0.3, -0.5]), np.array([-0.6, 0.2])
    stock = stock_path_samples(mi, geo, u, v, wi, wo, depth, spp)
    tracer = QueryTracer(geo, TracerConfig(max_depth=depth))

    def z_scores(du: float) -> np.ndarray:
        q = C.pack_queries(u + du, v, np.zeros(n), np.tile(wi, (n, 1)), np.tile(wo, (n, 1)))
        ours = tracer.samples(q, spp, seed=1)[:, :, 0]
        stderr = np.sqrt((stock.var(axis=1) + ours.var(axis=1)) / spp)
        return (ours.mean(axis=1) - stock.mean(axis=1)) / np.maximum(stderr, 1e-6)

    z = z_scores(0.0)
    assert np.abs(z).max() < 4.5 and abs(z.mean()) < 0.6, z
    assert np.abs(z_scores(2 / geo.height.shape[0])).max() > 6  # the test sees a 2-texel parallax error


def oblique_render(mi, geo, shapes: dict, seed: int) -> np.ndarray:
    """A 32 x 24 oblique view (60 degrees) of a 4 x 4-tile surface, side light, 16 spp, stock `path`."""
    camera = mi.ScalarTransform4f().look_at(origin=[2, -1.2, 3.0], target=[2, 2, 0], up=[0, 0, 1])
    scene = mi.load_dict({
        "type": "scene", **shapes,
        "light": {"type": "directional", "direction": [-0.6, 0.2, -0.77], "irradiance": 1.5},
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 40, "to_world": camera,
                   "film": {"type": "hdrfilm", "width": 32, "height": 24},
                   "sampler": {"type": "independent", "sample_count": 16}},
    })
    return np.array(mi.render(scene, seed=seed))[:, :, :3]


def test_instanced_reference_equals_the_single_mesh(mi, geo):
    """Instances of a 2 x 2-tile block (shapegroup + instance by id) render the same image as one
    mesh of the 4 x 4 tiles: the difference at the same seed is far below the seed-to-seed noise."""
    tiles = 4
    to_world = mi.ScalarTransform4f().translate([2, 2, 0]).scale([2, 2, 2])  # the rectangle [-1, 1]^2 -> [0, 4]^2
    single = {"surface": mesh.reference_surface(mi, geo, tiles, to_world)}
    origins = mesh.block_origins(np.zeros(2), np.full(2, tiles), 2)
    assert len(origins) == 4
    instanced = mesh.reference_instances(mi, geo, origins, 2)
    a, b = oblique_render(mi, geo, single, 0), oblique_render(mi, geo, instanced, 0)
    noise = np.mean((a - oblique_render(mi, geo, single, 1)) ** 2)
    assert a.mean() > 0.05  # the view sees the lit surface
    assert np.mean((a - b) ** 2) < 0.01 * noise
    assert b.mean() == pytest.approx(a.mean(), rel=1e-3)
