"""Query geometry: first-hit sigma is one sample's share of the pixel footprint (the std of the film's
reconstruction filter times `sample_footprint(spp)` of the whole render) times uv_scale, and query directions follow the contract (wo towards the viewer,
x along +u and y along +v on rectangles, spheres and every cube face)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neumip.client.mitsuba.bsdf import mi
from neumip.core.contract import sample_footprint
from neumip.client.mitsuba.integrator import filter_std_px
from neumip.client.mitsuba.render import RenderConfig, render_scene

from .recording import Recording
from .scenes import DISTANCE, FOV, WIDTH, facing_plane

FILTER_STD = {"gaussian": 0.5, "box": 1 / math.sqrt(12), "tent": 1 / math.sqrt(6)}
"""Std (pixels) of Mitsuba's reconstruction filters at their default radii."""


@pytest.mark.parametrize("rfilter", sorted(FILTER_STD))
def test_filter_std(rfilter):
    assert filter_std_px(mi.load_dict({"type": rfilter})) == pytest.approx(FILTER_STD[rfilter])


def test_sample_footprint_follows_pbrt():
    assert sample_footprint(1) == 1.0
    assert sample_footprint(4) == 0.5
    assert sample_footprint(64) == sample_footprint(1024) == 1 / 8


@pytest.mark.parametrize(
    ("spp", "max_lanes", "uv_scale", "rfilter", "share"),
    [(1, 2**21, 1.0, "gaussian", 1.0), (16, 2**21, 1.0, "gaussian", 0.25), (16, 2**21, 4.0, "gaussian", 0.25),
     (4, 2**21, 1.0, "box", 0.5), (16, 4 * WIDTH**2, 1.0, "gaussian", 0.25)],  # the last in 4 passes of 4 spp
)
def test_first_hit_sigma_is_a_sample_share_of_the_pixel_footprint(model_dir, spp, max_lanes, uv_scale, rfilter, share):
    evaluator = Recording(model_dir)
    result = render_scene(mi.load_dict(facing_plane(uv_scale, rfilter)), evaluator,
                          RenderConfig(spp=spp, max_lanes=max_lanes))
    assert result.passes == spp * WIDTH**2 // max_lanes or max_lanes > spp * WIDTH**2
    first = evaluator.calls[0]  # bounce 0: all camera hits, light and sampled queries
    pixel_world = 2 * DISTANCE * math.tan(math.radians(FOV / 2)) / WIDTH
    # sigma is the std of the pixel's reconstruction filter, in tiles (the rectangle spans 2 world
    # units per uv unit): 0.5 px for the default gaussian filter; each of n samples reads 1/sqrt(n) of it
    expected = uv_scale * FILTER_STD[rfilter] * pixel_world / 2 * share
    np.testing.assert_allclose(np.median(first[:, 2]), expected, rtol=0.02)
    assert first[:, 2].std() < 0.05 * expected  # a fronto-parallel plane: the same everywhere
    # the view covers the middle 80 % of the rectangle (2 * 3 * tan 15 deg = 1.6 of 2 units), in tiles
    visible = DISTANCE * math.tan(math.radians(FOV / 2)) / 2  # half-width in uv: 0.40
    for col in (0, 1):
        np.testing.assert_allclose(first[:, col].min(), uv_scale * (0.5 - visible), atol=0.02 * uv_scale)
        np.testing.assert_allclose(first[:, col].max(), uv_scale * (0.5 + visible), atol=0.02 * uv_scale)
    # wo (towards the viewer) stays within the camera's half-angle of the normal
    half_angle = math.sin(math.radians(FOV / 2) * math.sqrt(2))
    assert np.all(np.hypot(first[:, 5], first[:, 6]) <= half_angle + 1e-3)
    # ... and points back at the camera: right of centre (u > 0.5, local x = +u) it leans to -x
    assert np.corrcoef(first[:, 0], first[:, 5])[0, 1] < -0.95
    assert np.corrcoef(first[:, 1], first[:, 6])[0, 1] < -0.95


def side_view(shape: dict, camera, up) -> dict:
    """``shape`` (neural) seen from ``camera`` towards the origin; every visible point faces it."""
    return {
        "type": "scene",
        "integrator": {"type": "neumip_path", "max_depth": 2},
        "sensor": {
            "type": "perspective", "fov": FOV,
            "to_world": mi.ScalarTransform4f().look_at(origin=camera, target=[0, 0, 0], up=up),
            "film": {"type": "hdrfilm", "width": WIDTH, "height": WIDTH},
        },
        "sky": {"type": "constant"},
        "shape": {**shape, "bsdf": {"type": "neumip", "material": "lambert"}},
    }


VIEWS = {
    "rectangle": ({"type": "rectangle"}, [0, 0, 4], [0, 1, 0]),
    "sphere": ({"type": "sphere"}, [0, 4, 0], [0, 0, 1]),  # the equator round phi = 90 deg: no u seam
    **{f"cube{name}": ({"type": "cube"}, camera, up) for name, camera, up in [
        ("+z", [0, 0, 5], [0, 1, 0]), ("-z", [0, 0, -5], [0, 1, 0]), ("+x", [5, 0, 0], [0, 1, 0]),
        ("-x", [-5, 0, 0], [0, 1, 0]), ("+y", [0, 5, 0], [0, 0, 1]), ("-y", [0, -5, 0], [0, 0, 1])]},
}


@pytest.mark.parametrize("view", sorted(VIEWS))
def test_local_frame_follows_uv(model_dir, view):
    """wo points back at the camera: where u (v) is larger than at the image centre, wo leans to -x
    (-y). Mitsuba's own shading frame has y = n x dp_du, which is -v on spheres and cube faces."""
    evaluator = Recording(model_dir)
    render_scene(mi.load_dict(side_view(*VIEWS[view])), evaluator, RenderConfig(spp=1))
    first = evaluator.calls[0]
    assert np.corrcoef(first[:, 0], first[:, 5])[0, 1] < -0.9
    assert np.corrcoef(first[:, 1], first[:, 6])[0, 1] < -0.9


def test_secondary_hits_read_coarser_footprints(model_dir):
    """After a bounce the ray-cone estimate grows: a facing wall (same tiles per world unit) reads
    much larger sigmas than the camera hits."""
    scene = facing_plane(1.0)
    scene["integrator"]["max_depth"] = 4
    scene["back"] = {
        "type": "rectangle", "bsdf": {"type": "neumip", "material": "lambert", "uv_scale": 10.0},
        "to_world": mi.ScalarTransform4f().translate([0, 0, 2 * DISTANCE]).rotate([1, 0, 0], 180).scale(10),
    }
    evaluator = Recording(model_dir)
    render_scene(mi.load_dict(scene), evaluator, RenderConfig(spp=4))
    assert len(evaluator.calls) >= 3  # the first hits (at most two calls: groups, single queries), then more
    assert np.median(evaluator.calls[-1][:, 2]) > 10 * np.median(evaluator.calls[0][:, 2])
