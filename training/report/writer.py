"""report.md: the tables and figures of one run, every number read from its results."""

from __future__ import annotations

import math
from pathlib import Path

from neumip.core.contract import sample_footprint

from .analysis import OFFSET_VIEWS
from .config import ReportConfig
from .methods import COMPARED, MAX_DEPTH
from .views import DISTANCE_VIEWS, LADDER_LIGHT, LEVELS, LIGHTS, VIEWS


def _f(x, scale: float = 1.0, digits: int = 3) -> str:
    return "-" if x is None else f"{x * scale:.{digits}f}"


def headline_table(results: dict, light: str, timings: bool = True) -> list[str]:
    """Per material and distance under one light: MSE x1e-3 / FLIP of every compared method."""
    methods = _methods(results)
    lines = ["| material | footprint (map texels) | " + " | ".join(methods) + " | R noise |",
             "|---|---|" + "---|" * (len(methods) + 1)]
    for name, mat in results["materials"].items():
        for row in mat.get("headline", {}).get(light, []):
            cells = [f"{_f(row[m]['mse'], 1e3)} / {_f(row[m]['flip'])}" if row.get(m) else "-" for m in methods]
            lines.append(f"| {name} | {row['texels']:g} | " + " | ".join(cells) + f" | {_f(row['reference_noise'], 1e3)} |")
    return lines


def _methods(results: dict) -> list[str]:
    """The compared methods present in any material (a method without its model is left out)."""
    present = set()
    for mat in results["materials"].values():
        for rows in mat.get("headline", {}).values():
            present |= {m for row in rows for m in COMPARED if row.get(m)}
    return [m for m in COMPARED if m in present]


def _footprint(x) -> str:
    return "never" if x is None else f"{x:g}"


