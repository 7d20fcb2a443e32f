"""Every judged neural method (the paper's N, the map-informed Nmaps) is judged as N is: verdicts,
time to error, close-up checks and their tables, from small result dictionaries with known numbers;
and the trade-off's map-informed stages with what they cost."""

from __future__ import annotations

import json
import math

import pytest

from neumip.report import analysis, tradeoff, writer
from neumip.report.config import FULL, QUICK
from neumip.report.methods import JUDGED, NEURAL_MODELS, NO_OFFSET
from neumip.report.run import missing_ablations

SPP = FULL.spp
FOOTPRINTS = (1, 4, 16, 64, 256)


def _rows(wins_from: dict[str, float]) -> list[dict]:
    """Headline rows of one light: each method's MSE 1 from its footprint on, else 3; C's is 2."""
    return [{"texels": t, "C": {"mse": 2.0, "bias": 2.0}, "Cmip": {"mse": 2.0, "bias": 2.0},
             **{m: {"mse": 1.0 if t >= f else 3.0, "bias": 1.0} for m, f in wins_from.items()}} for t in FOOTPRINTS]


def test_each_judged_method_gets_its_own_verdicts():
    """Nmaps beats C from 1 texel under every light where N only does from 16 (the old verdicts were N's only)."""
    headline = {"high": _rows({"N": 16, "Nmaps": 1}), "side": _rows({"N": 4, "Nmaps": 1}),
                "front": _rows({"N": 16, "Nmaps": 4})}
    v = analysis.verdicts(headline)
    assert set(v) == {"N", "Nmaps"}
    assert v["N"]["C_mse"]["from"] == 16 and v["N"]["C_mse"]["fails_under"] == ["high", "front"]
    assert v["Nmaps"]["C_mse"]["from"] == 4 and v["Nmaps"]["C_mse"]["fails_under"] == ["front"]
    assert v["Nmaps"]["Cmip_bias"]["from"] == 1
    only_n = analysis.verdicts({"side": _rows({"N": 4})})
    assert set(only_n) == {"N"}  # a method without its model gets no verdict


def _ladder(points: dict[int, tuple[float, float]]) -> dict:
    return {spp: {"mse": mse, "seconds": secs, "load": 2.0} for spp, (mse, secs) in points.items()}


def _scored(mse: float, seconds: float | None = None, flip: float = 0.1, mean: float = 1.0, p99: float = 1.0) -> dict:
    e = {"mse": mse, "flip": flip, "ssim": 0.9, "mean_ratio": mean, "p99_ratio": p99, "bias": mse / 2, "noise": mse / 2}
    return e if seconds is None else {**e, "seconds": seconds, "load": 3.0}


def _ladder_view() -> dict:
    """level0_side: R's error falls as 1/time (8e-3 at 1 s, 2e-3 at 4 s); N at 64 spp reaches 4e-3
    in 2 s, Nmaps 1e-3 in 0.5 s, C's ladder stalls at 3e-3."""
    return {"reference": {"noise_mse": 0.0},
            "methods": {"R": _ladder({1: (8e-3, 1.0), 4: (2e-3, 4.0)}),
                        "N": {1: {"mse": 9e-3, "seconds": 0.1, "load": 2.5}, SPP: _scored(4e-3, 2.0)},
                        "Nmaps": {1: {"mse": 5e-3, "seconds": 0.1, "load": 2.5}, SPP: _scored(1e-3, 0.5)},
                        "N0": {SPP: _scored(5e-3)},
                        "C": {1: {"mse": 3e-3, "seconds": 0.05, "load": 2.0}, SPP: _scored(3e-3, 1.0, flip=0.2)}}}


def test_time_to_error_is_the_geometry_over_each_method():
    """R reaches N's MSE (4e-3) in 2 s: ratio 1; Nmaps' (1e-3) only beyond its ladder, extrapolated
    as 1/time to 8 s: ratio 16. C never gets below 3e-3: it reaches N's error but not Nmaps'."""
    rows = analysis.time_to_error({"level0_side": _ladder_view()}, SPP)
    by = {r["method"]: r for r in rows}
    assert set(by) == {"N", "Nmaps"} and all(r["texels"] == 1 for r in rows)
    assert by["N"]["seconds"]["R"] == pytest.approx(2.0) and by["N"]["ratio"] == pytest.approx(1.0)
    assert by["Nmaps"]["seconds"]["R"] == pytest.approx(8.0) and by["Nmaps"]["ratio"] == pytest.approx(16.0)
    assert by["N"]["seconds"]["C"] == pytest.approx(0.05) and by["Nmaps"]["seconds"]["C"] is None
    assert (by["N"]["target_mse"], by["N"]["own_seconds"]) == (4e-3, 2.0)
    assert by["N"]["load"]["R"] == 2.0 and by["Nmaps"]["load"]["Nmaps"] == 3.0
    # each rung of N's own ladder: its 1-spp error (9e-3, above R's first rung) R reaches only with its 1-spp
    # render, 1 s: 10x N's 0.1 s; its 64-spp error, the ratio above
    assert by["N"]["rungs"] == {1: pytest.approx(10.0), SPP: pytest.approx(1.0)}
    assert (by["N"]["best_spp"], by["N"]["best_ratio"]) == (1, pytest.approx(10.0))
    # Nmaps' 1-spp error 5e-3: R between its rungs, log-log, 4^(ln(5/8) / ln(1/4)) s
    assert by["Nmaps"]["rungs"][1] == pytest.approx(4 ** (math.log(5 / 8) / math.log(1 / 4)) / 0.1)


