"""The `--quick` report pipeline on real renders: flat (the known answer) and rock, one view.

Checks real numbers: on `flat` the neural image equals the real geometry within the reference's
noise; on rock the reference's own noise is far below the differences the report draws conclusions
from; a re-run reuses every cached render and gives the same numbers.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from neumip.training.report.config import QUICK
from neumip.training.report.run import run_report
from neumip.training.report.views import DISTANCE_VIEWS

MODELS = Path(__file__).resolve().parents[3] / "models"
VIEW = DISTANCE_VIEWS[0].name


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    results = run_report(root / "out", ["flat", "rock"], QUICK, MODELS, root / "cache", stages=("images",),
                         views=DISTANCE_VIEWS[:1])
    return root, results


def entry(results, material, method, spp=QUICK.spp):
    return results["materials"][material][VIEW]["methods"][method][str(spp)]


def test_flat_neural_equals_the_reference_within_its_noise(report):
    _, results = report
    n = entry(results, "flat", "N")
    ref_noise = results["materials"]["flat"][VIEW]["reference"]["noise_mse"]
    assert n["mse"] <= 1.2 * (n["noise"] + ref_noise)  # nothing left but the two images' noise
    assert n["mean_ratio"] == pytest.approx(1.0, abs=0.02)
    assert n["bias"] < 0.2 * n["noise"]


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
        for spp in QUICK.reference_ladder:
            assert set(methods["R"][str(spp)]) >= {"mse", "flip", "ssim", "seconds", "mean_ratio"}
        assert (out / "strips" / f"{material}_{VIEW}.png").stat().st_size > 1000
        assert (out / f"error_time_{material}.png").exists()
    assert "N0" in on_disk["materials"]["rock"][VIEW]["methods"]  # rock_nooffset is shipped
    text = (out / "report.md").read_text()
    row = on_disk["materials"]["rock"]["headline"][0]
    assert f"{row['N']['mse'] * 1e3:.3f} / {row['N']['flip']:.3f}" in text


def test_rerun_reuses_every_render(report):
    root, results = report
    again = run_report(root / "out2", ["flat"], QUICK, MODELS, root / "cache", stages=("images",),
                       views=DISTANCE_VIEWS[:1])
    assert again["cached_renders_reused"] > 0
    assert again["materials"]["flat"][VIEW]["methods"]["N"] == results["materials"]["flat"][VIEW]["methods"]["N"]


@pytest.mark.slow
def test_cli_quick_runs_every_stage(tmp_path):
    """`neumip report --quick` end to end (every view, stability, the trade-off's training): minutes."""
    from neumip.client.cli import main

    out = tmp_path / "report"
    assert main(["report", "--quick", "-o", str(out), "--materials", "flat", "rock", "yarn",
                 "--models", str(MODELS), "--cache", str(tmp_path / "cache")]) == 0
    results = json.loads((out / "results.json").read_text())
    assert set(results["tradeoff"]["points"]) >= {"base", "no_offset", "seed1", "seed2"}
    assert all(p["queries_per_second"] > 0 for p in results["tradeoff"]["points"].values())
    assert results["stability"]["sweeps"]["flat"]["sigma"]["largest_step"] < 0.01
    assert "horizon" in results["stability"]
    for name in ("tradeoff.png", "stability_sweeps.png", "horizon.png", "report.md"):
        assert (out / name).exists()
