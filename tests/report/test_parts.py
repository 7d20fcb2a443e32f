"""Pieces of the report: the views' footprint, the mip levels, the cache, the analysis, the sweeps."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from neumip.engines.local import LocalMaterials
from neumip.report import analysis, methods, stability, views
from neumip.report.cache import RenderCache

MODELS = Path(__file__).resolve().parents[2] / "models"


@pytest.mark.parametrize("level", [0, 2, 4, 6])
def test_view_footprint_at_the_image_centre(level):
    """The integrator's sigma (filter std x the larger uv step of a pixel) at the centre pixel equals
    2^level finest texels, measured with Mitsuba's own ray differentials on the neural plane."""
    from neumip.client.mitsuba.render import mi  # registers the plugins

    film = views.Film(64, 48)
    spec = methods.SceneSpec(views.View("v", 55.0, level), film, 64)
    scene = mi.load_dict(methods.neural_scene(mi, spec, "flat"))
    sensor = scene.sensors()[0]
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(0.5, 0.5), mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(mi.RayDifferential3f(ray))
    si.compute_uv_partials(ray)
    uv_scale = 2.0 * spec.half_size(2.0)
    step = max(np.linalg.norm(np.array(si.duv_dx)), np.linalg.norm(np.array(si.duv_dy))) * uv_scale
    sigma_texels = views.FILTER_STD_PX * step * 64
    assert sigma_texels == pytest.approx(2.0**level, rel=0.02)


def test_light_samples_choose_a_light_by_the_irradiance_it_gives_the_plane():
    """Mitsuba's own emitter choice in a report scene: the sun (unit irradiance on the plane) is picked
    1 / (1 + pi ENV_RADIANCE) of the time, not half of it; its sample is weighted by the inverse."""
    from neumip.client.mitsuba.render import mi  # registers the plugins

    spec = methods.SceneSpec(views.View("v", 55.0, 0, light_zenith=60.0), views.Film(16, 12), 64)
    scene = mi.load_dict(methods.neural_scene(mi, spec, "flat"))
    sun_share = 1.0 / (1.0 + math.pi * views.ENV_RADIANCE)
    suns = [i for i, e in enumerate(scene.emitters()) if not e.is_environment()]
    for sample, want in ((0.5 * sun_share, sun_share), (0.5 * (1 + sun_share), 1 - sun_share)):
        index, weight, _ = scene.sample_emitter(mi.Float(sample))
        assert (index.numpy()[0] in suns) == (want == sun_share)
        assert weight.numpy()[0] == pytest.approx(1.0 / want, rel=1e-5)


def test_visible_corners_and_block_cover():
    view, film = views.DISTANCE_VIEWS[1], views.Film(64, 48)
    d = views.camera_distance(view, film, 64)
    corners = views.visible_corners(view, film, d)
    assert corners[:, 1].max() > abs(corners[:, 1].min())  # the far side is farther (perspective)
    pts = np.array([[0.0, 0.0], [1e3, 0.0]])
    assert views.distance_to_polygon(pts, corners)[0] == 0
    assert views.distance_to_polygon(pts, corners)[1] > 900
    with pytest.raises(ValueError, match="horizon"):
        views.visible_corners(views.View("sky", 89.0, 0, fov=10), film, 1.0)


def test_mip_maps_average_and_flatten():
    a = np.random.default_rng(0).uniform(size=(16, 16, 3))
    down = methods.box_down(a, 2)
    assert down.shape == (4, 4, 3)
    np.testing.assert_allclose(down.mean(axis=(0, 1)), a.mean(axis=(0, 1)))
    assert methods.box_down(a, 5).shape == (1, 1, 3)
    x = (np.arange(32) + 0.5) / 32
    height = 0.05 * np.sin(2 * np.pi * 4 * x)[None, :].repeat(32, 0)  # 4 grooves per tile
    flat = methods.tangent_normals(np.zeros((8, 8)))
    np.testing.assert_allclose(flat[..., 2], 1.0)
    fine = methods.tangent_normals(height)[..., 2].mean()
    coarse = methods.tangent_normals(methods.box_down(height, 3))[..., 2].mean()
    assert fine < 0.9 and coarse > 0.99  # averaged slopes: the grooves flatten


def test_mip_level_follows_the_pixel_step():
    film = views.Film(64, 48)
    for level, expected in ((0, 3), (2, 5), (4, 7), (6, 8)):  # 256^2 maps, pixel step 2 sigma
        spec = methods.SceneSpec(views.View("v", 55.0, level), film, 64)
        assert methods.mip_level_for(spec, 256) == expected