def _close_ups() -> dict:
    """Close-ups where Nmaps' offset gains 4x at level0_side and loses at level2_side; Nmaps is
    below half C's MSE everywhere but level2_high; N0 and N as in the old single-method test."""
    views = {}
    for name in analysis.CLOSE_UP_VIEWS:
        views[name] = {"reference": {"noise_mse": 0.0}, "methods": {"C": {SPP: _scored(4.0, flip=0.2)}, "N": {SPP: _scored(3.0, flip=0.3)},
                                   "N0": {SPP: _scored(3.0)}, "Nmaps": {SPP: _scored(1.0, flip=0.1)},
                                   "Nmaps0": {SPP: _scored(1.0)}}}
    views["level0_side"]["methods"]["Nmaps0"] = {SPP: _scored(4.0)}
    views["level2_side"]["methods"]["Nmaps0"] = {SPP: _scored(0.5)}
    views["level2_high"]["methods"]["Nmaps"] = {SPP: _scored(3.0, flip=0.25)}
    views["level2_high"]["methods"]["Nmaps0"] = {SPP: _scored(3.0)}
    views["low_light"] = {"methods": {"N": {SPP: _scored(1.0, mean=0.9, p99=0.5)},
                                      "Nmaps": {SPP: _scored(1.0, mean=0.97, p99=0.95)}}}
    return views


def test_close_up_checks_per_method():
    checks = analysis.close_up_checks(_close_ups(), SPP)
    assert set(checks) == {"N", "Nmaps"}
    m = checks["Nmaps"]
    gains = {v: g for v, g in m["offset_gain"].items() if g is not None}
    assert gains["level0_side"] == 4.0 and gains["level2_side"] == 0.5 and gains["level0_high"] == 1.0
    assert m["offset_gain"]["grazing75"] is None  # no view: no gain
    assert m["offset_gain_min"] == 0.5 and m["offset_loses"] == ["level2_side"]
    assert m["mse_over_c"]["level0_front"] == 0.25 and m["mse_over_c_max"] == 0.75  # level2_high
    assert m["flip_below_c"] == [len(analysis.CLOSE_UP_VIEWS) - 1, len(analysis.CLOSE_UP_VIEWS)]
    assert (m["low_light_mean"], m["low_light_p99"]) == (0.97, 0.95)
    n = checks["N"]
    assert n["offset_gain_min"] == 1.0 and n["mse_over_c_max"] == 0.75 and n["flip_below_c"][0] == 0
    assert (n["low_light_mean"], n["low_light_p99"]) == (0.9, 0.5)
    assert analysis.close_up_checks({}, SPP) == {}


def test_every_judged_method_has_a_no_offset_ablation_and_a_model_file():
    assert JUDGED == ("N", "Nmaps")
    assert NO_OFFSET == {"N": "N0", "Nmaps": "Nmaps0"}
    assert NEURAL_MODELS["Nmaps0"].format(name="rock") == "rock_maps_nooffset"
    notes = missing_ablations("rock", ("R", "N", "Nmaps", "C"), "models")
    assert len(notes) == 2 and "rock_nooffset" in notes[0] and "rock_maps_nooffset" in notes[1]
    assert missing_ablations("rock", ("R", "N", "N0", "C"), "models") == []


def _material_results() -> dict:
    """One material's results as results.json holds them: the analyses of small view results, through JSON."""
    views = {**_close_ups(), "level0_side": _ladder_view()}
    headline = {"side": [{"view": "level0_side", "texels": 1, "reference_noise": 1e-5,
                          **{m: views["level0_side"]["methods"][m][SPP] for m in ("N", "N0", "Nmaps", "C")},
                          "Cmip": None, "Nmaps0": None}]}
    mat = {"headline": headline, "verdicts": analysis.verdicts(headline),
           "close_up": analysis.close_up_checks(views, SPP), "time_to_error": analysis.time_to_error(views, SPP)}
    results = {"seconds": 60.0, "cached_renders_reused": 0, "materials": {"rock": mat},
               "notes": ["no rock_maps_nooffset model in models: Nmaps0 and Nmaps's offset gain not shown"]}
    return json.loads(json.dumps(results, default=float))


