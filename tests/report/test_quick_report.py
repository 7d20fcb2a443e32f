"""The `--quick` report pipeline on real renders: flat (the known answer), rock, and a user's material
given as a description file (planks, from texture maps, with its own models and a second model judged
beside them), in one ladder view.

Checks real numbers: on `flat` the neural image equals the real geometry within the reference's
noise; on rock the reference's own noise is far below the differences the report draws conclusions
from; the user's material is rendered with the models named after its description; a re-run reuses
every cached render and gives the same numbers.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import pytest

from neumip.report.config import QUICK
from neumip.report.run import run_report
from neumip.report.views import DISTANCE_VIEWS

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "models"
USER_MATERIAL = ROOT / "docs" / "materials" / "planks.toml"
USER_MODELS = ROOT / "docs" / "materials" / "planks_models"
LADDER_VIEW = next(v for v in DISTANCE_VIEWS if v.ladder and v.level == 0)
VIEW = LADDER_VIEW.name


@pytest.fixture(scope="module")
def models(tmp_path_factory, one_torch_thread):
    """One models folder with shipped models and the user's material's, and a second model of it to judge beside N
    (planks_maps, planks_maps_nooffset: stand-ins, the planks ablation and the shipped rock's; links: the report reads
    one folder)."""
    folder = tmp_path_factory.mktemp("models")
    for f in [*MODELS.glob("flat.onnx"), *MODELS.glob("rock*.onnx"), *USER_MODELS.glob("planks*.onnx")]:
        (folder / f.name).symlink_to(f)
    (folder / "planks_maps.onnx").symlink_to(USER_MODELS / "planks_nooffset.onnx")
    (folder / "planks_maps_nooffset.onnx").symlink_to(MODELS / "rock_nooffset.onnx")
    return folder


@pytest.fixture(scope="module")
def report(tmp_path_factory, models):
    root = tmp_path_factory.mktemp("report")
    results = run_report(root / "out", ["flat", "rock", str(USER_MATERIAL)], QUICK, models, root / "cache",
                         stages=("images",), views=(LADDER_VIEW,))
    return root, results


def entry(results, material, method, spp=QUICK.spp):
    return results["materials"][material][VIEW]["methods"][method][str(spp)]


def test_flat_neural_equals_the_reference_within_its_noise(report):
    _, results = report
    n = entry(results, "flat", "N")
    ref_noise = results["materials"]["flat"][VIEW]["reference"]["noise_mse"]
    assert n["mse"] <= 1.2 * (n["noise"] + ref_noise)  # nothing left but the two images' noise
    assert n["mean_ratio"] == pytest.approx(1.0, abs=0.02)
    assert n["bias"] < 0.2 * (n["noise"] + ref_noise)  # what is left: the trained model's own small error


def test_reference_noise_is_below_the_differences_reported(report):
    _, results = report
    view = results["materials"]["rock"][VIEW]
    ref_noise = view["reference"]["noise_mse"]
    mse = {m: entry(results, "rock", m)["mse"] for m in ("N", "N0", "C", "Cmip")}
    gaps = [abs(mse["C"] - mse["N"]), abs(mse["Cmip"] - mse["N"]), abs(mse["N0"] - mse["N"])]
    assert ref_noise < 0.25 * min(gaps), (ref_noise, mse)
    r = entry(results, "rock", "R")  # R against itself: no bias beyond its noise
    assert r["bias"] < 0.2 * r["noise"]


def test_results_json_and_markdown(report):
    root, results = report
    out = root / "out"
    on_disk = json.loads((out / "results.json").read_text())
    for material in ("flat", "rock"):
        methods = on_disk["materials"][material][VIEW]["methods"]
        assert set(methods) >= {"R", "N", "C", "Cmip"}
        for spp in QUICK.ladder:
            assert set(methods["R"][str(spp)]) >= {"mse", "flip", "ssim", "seconds", "load", "mean_ratio"}
        assert (out / "strips" / f"{material}_{VIEW}.png").stat().st_size > 1000
        assert (out / f"error_time_{material}.png").exists()
    assert "N0" in on_disk["materials"]["rock"][VIEW]["methods"]  # rock_nooffset is shipped
    text = (out / "report.md").read_text()
    row = on_disk["materials"]["rock"]["headline"][LADDER_VIEW.light][0]
    assert f"{row['N']['mse'] * 1e3:.3f} / {row['N']['flip']:.3f}" in text
    assert text.startswith("# neumip evidence report: SMOKE RUN (--quick)")
    assert "Time to error" not in text and "time_to_error" not in on_disk["materials"]["rock"]
    assert not (root / ".out.partial").exists()  # published whole


def test_user_material_from_a_description_file(report):
    """`--materials my.toml`: the description's name finds planks.onnx and planks_nooffset.onnx."""
    _, results = report
    methods = results["materials"]["planks"][VIEW]["methods"]
    assert set(methods) >= {"R", "N", "N0", "C", "Cmip"}
    assert methods["N"][str(QUICK.spp)]["mean_ratio"] == pytest.approx(1.0, abs=0.5)  # a plausible image of it