def test_cache_is_atomic_and_survives_a_corrupt_file(tmp_path):
    cache = RenderCache(tmp_path)
    params = {"a": 1, "b": [1, 2]}
    assert cache.get(params) is None
    img = np.random.default_rng(0).random((4, 5, 3)).astype(np.float32)
    cache.put(params, img, 1.5)
    got = cache.get(params)
    np.testing.assert_array_equal(got.image, img)
    assert got.seconds == 1.5 and not list(tmp_path.glob(".*partial*"))
    cache.path(params).write_bytes(cache.path(params).read_bytes()[:50])  # a half-written file
    assert cache.get(params) is None


def test_time_to_reach_interpolates_log_log():
    ladder = {1: {"mse": 1e-2, "seconds": 1.0}, 4: {"mse": 2.5e-3, "seconds": 4.0}, 16: {"mse": 6.25e-4, "seconds": 16.0}}
    assert analysis.time_to_reach(ladder, 5e-3) == pytest.approx(2.0)
    assert analysis.time_to_reach(ladder, 1e-4) is None
    assert analysis.time_to_reach(ladder, 1.0) == 1.0
    rows = [{"texels": t, "N": {"mse": n}, "C": {"mse": c}} for t, n, c in ((1, 3, 2), (4, 2, 2.5), (16, 1, 2))]
    assert analysis.winning_footprint(rows, "C") == 4


def test_a_rung_s_time_is_its_fastest_round_so_one_slow_render_moves_no_fit():
    """A shared machine only adds time: one render slowed 5x in one timed round leaves the rung's seconds, and the
    fit of seconds on spp, where the other rounds put them."""
    from neumip.report import pipeline
    from neumip.report.config import ReportConfig

    cfg = ReportConfig()
    # each round a little slower than the one before; round 1 (the first timed) the fastest
    clean = {(m, spp, r): (0.02 + 0.01 * spp + 0.001 * r, 1.0) for m in "R" for spp in cfg.ladder
             for r in range(cfg.rounds + 1)}
    slowed = dict(clean)
    slowed[("R", 4, 1)] = (5 * clean[("R", 4, 1)][0], 3.0)  # the fastest round of one rung, slowed 5x

    def fit(timings):
        entries = {spp: {"mse": 1.0} for spp in cfg.ladder}
        return pipeline._ladder(entries, "R", None, 1.0, {}, timings, cfg), entries

    (want, clean_entries), (got, entries) = fit(clean), fit(slowed)
    assert cfg.rounds >= 2
    assert [clean_entries[s]["seconds"] for s in cfg.ladder] == [clean[("R", s, 1)][0] for s in cfg.ladder]
    assert want["seconds_per_spp"] == pytest.approx(0.01) and want["fixed_seconds"] == pytest.approx(0.021)
    assert entries[4]["seconds"] == clean[("R", 4, 2)][0]  # the next fastest round
    assert got["seconds_per_spp"] == pytest.approx(0.01, abs=1e-4) and got["fixed_seconds"] == pytest.approx(0.021, abs=1e-3)


def test_close_up_checks_read_the_offset_gain_and_the_highlights():
    def entry(mse, mean=1.0, p99=1.0):
        return {64: {"mse": mse, "mean_ratio": mean, "p99_ratio": p99}}

    material = {
        "level0_side": {"methods": {"N": entry(1.0), "N0": entry(2.5)}},
        "level2_side": {"methods": {"N": entry(2.0), "N0": entry(1.0)}},
        "grazing75": {"methods": {"N": entry(1.0)}},  # no N0: no gain
        "low_light": {"methods": {"N": entry(1.0, 0.9, 0.5), "N0": entry(1.0)}},
    }
    checks = analysis.close_up_checks(material, 64)["N"]
    gains = {v: g for v, g in checks["offset_gain"].items() if g is not None}
    assert gains == {"level0_side": 2.5, "level2_side": 0.5}  # no N0 or no view: no gain
    assert checks["offset_gain_min"] == 0.5 and checks["offset_loses"] == ["level2_side"]
    assert (checks["low_light_mean"], checks["low_light_p99"]) == (0.9, 0.5)
    assert analysis.close_up(material, 64, "N")["mse_over_c_max"] is None  # no C: no ratio
    assert analysis.close_up({}, 64, "N")["low_light_p99"] is None


def test_sweeps_of_the_known_answer_are_flat():
    """flat answers 0.5 / pi everywhere: no steps across levels, seams, shifts or sub-texel moves."""
    ev = LocalMaterials(MODELS, threads=1)
    s = stability.sweeps(ev, "flat", 32, 64)
    assert s["grazing"]["finite"] and s["grazing"]["max_over_min"] < 1.01
    assert s["sigma"]["largest_step"] < 0.01
    assert s["position"]["seam_step"] < 0.01 and max(s["position"]["max_rel_change"][:5]) < 0.01
    assert np.mean(s["grazing"]["mean"]) == pytest.approx(0.5 / math.pi, rel=0.01)