def test_the_tables_show_each_method_side_by_side(tmp_path):
    results = _material_results()
    text = writer.write_markdown(tmp_path, results, FULL).read_text()
    headline = writer.headline_table(results, "side")
    assert headline[0].startswith("| material | footprint (map texels) | N | Nmaps | C |")  # no ablations
    assert headline[2] == "| rock | 1 | 4.000 / 0.100 | 1.000 / 0.100 | 3.000 / 0.200 | 0.010 |"  # no Cmip: no column
    winners = writer.winners(results)
    assert [line.split(" | ")[1] for line in winners[2:]] == ["N", "Nmaps"]
    times = writer.time_table(results)
    assert "R's s / X's s" in times[0]
    assert "| rock | 1 | N | 4.000 | 2.00 | 2.00 | **1.00** | 0.05 | - | 10.00 / 1.00 |" in times[2]
    assert "at X's 1 / 64-spp error" in times[0]
    assert "| rock | 1 | Nmaps | 1.000 | 0.50 | 8.00 | **16.00** | - | - |" in times[3]
    close = writer.close_up_table(results)
    assert [line.split(" | ")[1] for line in close[2:]] == ["N", "Nmaps"]
    assert "| **1.33** | 1 of 6 |" in close[2]  # N: 4e-3 against C's 3e-3 at 1 texel (side), its FLIP below C's there only
    assert "| **0.75** | 5 of 6 | 0.97 | 0.95 |" in close[3]  # Nmaps: at most 3/4 of C's MSE (level2_high)
    assert "- **rock, Nmaps**: beats C by MSE at 64 spp from 1 map texels under every light" in text
    assert f"16.00x its time to reach its {SPP}-spp error at 1 texels" in text
    assert "at its most favourable rung, at least 10.00x at every footprint (the least at 1 texels, at 1 spp)" in text
    assert "Nmaps0 and Nmaps's offset gain not shown" in text
    smoke = writer.write_markdown(tmp_path, results, QUICK).read_text()
    assert "R's s / X's s" not in smoke  # a smoke run draws no timing verdicts


def test_map_variants_only_where_the_material_has_maps():
    names = [v.name for v in tradeoff.variants(FULL)]
    assert {"base", "no_offset", "maps", "maps_hz"} <= set(names) and len(set(names)) == len(names)
    with_maps = {v.name: v for v in tradeoff.variants(FULL)}
    assert with_maps["maps"].maps == tradeoff.MapConfig() and with_maps["maps_hz"].maps.horizons == 8
    assert (with_maps["maps"].resolution, with_maps["maps"].offset) == (with_maps["base"].resolution, True)
    assert not any(v.maps or v.classical or v.relief for v in tradeoff.variants(FULL, maps=False))
    assert [with_maps[f"relief{k}"].relief for k in (4, 8, 16)] == [4, 8, 16]
    assert not with_maps["relief8_no_offset"].offset
    assert tradeoff.describe(with_maps["maps_hz"])["maps"]["horizons"] == 8
    assert with_maps["classical"].classical and with_maps["classical"].maps is None
    assert with_maps["maps_hz_classical"].classical and with_maps["maps_hz_classical"].maps.horizons == 8


def test_the_tradeoff_table_shows_what_each_stage_costs(tmp_path):
    def point(maps, seconds, qps, classical=False, relief=0):
        v = tradeoff.Variant("x", maps=maps, classical=classical, relief=relief)
        return {**tradeoff.describe(v), "training_seconds": seconds, "setup_seconds": 1.0, "training_load": 2.5,
                "queries_per_second": qps,
                "validation_mse": 1e-3, "image_mse": 2e-3, "image_view": "level2_side"}

    points = {"base": point(None, 100.0, 2e6), "maps_hz": point(tradeoff.MapConfig(horizons=8), 130.0, 1.9e6),
              "maps_hz_classical": point(tradeoff.MapConfig(horizons=8), 150.0, 1.2e6, classical=True),
              "relief8": point(None, 120.0, 1.5e6, relief=8)}
    tr = json.loads(json.dumps({"material": "rock", "points": points, "steps": 600, "batch": 8192, "note": None}))
    lines = writer.tradeoff_section({"tradeoff": tr})
    assert any(line.startswith("| base |") and "| - | 0 | 100.0 (1.0; 2.5) | 2.00 |" in line for line in lines)
    assert any(line.startswith("| maps_hz |") and "| map encoder + 8 horizons | 0 | 130.0 (1.0; 2.5) | 1.90 |" in line
               for line in lines)
    assert any(line.startswith("| maps_hz_classical |") and "| map encoder + 8 horizons + classical base |" in line
               for line in lines)
    assert any(line.startswith("| relief8 |") and "| relief, 8 steps |" in line for line in lines)
    flat = writer.tradeoff_section({"tradeoff": {**tr, "points": {"base": tr["points"]["base"]},
                                                 "note": "flat has no height map (its height is 1 x 1): no map-informed variants"}})
    assert "flat has no height map (its height is 1 x 1): no map-informed variants." in flat
    assert set(tradeoff.training_cost(tmp_path, "base").values()) == {None}  # trained before costs were recorded
    from neumip.report import charts

    assert charts.tradeoff(tr["points"], tmp_path / "t.png").stat().st_size > 1000
