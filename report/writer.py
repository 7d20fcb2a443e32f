"""report.md: the tables and figures of one run, every number read from its results."""

from __future__ import annotations

import math
from pathlib import Path

from neumip.core.contract import sample_footprint

from neumip.report.analysis import CLOSE_UP_VIEWS, OFFSET_VIEWS
from neumip.report.config import ReportConfig
from neumip.report.methods import COMPARED, MAX_DEPTH, NO_OFFSET
from neumip.report.views import DISTANCE_VIEWS, LADDER_LIGHT, LEVELS, LIGHTS, VIEWS


def _f(x, scale: float = 1.0, digits: int = 3) -> str:
    return "-" if x is None else f"{x * scale:.{digits}f}"


def headline_table(results: dict, light: str) -> list[str]:
    """Per material and distance under one light: image MSE x1e-3 / FLIP of every judged neural method
    present and of the classical methods, side by side (the ablations are in the per-material tables)."""
    methods = _methods(results, HEADLINE_METHODS)
    lines = ["| material | footprint (map texels) | " + " | ".join(methods) + " | R noise |",
             "|---|---|" + "---|" * (len(methods) + 1)]
    for name, mat in results["materials"].items():
        for row in mat.get("headline", {}).get(light, []):
            cells = [f"{_f(row[m]['mse'], 1e3)} / {_f(row[m]['flip'])}" if row.get(m) else "-" for m in methods]
            lines.append(f"| {name} | {row['texels']:g} | " + " | ".join(cells) + f" | {_f(row['reference_noise'], 1e3)} |")
    return lines


HEADLINE_METHODS = tuple(m for m in COMPARED if m not in NO_OFFSET.values())
"""The methods of the headline tables: the judged neural methods and the classical ones."""


def _methods(results: dict, among: tuple[str, ...] = COMPARED) -> list[str]:
    """The methods of ``among`` present in any material (a method without its model is left out)."""
    present = set()
    for mat in results["materials"].values():
        for rows in mat.get("headline", {}).values():
            present |= {m for row in rows for m in among if row.get(m)}
    return [m for m in among if m in present]


def _footprint(x) -> str:
    return "never" if x is None else f"{x:g}"


def winners(results: dict) -> list[str]:
    """Per material and judged neural method: from which footprint it beats C and Cmip, under every
    light (bold) and under each."""
    lines = ["| material | method | beats C: MSE at equal spp | C: bias (floor) | beats Cmip: MSE | Cmip: bias |",
             "|---|---|---|---|---|---|"]
    for name, mat in results["materials"].items():
        for method, v in mat.get("verdicts", {}).items():
            cells = []
            for key in ("C_mse", "C_bias", "Cmip_mse", "Cmip_bias"):
                d = v[key]
                per = ", ".join(f"{light} {_footprint(x)}" for light, x in d["per_light"].items())
                cells.append(f"**{_footprint(d['from'])}** ({per})")
            lines.append(f"| {name} | {method} | " + " | ".join(cells) + " |")
    return lines


def close_up_table(results: dict) -> list[str]:
    """Per material and judged neural method X: the offset's gain (X's ablation's MSE / X's) per view and
    its minimum; X's largest MSE / C's in the close-ups and its FLIP wins over C there; X's low-light
    mean and p99 / R's."""
    lines = ["| material | method | " + " | ".join(f"offset gain, {v}" for v in OFFSET_VIEWS)
             + " | smallest gain | close-ups: largest MSE / C's | close-ups: FLIP below C's | low light: mean / R "
             "| low light: p99 / R |", "|---|---|" + "---|" * (len(OFFSET_VIEWS) + 5)]
    for name, mat in results["materials"].items():
        for method, checks in mat.get("close_up", {}).items():
            won, total = checks["flip_below_c"]
            cells = [_f(checks["offset_gain"].get(v), 1, 2) for v in OFFSET_VIEWS]
            cells += [f"**{_f(checks['offset_gain_min'], 1, 2)}**", f"**{_f(checks['mse_over_c_max'], 1, 2)}**",
                      f"{won} of {total}", _f(checks["low_light_mean"], 1, 2), _f(checks["low_light_p99"], 1, 2)]
            lines.append(f"| {name} | {method} | " + " | ".join(cells) + " |")
    return lines