def winners(results: dict) -> list[str]:
    lines = ["| material | N beats C: MSE at equal spp | C: bias (floor) | N beats Cmip: MSE | Cmip: bias |",
             "|---|---|---|---|---|"]
    for name, mat in results["materials"].items():
        v = mat.get("verdicts")
        if not v:
            continue
        cells = []
        for key in ("C_mse", "C_bias", "Cmip_mse", "Cmip_bias"):
            d = v[key]
            per = ", ".join(f"{light} {_footprint(x)}" for light, x in d["per_light"].items())
            cells.append(f"**{_footprint(d['from'])}** ({per})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def close_up_table(results: dict) -> list[str]:
    """Per material: the offset's gain (N0's MSE / N's) per view, its minimum, N's low-light mean and p99 / R's."""
    lines = ["| material | " + " | ".join(f"offset gain, {v}" for v in OFFSET_VIEWS)
             + " | smallest gain | low light: mean / R | low light: p99 / R |", "|---|" + "---|" * (len(OFFSET_VIEWS) + 3)]
    for name, mat in results["materials"].items():
        checks = mat.get("close_up")
        if checks:
            cells = [_f(checks["offset_gain"].get(v), 1, 2) for v in OFFSET_VIEWS]
            cells += [f"**{_f(checks['offset_gain_min'], 1, 2)}**", _f(checks["low_light_mean"], 1, 2),
                      _f(checks["low_light_p99"], 1, 2)]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def time_table(results: dict) -> list[str]:
    """Per material and ladder footprint: each method's seconds to reach N's MSE, with the load average."""
    methods = ["R"] + _methods(results)
    lines = ["| material | footprint (map texels) | N's MSE x1e-3 | " + " | ".join(f"{m} s" for m in methods)
             + " | load average |", "|---|---|---|" + "---|" * (len(methods) + 1)]
    for name, mat in results["materials"].items():
        for row in mat.get("time_to_error", []):
            loads = [x for x in row["load"].values() if x == x]
            load = f"{min(loads):.1f}-{max(loads):.1f}" if loads else "-"
            cells = [_f(row["seconds"].get(m), 1, 2) for m in methods]
            lines.append(f"| {name} | {row['texels']:g} | {_f(row['target_mse'], 1e3)} | " + " | ".join(cells) + f" | {load} |")
    return lines


def view_table(name: str, mat: dict, spp: int) -> list[str]:
    lines = [f"| view | film | method | MSE x1e-3 | FLIP | SSIM | mean / R | p99 / R | bias x1e-3 | noise x1e-3 |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for view in VIEWS:
        res = mat.get(view.name)
        if res is None:
            continue
        film = "x".join(map(str, res.get("film", [])))
        for m, entries in res["methods"].items():
            e = entries.get(str(spp))
            if e is None:
                continue
            lines.append(f"| {view.name} | {film} | {m} | {_f(e['mse'], 1e3)} | {_f(e['flip'])} | {_f(e['ssim'])} | "
                         f"{_f(e['mean_ratio'])} | {_f(e.get('p99_ratio'))} | {_f(e.get('bias'), 1e3)} | {_f(e.get('noise'), 1e3)} |")
    return lines


def fit_table(mat: dict) -> list[str]:
    """Per ladder view: each method's seconds per spp and fixed seconds per render (linear fit)."""
    views = [v.name for v in DISTANCE_VIEWS if mat.get(v.name, {}).get("fits")]
    if not views:
        return []
    lines = ["| method | " + " | ".join(f"{v}: ms/spp, fixed s" for v in views) + " |",
             "|---|" + "---|" * len(views)]
    for m in mat[views[0]]["fits"]:
        cells = [mat[v]["fits"].get(m) for v in views]
        lines.append(f"| {m} | " + " | ".join("-" if c is None else f"{c['seconds_per_spp'] * 1e3:.2f}, {c['fixed_seconds']:.2f}"
                                               for c in cells) + " |")
    return lines


SMOKE_TITLE = "# neumip evidence report: SMOKE RUN (--quick)"
SMOKE_NOTE = ("**This is a smoke run** (`neumip report --quick`): tiny images and few samples, to check that the "
              "pipeline runs. Its figures are not evidence, its timings mean nothing, and it draws no timing verdicts.")


def write_markdown(out: Path, results: dict, config: ReportConfig) -> Path:
    cfg = config
    lights = ", ".join(f"{l.name} (zenith {l.zenith:g}, azimuth {l.azimuth:g} degrees from the view)" for l in LIGHTS)
    L = [SMOKE_TITLE if cfg.smoke else "# neumip evidence report", ""]
    if cfg.smoke:
        L += [SMOKE_NOTE, ""]
    L += ["Generated by `" + results.get("command", "neumip report") + "` (every number below is in `results.json` "
         f"beside this file; this run took {results['seconds'] / 60:.1f} min and took {results['cached_renders_reused']} "
         f"renders from its cache; the renders' own wall time, summed: {results.get('render_seconds', 0) / 60:.1f} min). "
         "Timings are wall time in one process on a busy shared 2-core machine, with its load average beside them: "
         "compare them as ratios.", "",
         "## Set-up", "",
         f"- **Views**: a plane seen by a perspective camera ({cfg.film.width} x {cfg.film.height} pixels) at "
         "55 degrees from the normal, at distances where a pixel's footprint (std: half a pixel step, the film's "
         "Gaussian filter) covers " + ", ".join(f"{2 ** lv:g}" for lv in LEVELS) + " texels of the material's maps "
         "(its description's `resolution`, whatever the model's) at the image centre. Far views of real geometry "
         f"that would show more than {cfg.max_reference_tiles:,.0f} tiles get a smaller film of the same shape (R's "
         "cost grows with its instances; the film of each view is in the tables below). Every distance is lit by "
         f"each of three directional lights: {lights}, each giving unit irradiance on the plane, plus a dim constant "
         "environment (radiance 0.05). Grazing views at 75 and 85 degrees (side light) and a light 5 degrees above the "
         "horizon, at 4 map texels.",
         "- **R**: the real displaced microgeometry (the description's heightfield and principled maps), built "
         "from `instance`s of one block of tiles (a Mitsuba `shapegroup`) covering the visible "
         f"plane plus the parallax and shadow reach of the deepest groove, stock `path`, max_depth {MAX_DEPTH} "
         f"(up to 4 surface interactions, as the ground-truth tracer); a material without a heightfield is the plane "
         f"itself. Reference = mean of two seeds at {cfg.reference_spp} spp each; its noise (MSE of the mean, from "
         "the two seeds) is listed per view.",
         "- **N** / **N0** / **Nmaps**: the neural material `MODELS/NAME.onnx`, without the neural offset "
         "`NAME_nooffset.onnx`, informed by the maps `NAME_maps.onnx`, each where its file exists, `neumip_path`. "
         "Each of n samples per pixel queries max(1/8, 1/sqrt(n)) of the pixel footprint (pbrt-v4's rule): at "
         f"{cfg.spp} spp, {math.log2(1 / sample_footprint(cfg.spp)):g} levels finer than the footprint.",
         "- **C**: the generator's principled BSDF with full-resolution albedo, roughness and metallic bitmaps and a "
         "`normalmap` from the height's periodic central-difference gradient, stock `path`.",
         "- **Cmip**: C with every map box-averaged by 2^k before rendering, k = log2(pixel step x map resolution) at "
         "the image centre (one texel per pixel step, the trilinear mip rule; Mitsuba 3.9's bitmap has no mipmap "
         "filter, so the level is chosen per view). The normal map of level k comes from the box-averaged height, "
         "i.e. averaged slopes: grooves flatten as in a mip-mapped normal map.",
         f"- **Metrics**: linear-RGB MSE (x 1e-3); LDR-FLIP (`flip-evaluator`, mean of its error map) and SSIM "
         "(scikit-image) after the same tone mapping (exposure mapping R's mean luminance to 0.25, clip, sRGB); "
         f"mean luminance / R's. Each method is rendered with two seeds at {cfg.spp} spp: noise = MSE(seed 0, seed 1) "
         "/ 2, bias = MSE - noise - R's noise.",
         f"- **Error against time** (the {LADDER_LIGHT} light's views): every method, R included, at {list(cfg.ladder)} "
         f"spp in interleaved rounds (R, N, ..., R, N, ...), one untimed round then {cfg.rounds} timed; only the "
         "method being timed has a scene alive in the process (built, warmed up by an untimed 1-spp render, "
         "rendered, released); median seconds, with the 1-minute load average. R's time beyond its 64-spp rung is "
         "extrapolated (unbiased: its error above R's noise falls as 1/time).", ""]
    L += ["## Summary", "", "What holds under every light (read from the tables below):", ""]
    L += summary(results, cfg) + [""]
    L += ["## Headline", "", f"MSE x1e-3 / FLIP at {cfg.spp} spp, one table per light.", ""]
    for light in LIGHTS:
        L += [f"### Light: {light.name} (zenith {light.zenith:g}, azimuth {light.azimuth:g})", ""]
        L += headline_table(results, light.name) + [""]
    L += ["Footprint (map texels) from which N is better than the classical material at every larger footprint, "
          f"by MSE at {cfg.spp} spp (what a render at equal samples shows) and by bias (the error floor left after "
          "the noise is averaged away). **Bold: the verdict under every light** (the largest of the per-light "
          "footprints; `never` where under some light N never wins from the largest footprint down); in brackets, "
          "each light's own.", ""]
    L += winners(results) + [""]
    fails = _failing_lights(results)
    if fails:
        L += ["Where a stronger verdict fails: " + "; ".join(fails) + ".", ""]
    L += [f"Close-ups: the neural offset's gain (N0's MSE / N's, at {cfg.spp} spp; above 1: the offset helps) at 1 and "
          "4 map texels under every light and at the grazing views; **the smallest gain is the one that holds "
          "everywhere**. Then whether N's highlights survive a light 5 degrees above the horizon (its mean and "
          "99th-percentile luminance / R's):", ""]
    L += close_up_table(results) + [""]
    if cfg.smoke:
        L += ["No timing verdicts: a smoke run's timings mean nothing.", ""]
    else:
        L += [f"Time to error ({LADDER_LIGHT} light): seconds each method's timed ladder needs to reach N's MSE at "
              f"{cfg.spp} spp (log-log interpolation between rungs; `-`: its error never gets there, a bias floor; "
              "R beyond its ladder extrapolated), with the machine's 1-minute load average over those renders.", ""]
        L += time_table(results) + [""]
    for name, note in results.get("notes", {}).items():
        L.append(f"- {note}")
    L.append("")
    for name, mat in results["materials"].items():
        L += [f"## {name}", "", f"![error against time]({'error_time_' + name + '.png'})", ""]
        if not cfg.smoke:
            L += fit_table(mat) + [""]
        L += view_table(name, mat, cfg.spp) + [""]
        for view in VIEWS:
            if view.name in mat:
                L += [f"![{name} {view.name}](strips/{name}_{view.name}.png)", ""]
    L += stability_section(results) + tradeoff_section(results)
    path = out / "report.md"
    path.write_text("\n".join(L) + "\n")
    return path


def _failing_lights(results: dict) -> list[str]:
    """Per material and verdict: the best per-light footprint and the lights under which it fails."""
    out = []
    for name, mat in results["materials"].items():
        for key, d in mat.get("verdicts", {}).items():
            known = [x for x in d["per_light"].values() if x is not None]
            if d["fails_under"] and known:
                against, what = key.split("_")
                out.append(f"{name}, N beats {against} by {what} from {min(known):g} texels: "
                           f"not under {', '.join(d['fails_under'])}")
    return out


def summary(results: dict, config: ReportConfig) -> list[str]:
    """One line per material: the verdicts that hold under every light, and the lights that break stronger ones."""
    lines = []
    for name, mat in results["materials"].items():
        v, checks = mat.get("verdicts"), mat.get("close_up", {})
        if not v:
            continue
        parts = []
        for against in ("C", "Cmip"):
            d = v[f"{against}_mse"]
            where = "never under every light" if d["from"] is None else f"from {d['from']:g} map texels under every light"
            fails = f" (fails under {', '.join(d['fails_under'])} from a smaller footprint)" if d["fails_under"] else ""
            parts.append(f"N beats {against} by MSE at {config.spp} spp {where}{fails}")
        if checks.get("offset_gain_min") is not None:
            loses = checks["offset_loses"]
            parts.append(f"the neural offset's gain is at least {checks['offset_gain_min']:.2f}x in its close-up views"
                         + (f" (the offset loses in {', '.join(loses)})" if loses else ""))
        lines.append(f"- **{name}**: " + "; ".join(parts) + ".")
    return lines


def stability_section(results: dict) -> list[str]:
    st = results.get("stability")
    if not st:
        return []
    L = ["## Stability", "", "![sweeps](stability_sweeps.png)", "",
         "| model | grazing: 89.9 / 80 deg | grazing finite | sigma: largest step (at level) | median step | "
         "u + 1e3: max change | u + 1e6: max change | seam step | interior step | sub-texel largest step / range |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for name, s in st["sweeps"].items():
        g, sg, p, t = s["grazing"], s["sigma"], s["position"], s["subtexel"]
        shifts = dict(zip(p["shift_tiles"], p["max_rel_change"]))
        L.append(f"| {name} | {_f(g['ratio_89_9_to_80'])} | {g['finite']} | {_f(sg['largest_step'])} ({sg['at_level']:.2f}) | "
                 f"{_f(sg['median_step'], 1, 4)} | {_f(shifts.get(1000.0))} | {_f(shifts.get(1000000.0))} | "
                 f"{_f(p['seam_step'])} | {_f(p['interior_step'])} | {_f(t['largest_step_over_range'])} |")
    L += ["", "Steps and changes are relative to the mean answer. u + k moves a query by k whole tiles (the answer "
          "should not change); float32 positions near 1e6 are spaced 0.06 tiles apart, so there the position itself "
          "is lost before the model sees it.", ""]
    if "horizon" in st:
        h = st["horizon"]
        L += ["![horizon](horizon.png)", "",
              "A plane out to the horizon (N and C; R cannot be built to the horizon). Largest relative jump of the "
              "row-mean luminance between neighbouring rows (bands or popping between levels show as jumps): "
              + ", ".join(f"{m} {_f(r['largest_jump'])} (median {_f(r['median_jump'], 1, 4)})" for m, r in h.items())
              + ". The largest jumps are the pattern's own rows near the camera, in both; a level boundary would "
              "show as a step in N's profile that C's lacks.", ""]
    L += ["Glints under a low light: the `low_light` strips above (light 5 degrees above the horizon).", ""]
    return L


def tradeoff_section(results: dict) -> list[str]:
    tr = results.get("tradeoff")
    if not tr:
        return []
    L = ["## The model's own trade-off", "",
         f"Configurations trained on {tr['material']} with {tr['steps']} steps of {tr['batch']} queries (a short "
         "schedule, the same for all: they compare with one another, not with the shipped models, and the larger "
         "pyramids are the least converged after it). Validation MSE "
         "on low-noise (64 spp) reference queries; image MSE in the level0 view against R; queries per second "
         "in-process (ONNX Runtime, median of interleaved rounds).", "",
         "![trade-off](tradeoff.png)", "",
         "| configuration | resolution | channels | MLP width | offset | seed | M queries/s | validation MSE x1e-3 | image MSE x1e-3 |",
         "|---|---|---|---|---|---|---|---|---|"]
    for name, p in tr["points"].items():
        L.append(f"| {name} | {p['resolution']} | {p['channels']} | {p['hidden']} | {p['offset']} | {p['seed']} | "
                 f"{p['queries_per_second'] / 1e6:.2f} | {_f(p['validation_mse'], 1e3)} | {_f(p['image_mse'], 1e3)} |")
    seeds = tr.get("seeds", {})
    if seeds:
        L += ["", "Training seeds (base, seed1, seed2): " + "; ".join(
            f"{k}: {', '.join(f'{v * 1e3:.3f}' for v in s['values'])} x1e-3, spread (max-min)/mean {s['spread'] * 100:.0f} %"
            for k, s in seeds.items())]
    return L + [""]
