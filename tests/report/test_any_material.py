"""The report as an instrument on any material: description files and their models, the light set,
per-light verdicts, footprints in the description's texels, honest FLIP maps, where output goes."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from neumip.report import analysis, metrics, views
from neumip.report.config import FULL, QUICK
from neumip.report.methods import MissingModelError, neural_models
from neumip.report.run import ReportError, find_materials, run_report

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "models"
PLANKS = ROOT / "docs" / "materials" / "planks.toml"


def user_material(folder: Path, name: str = "mine") -> Path:
    """A copy of the planks description (maps beside it) under another name."""
    for f in PLANKS.parent.glob("planks_*.png"):
        shutil.copy(f, folder / f.name)
    text = PLANKS.read_text().replace('name = "planks"', f'name = "{name}"')
    path = folder / f"{name}.toml"
    path.write_text(text)
    return path


def test_a_description_file_finds_its_models_by_the_description_name(tmp_path):
    toml = user_material(tmp_path, "mine")
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(MODELS / "rock.onnx", models / "mine.onnx")
    found = find_materials([str(toml)], models)  # not "mine.toml.onnx"
    assert list(found) == ["mine"] and found["mine"].name == "mine"
    assert neural_models("mine", models) == {"N": models / "mine.onnx"}
    shutil.copy(MODELS / "rock.onnx", models / "mine_maps.onnx")  # another method: found by its name
    assert set(neural_models("mine", models)) == {"N", "Nmaps"}


@pytest.mark.parametrize("material", ["user_file", "shipped_name"])
def test_a_missing_model_is_one_error_and_nothing_is_written(tmp_path, material):
    toml = user_material(tmp_path, "mine")
    arg = str(toml) if material == "user_file" else "yarn"
    models = tmp_path / "empty_models"
    models.mkdir()
    out, cache = tmp_path / "out" / "report", tmp_path / "cache"
    with pytest.raises(MissingModelError, match="no model .*(mine|yarn).onnx"):
        run_report(out, [arg], QUICK, models, cache)
    assert not (tmp_path / "out").exists() and not cache.exists()



def test_a_corrupt_model_is_one_error_before_any_render(tmp_path):
    """A model file that is there but unusable (not ONNX) fails the check, not the first neural render
    after the reference renders; nothing is written."""
    from neumip.engines.local import ModelError

    toml = user_material(tmp_path, "mine")
    models = tmp_path / "models"
    models.mkdir()
    (models / "mine.onnx").write_bytes(b"not onnx")
    out, cache = tmp_path / "out" / "report", tmp_path / "cache"
    with pytest.raises(ModelError, match="mine.onnx"):
        run_report(out, [str(toml)], QUICK, models, cache)
    assert not (tmp_path / "out").exists() and not cache.exists()

def test_the_cli_says_one_line_and_writes_nothing(tmp_path, capsys):
    from neumip.client.cli import main

    toml = user_material(tmp_path, "mine")
    out = tmp_path / "out"
    assert main(["report", "--quick", "--materials", str(toml), "--models", str(tmp_path), "-o", str(out),
                 "--cache", str(tmp_path / "cache")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no model" in err[0] and "mine.onnx" in err[0]
    assert not out.exists() and not (tmp_path / "cache").exists()
    with pytest.raises(ReportError, match="twice"):
        find_materials(["rock", "rock"], MODELS)


def test_the_default_output_is_not_the_committed_report():
    from neumip.client.cli import build_parser

    args = build_parser().parse_args(["report"])
    assert args.output is None  # resolved to runs/report/out: docs/report only when asked with -o


def test_every_distance_is_seen_under_three_different_lights():
    lights = {light.name: light for light in views.LIGHTS}
    assert {"high", "side", "front"} <= set(lights)
    for level in views.LEVELS:
        at = [v for v in views.DISTANCE_VIEWS if v.level == level]
        assert {v.light for v in at} == set(lights)
        directions = np.array([views.light_direction(v) for v in at])
        assert np.min(np.abs(directions @ directions.T - np.eye(len(at)) * 2)) < 0.99  # pairwise different
    assert lights["high"].zenith <= 30
    assert views.light_direction(views.distance_view(0, lights["front"]))[1] > 0  # beyond the centre, facing the camera
    assert views.light_direction(views.distance_view(0, lights["side"]))[1] == pytest.approx(0, abs=1e-9)
    assert min(views.LEVELS) == 0 and 2 ** max(views.LEVELS) >= 256  # 1 to 256 map texels
    assert [v.name for v in views.EXTRA_VIEWS] == ["grazing75", "grazing85", "low_light"]
    assert sum(v.ladder for v in views.DISTANCE_VIEWS) == len(views.LEVELS)  # ladders under one light


def test_a_verdict_holds_only_where_it_holds_under_every_light():
    def rows(n_wins_from):
        return [{"texels": t, "N": {"mse": 1.0 if t >= n_wins_from else 3.0, "bias": 1.0}, "C": {"mse": 2.0, "bias": 2.0},
                 "Cmip": None} for t in (1, 4, 16, 64, 256)]

    v = analysis.verdicts({"high": rows(1), "side": rows(1), "front": rows(16)})["N"]
    assert v["C_mse"]["from"] == 16 and v["C_mse"]["fails_under"] == ["front"]
    assert v["C_bias"]["from"] == 1 and v["C_bias"]["fails_under"] == []
    never = analysis.verdicts({"high": rows(1), "front": rows(1000)})["N"]
    assert never["C_mse"]["from"] is None and never["C_mse"]["fails_under"] == ["front"]


def test_footprints_count_the_description_texels_whatever_the_model():
    """Two models of one material (64^2 and 256^2) are judged on the same views: the renderer's
    footprint unit is the description's resolution, never the model's."""
    from neumip.engines.kernel import KernelMaterials
    from neumip.groundtruth.description import find_description, resolve
    from neumip.report.renderer import MaterialRenderer

    desc = find_description("rock")
    r = MaterialRenderer("rock", desc, resolve(desc), MODELS, KernelMaterials(MODELS), FULL, None)
    assert r.resolution == desc.resolution == 256
    close, far = views.distance_view(0, views.LIGHTS[0]), views.distance_view(8, views.LIGHTS[0])
    assert r.spec(close).distance * 256 == pytest.approx(views.camera_distance(close, FULL.film, 1))
    assert r.spec(close).film == FULL.film
    small = r.spec(far).film  # 256 texels at 192 x 144 would show ~190 000 tiles of real geometry
    assert small.width < FULL.film.width and small.width / small.height == pytest.approx(4 / 3, rel=0.1)


def test_film_for_tiles_keeps_the_real_geometry_bounded():
    view, film = views.distance_view(8, views.LIGHTS[1]), views.Film(192, 144)
    tiles = film.width * film.height * (2 * 256 / 256) ** 2 / math.cos(math.radians(view.theta))
    shrunk = views.film_for_tiles(view, film, 256, tiles / 4)
    assert (shrunk.width, shrunk.height) == (96, 72)
    assert views.film_for_tiles(view, film, 256, tiles * 2) == film


def test_flip_map_is_the_error_whose_mean_is_the_score():
    """The map shown in the strips is FLIP's error itself: its mean equals the FLIP score (the old map,
    a channel of the magma-coloured map, averaged 0.217 where the score was 0.189)."""
    rng = np.random.default_rng(1)
    reference = rng.uniform(0.0, 0.3, (48, 64, 3))
    image = np.clip(reference * rng.uniform(0.5, 1.6, reference.shape), 0, None)
    scores, fmap = metrics.score(reference, image, metrics.exposure_for(reference))
    assert fmap.shape == (48, 64)
    assert 0.0 <= fmap.min() and fmap.max() <= 1.0
    assert float(fmap.mean()) == pytest.approx(scores.flip, rel=1e-4)


def test_time_to_reach_extrapolates_only_an_unbiased_method():
    ladder = {1: {"mse": 1.1e-2, "seconds": 1.0}, 4: {"mse": 3.5e-3, "seconds": 4.0}}
    assert analysis.time_to_reach(ladder, 2e-3) is None  # a biased method: beyond its ladder, unknown
    floor = 1e-3  # R's noise: error above it falls as 1/time
    assert analysis.time_to_reach(ladder, 2e-3, floor) == pytest.approx(4.0 * 2.5e-3 / 1e-3)
    assert analysis.time_to_reach(ladder, 0.5e-3, floor) is None  # below the reference's own noise