TIME_GOAL = 2.0
"""Issue 25's goal: the real geometry needs at least this many times the neural method's time to reach its error."""


def time_table(results: dict) -> list[str]:
    """Per material, ladder footprint and judged neural method X: X's MSE and seconds at the report's
    spp, R's (and C's, Cmip's) seconds to reach that MSE, the ratio R / X, and the load average."""
    ladder = sorted({int(n) for mat in results["materials"].values() for row in mat.get("time_to_error", [])
                     for n in row.get("rungs", {})})
    lines = ["| material | footprint (map texels) | method X | X's image MSE x1e-3 | X's s | R's s to X's MSE | "
             "**R's s / X's s** | C's s to X's MSE | Cmip's s to X's MSE | "
             f"R's s / X's s at X's {' / '.join(map(str, ladder))}-spp error | load average |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, mat in results["materials"].items():
        for row in mat.get("time_to_error", []):
            loads = [x for x in row["load"].values() if x == x]
            load = f"{min(loads):.1f}-{max(loads):.1f}" if loads else "-"
            secs = row["seconds"]
            rungs = {int(n): x for n, x in row.get("rungs", {}).items()}
            lines.append(f"| {name} | {row['texels']:g} | {row['method']} | {_f(row['target_mse'], 1e3)} | "
                         f"{_f(row['own_seconds'], 1, 2)} | {_f(secs.get('R'), 1, 2)} | **{_f(row['ratio'], 1, 2)}** | "
                         f"{_f(secs.get('C'), 1, 2)} | {_f(secs.get('Cmip'), 1, 2)} | "
                         f"{' / '.join(_f(rungs.get(n), 1, 2) for n in ladder)} | {load} |")
    return lines


def view_table(name: str, mat: dict, spp: int) -> list[str]:
    lines = ["| view | film | method | image MSE x1e-3 | FLIP | SSIM | mean / R | p99 / R | bias x1e-3 | noise x1e-3 |",
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
         "- **N** / **N0**: the neural material `MODELS/NAME.onnx` (the shipped ones are what `neumip fit` makes: for a "
         "material defined by maps the `maps` recipe, latent textures encoded from its prefiltered maps on the classical "
         "base, with the relief stage; the paper's model for one without) and the same trained without the parallax stages "
         "(neither the relief nor the neural offset, `neumip fit --no-offset --relief 0`) `NAME_nooffset.onnx`; "
         "**Nmaps** / **Nmaps0**: a second model judged beside N, `NAME_maps.onnx`, and its ablation "
         "`NAME_maps_nooffset.onnx`; each where its file exists, `neumip_path`. "
         "N and Nmaps are judged alike (verdicts, time to error, close-ups); N0 and Nmaps0 give the parallax stages' gain (the offset gain). "
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
         "rendered, released); the fastest round's seconds, with the 1-minute load average. R's time beyond its 64-spp rung is "
         "extrapolated (unbiased: its error above R's noise falls as 1/time).", ""]
    L += ["## Summary", "", "What holds under every light (read from the tables below):", ""]
    L += summary(results, cfg) + [""]
    L += ["## Headline", "", f"Image MSE x1e-3 / FLIP at {cfg.spp} spp, one table per light (image MSE: per pixel "
          "against R; not the query MSE of a fit's table: report/README.md#two-errors).", ""]
    for light in LIGHTS:
        L += [f"### Light: {light.name} (zenith {light.zenith:g}, azimuth {light.azimuth:g})", ""]
        L += headline_table(results, light.name) + [""]
    L += ["Footprint (map texels) from which each neural method is better than the classical material at every "
          f"larger footprint, by MSE at {cfg.spp} spp (what a render at equal samples shows) and by bias (the error "
          "floor left after the noise is averaged away). **Bold: the verdict under every light** (the largest of the "
          "per-light footprints; `never` where under some light the method never wins from the largest footprint "
          "down); in brackets, each light's own.", ""]
    L += winners(results) + [""]
    fails = _failing_lights(results)
    if fails:
        L += ["Where a stronger verdict fails: " + "; ".join(fails) + ".", ""]
    L += [f"Close-ups, per neural method X at {cfg.spp} spp: the offset gain, what the parallax stages (the relief where "
          "X has one, and the neural offset) buy (X0's MSE / X's: N0 / N, Nmaps0 / Nmaps; above 1: they help) at 1 and 4 map texels under every light and at the grazing views, **the "
          "smallest gain being the one that holds everywhere**; X's largest MSE / C's over the close-ups at 1 and 4 "
          f"map texels under every light ({len(CLOSE_UP_VIEWS)} views; the goal: at most 0.5) and in how many of them "
          "X's FLIP is below C's; whether X's highlights survive a light 5 degrees above the horizon (its mean and "
          "99th-percentile luminance / R's; the goal: within 10 %):", ""]
    L += close_up_table(results) + [""]
    if cfg.smoke:
        L += ["No timing verdicts: a smoke run's timings mean nothing.", ""]
    else:
        L += [f"Time to error ({LADDER_LIGHT} light), per neural method X: X's MSE and seconds at {cfg.spp} spp, the "
              "seconds R (the real geometry), C and Cmip need to reach that MSE (from their timed ladders, log-log "
              "interpolation between rungs; `-`: the error never gets there, a bias floor; R beyond its ladder "
              f"extrapolated), and **R's seconds / X's seconds** (the goal: at least {TIME_GOAL:g} at every "
              "footprint), with the machine's 1-minute load average over those renders. The same ratio at each rung "
              "of X's own ladder follows: a neural lookup prefilters the pixel's footprint, so X's error falls faster "
              f"at few samples than the geometry's, and at {cfg.spp} spp X is near its bias floor, its least "
              "favourable operating point.", ""]
        L += time_table(results) + [""]
    for note in results.get("notes", []):
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
    """Per material, neural method and verdict: the best per-light footprint and the lights under which it fails."""
    out = []
    for name, mat in results["materials"].items():
        for method, v in mat.get("verdicts", {}).items():
            for key, d in v.items():
                known = [x for x in d["per_light"].values() if x is not None]
                if d["fails_under"] and known:
                    against, what = key.split("_")
                    out.append(f"{name}, {method} beats {against} by {what} from {min(known):g} texels: "
                               f"not under {', '.join(d['fails_under'])}")
    return out


def summary(results: dict, config: ReportConfig) -> list[str]:
    """One line per material and neural method: the verdicts that hold under every light (and the lights
    that break stronger ones), the close-ups against C, the offset's gain, the highlights and the time to error."""
    lines = []
    for name, mat in results["materials"].items():
        for method, v in mat.get("verdicts", {}).items():
            checks = mat.get("close_up", {}).get(method, {})
            times = [r for r in mat.get("time_to_error", []) if r["method"] == method]
            lines.append(f"- **{name}, {method}**: " + "; ".join(_summary_parts(method, v, checks, times, config)) + ".")
    return lines


def _summary_parts(method: str, v: dict, checks: dict, times: list[dict], config: ReportConfig) -> list[str]:
    parts = []
    for against in ("C", "Cmip"):
        d = v[f"{against}_mse"]
        where = "never under every light" if d["from"] is None else f"from {d['from']:g} map texels under every light"
        fails = f" (fails under {', '.join(d['fails_under'])} from a smaller footprint)" if d["fails_under"] else ""
        parts.append(f"beats {against} by MSE at {config.spp} spp {where}{fails}")
    if checks.get("mse_over_c_max") is not None:
        won, total = checks["flip_below_c"]
        parts.append(f"at 1-4 texels its MSE is at most {checks['mse_over_c_max']:.2f}x C's, its FLIP below C's in "
                     f"{won} of {total} views")
    if checks.get("offset_gain_min") is not None:
        loses = checks["offset_loses"]
        parts.append(f"the offset's gain is at least {checks['offset_gain_min']:.2f}x in its close-up views"
                     + (f" (the offset loses in {', '.join(loses)})" if loses else ""))
    if checks.get("low_light_mean") is not None:
        parts.append(f"low light: mean {checks['low_light_mean']:.2f}, p99 {checks['low_light_p99']:.2f} of R's")
    known = [r for r in times if r["ratio"] is not None]
    if known:
        worst = min(known, key=lambda r: r["ratio"])
        parts.append(f"the real geometry needs {worst['ratio']:.2f}x its time to reach its {config.spp}-spp error at "
                     f"{worst['texels']:g} texels (the smallest ratio over the footprints)")
    best = [r for r in times if r.get("best_ratio") is not None]
    if best:
        worst = min(best, key=lambda r: r["best_ratio"])
        parts.append(f"at its most favourable rung, at least {worst['best_ratio']:.2f}x at every footprint (the "
                     f"least at {worst['texels']:g} texels, at {worst['best_spp']} spp)")
    return parts


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


def _stage(p: dict) -> str:
    """The map-informed stages of a trade-off point ('-': the paper's model)."""
    maps = p.get("maps")
    stages = [f"relief, {p['relief']} steps"] if p.get("relief") else []
    stages += ["map encoder" + (f" + {maps['horizons']} horizons" if maps.get("horizons") else "")] if maps else []
    stages += ["classical base"] if p.get("classical") else []
    return " + ".join(stages) or "-"


def _image_view(tr: dict) -> str:
    return next((p["image_view"] for p in tr["points"].values() if p.get("image_view")), "one")


def tradeoff_section(results: dict) -> list[str]:
    tr = results.get("tradeoff")
    if not tr:
        return []
    L = ["## The model's own trade-off", "",
         f"Configurations trained on {tr['material']} with {tr['steps']} steps of {tr['batch']} queries (a short "
         "schedule, the same for all: they compare with one another, not with the shipped models, and the larger "
         "pyramids are the least converged after it). What each stage costs: at training, wall seconds on one "
         "torch thread (set-up and training; in brackets the set-up alone, which opens the data and prefilters a "
         "map-informed model's maps, and the 1-minute load average at its end: the machine is shared; the first "
         "configuration trained in a process also pays torch's first use), and at render, queries per second in-process (ONNX "
         "Runtime, median of interleaved rounds; a map-informed model is exported as the paper's graph with its "
         "textures baked, measured like the others; base, seed1, seed2, maps and maps_hz are graphs of one size, so the "
         "spread of their queries per second is this measurement's noise; the relief and the classical base add stages to the graph). What it buys: validation MSE on low-noise (64 spp) reference "
         f"queries, and image MSE in the {_image_view(tr)} view against R.", "",
         "![trade-off](tradeoff.png)", "",
         "| configuration | resolution | channels | MLP width | offset | maps | seed | training s (set-up s; load) | M queries/s "
         "| query MSE x1e-3 (held out) | image MSE x1e-3 |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, p in tr["points"].items():
        training = _f(p.get("training_seconds"), 1, 1)
        if p.get("training_load") is not None:
            training += f" ({_f(p.get('setup_seconds'), 1, 1)}; {p['training_load']:.1f})"
        L.append(f"| {name} | {p['resolution']} | {p['channels']} | {p['hidden']} | {p['offset']} | {_stage(p)} | "
                 f"{p['seed']} | {training} | {p['queries_per_second'] / 1e6:.2f} | {_f(p['validation_mse'], 1e3)} | "
                 f"{_f(p['image_mse'], 1e3)} |")
    if tr.get("note"):
        L += ["", tr["note"] + "."]
    seeds = tr.get("seeds", {})
    if seeds:
        L += ["", "Training seeds (base, seed1, seed2): " + "; ".join(
            f"{k}: {', '.join(f'{v * 1e3:.3f}' for v in s['values'])} x1e-3, spread (max-min)/mean {s['spread'] * 100:.0f} %"
            for k, s in seeds.items())]
    return L + [""]