def test_a_second_model_is_judged_as_n(report):
    """A second model, planks_maps.onnx with planks_maps_nooffset.onnx, is rendered as Nmaps and Nmaps0 and judged like N:
    a verdict, close-up checks with the offset's gain Nmaps0 / Nmaps, rows beside N's in the tables."""
    root, results = report
    mat = results["materials"]["planks"]
    methods = mat[VIEW]["methods"]
    assert {"Nmaps", "Nmaps0"} <= set(methods)
    assert methods["Nmaps"][str(QUICK.spp)]["mse"] != methods["N"][str(QUICK.spp)]["mse"]  # another model's image
    assert set(mat["verdicts"]) == set(mat["close_up"]) == {"N", "Nmaps"}
    nmaps = mat["close_up"]["Nmaps"]
    gain = methods["Nmaps0"][str(QUICK.spp)]["mse"] / methods["Nmaps"][str(QUICK.spp)]["mse"]
    assert nmaps["offset_gain"][VIEW] == pytest.approx(gain)
    over_c = methods["Nmaps"][str(QUICK.spp)]["mse"] / methods["C"][str(QUICK.spp)]["mse"]
    assert nmaps["mse_over_c_max"] == pytest.approx(over_c)  # the one close-up rendered
    assert set(results["materials"]["flat"]["verdicts"]) == {"N"}  # no flat_maps: no Nmaps verdict
    text = (root / "out" / "report.md").read_text()
    assert "| planks | N |" in text and "| planks | Nmaps |" in text and "- **planks, Nmaps**:" in text
    assert np.isfinite([e["mse"] for e in methods["Nmaps"].values()]).all()


def test_rerun_reuses_every_render(report):
    root, results = report
    again = run_report(root / "out2", ["flat"], QUICK, MODELS, root / "cache", stages=("images",),
                       views=(LADDER_VIEW,))
    assert again["cached_renders_reused"] > 0
    assert again["materials"]["flat"][VIEW]["methods"]["N"] == results["materials"]["flat"][VIEW]["methods"]["N"]


def test_a_new_model_re_times_every_method_beside_it(report, tmp_path):
    """Timings are compared as ratios within one run: where a ladder view renders a model anew, every
    method's timed rungs are rendered anew too, not taken from the cache (their images are the same)."""
    import onnx

    root, results = report
    model = onnx.load(MODELS / "flat.onnx")
    model.doc_string = "the same material, another file"
    onnx.save(model, tmp_path / "flat.onnx")
    again = run_report(root / "out3", ["flat"], QUICK, tmp_path, root / "cache", stages=("images",),
                       views=(LADDER_VIEW,))
    before, after = (r["materials"]["flat"][VIEW]["methods"] for r in (results, again))
    for method in ("R", "C"):
        for spp in QUICK.ladder:
            old, new = before[method][str(spp)], after[method][str(spp)]
            assert new["mse"] == old["mse"]  # the same image
            assert (new["seconds"], new["load"]) != (old["seconds"], old["load"])  # timed again, in this run


def test_retime_times_every_rung_anew_and_keeps_the_images(report):
    """`--retime`: the same files, every method's timed rungs rendered anew in this run (their images the same,
    their timings this run's); the references and the scored renders come from the cache."""
    import dataclasses

    root, results = report
    again = run_report(root / "out4", ["flat"], dataclasses.replace(QUICK, retime=True), MODELS, root / "cache",
                       stages=("images",), views=(LADDER_VIEW,))
    before, after = (r["materials"]["flat"][VIEW]["methods"] for r in (results, again))
    for method in ("R", "N", "C"):
        for spp in QUICK.ladder:
            old, new = before[method][str(spp)], after[method][str(spp)]
            assert new["mse"] == old["mse"]
            assert (new["seconds"], new["load"]) != (old["seconds"], old["load"])
    assert again["cached_renders_reused"] > 0  # the references


@pytest.mark.slow
def test_cli_quick_runs_every_stage(tmp_path):
    """`neumip report --quick` end to end (every view, stability, the trade-off's training): minutes."""
    from neumip.client.cli import main

    out = tmp_path / "report"
    assert main(["report", "--quick", "-o", str(out), "--materials", "flat", "rock", "yarn",
                 "--models", str(MODELS), "--cache", str(tmp_path / "cache")]) == 0
    results = json.loads((out / "results.json").read_text())
    points = results["tradeoff"]["points"]
    assert set(points) >= {"base", "no_offset", "seed1", "seed2", "maps", "maps_hz"}  # rock has maps
    assert all(p["queries_per_second"] > 0 and p["training_seconds"] > 0 for p in points.values())
    assert points["maps_hz"]["maps"]["horizons"] == 8 and results["tradeoff"]["note"] is None
    assert results["stability"]["sweeps"]["flat"]["sigma"]["largest_step"] < 0.01
    assert "horizon" in results["stability"]
    for name in ("tradeoff.png", "stability_sweeps.png", "horizon.png", "report.md"):
        assert (out / name).exists()
