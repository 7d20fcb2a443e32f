"""What the report concludes from its numbers (pure functions of the results dictionary).

A verdict ("N beats C from 4 texels", "the offset gains 2x") is drawn per light, and the headline
verdict is the one that holds under every light: the largest footprint of the per-light ones, the
smallest gain; the lights under which a stronger claim fails are named beside it. Every judged neural
method (:data:`.methods.JUDGED`: N, and a second model Nmaps where its file exists) is judged by the same
functions, each where its model was rendered.
"""

from __future__ import annotations

import math

from neumip.report.methods import COMPARED, JUDGED, NO_OFFSET
from neumip.report.views import DISTANCE_VIEWS, EXTRA_VIEWS, LIGHTS, View

HEADLINE_KEYS = ("mse", "flip", "ssim", "mean_ratio", "bias", "noise")


def main_entry(view_result: dict, method: str, spp: int) -> dict | None:
    return view_result["methods"].get(method, {}).get(spp)


def time_to_reach(entries: dict, target: float, floor: float | None = None) -> float | None:
    """Seconds a ladder (spp -> {mse, seconds}) needs to reach MSE ``target``: log-log interpolation
    between the two ladder points around it. Beyond the last point: None, or, for an unbiased method
    whose error above ``floor`` (the reference's noise) falls as 1/time, that line extrapolated."""
    pts = sorted((e["seconds"], e["mse"]) for e in entries.values() if "seconds" in e and "mse" in e)
    pts.sort(key=lambda p: -p[1])  # by decreasing error
    if not pts:
        return None
    if pts[-1][1] > target:
        t, e = pts[-1]
        if floor is None or target <= floor or t <= 0:
            return None
        return t * (e - floor) / (target - floor)
    if pts[0][1] <= target:
        return pts[0][0]
    for (t0, e0), (t1, e1) in zip(pts, pts[1:]):
        if e1 <= target <= e0:
            if e0 == e1 or t0 <= 0 or t1 <= 0:
                return t1
            f = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(t0) + f * (math.log(t1) - math.log(t0)))
    return None


def _views_of(light: str) -> list[View]:
    return [v for v in DISTANCE_VIEWS if v.light == light]


def headline(material_result: dict, spp: int) -> dict[str, list[dict]]:
    """Per light, per distance view: each method's scores at ``spp``."""
    out = {}
    for light in LIGHTS:
        rows = []
        for view in _views_of(light.name):
            res = material_result.get(view.name)
            if res is None:
                continue
            row = {"view": view.name, "texels": view.footprint_texels, "reference_noise": res["reference"]["noise_mse"]}
            for m in COMPARED:
                e = main_entry(res, m, spp)
                row[m] = None if e is None else {k: e[k] for k in HEADLINE_KEYS}
            rows.append(row)
        if rows:
            out[light.name] = rows
    return out


def time_to_error(material_result: dict, spp: int) -> list[dict]:
    """Per ladder view and judged neural method X present (:data:`JUDGED`): X's MSE at ``spp`` and the
    seconds of that render, every method's seconds to reach that MSE (from the timed ladders; R
    extrapolated beyond its ladder), ``ratio`` = R's seconds to reach X's MSE / X's seconds at ``spp``
    (how much longer the real geometry needs for X's error; the issue's goal is at least 2), and the
    machine's load average during each method's renders.

    ``rungs``: the same ratio at each rung n of X's own ladder (R's seconds to reach X's n-spp MSE / X's n-spp
    seconds), and ``best_spp`` / ``best_ratio`` the rung where it is largest. A neural lookup prefilters the
    pixel's footprint, so X's error falls faster at few samples than the geometry's, and ``spp`` (where X is
    near its bias floor) is its least favourable operating point; each rung is a render a user could stop at."""
    rows = []
    for view in DISTANCE_VIEWS:
        res = material_result.get(view.name)
        if res is None or not view.ladder:
            continue
        ladders = {m: {s: e for s, e in entries.items() if "seconds" in e} for m, entries in res["methods"].items()}
        ladders = {m: ladder for m, ladder in ladders.items() if ladder}
        floor = res["reference"]["noise_mse"]
        for method in JUDGED:
            own = main_entry(res, method, spp)
            if own is None or "seconds" not in own:
                continue
            seconds = {m: time_to_reach(ladder, own["mse"], floor if m == "R" else None) for m, ladder in ladders.items()}
            r = seconds.get("R")
            rungs = {}
            for n, e in sorted(ladders.get(method, {}).items()):
                t = time_to_reach(ladders["R"], e["mse"], floor) if "R" in ladders else None
                rungs[n] = None if t is None or e["seconds"] <= 0 else t / e["seconds"]
            known = {n: x for n, x in rungs.items() if x is not None}
            best = max(known, key=known.get) if known else None
            rows.append({"view": view.name, "texels": view.footprint_texels, "method": method,
                         "target_mse": own["mse"], "own_seconds": own["seconds"], "seconds": seconds,
                         "ratio": r / own["seconds"] if r is not None and own["seconds"] > 0 else None,
                         "rungs": rungs, "best_spp": best, "best_ratio": known.get(best),
                         "load": {m: max(e.get("load", float("nan")) for e in ladder.values())
                                  for m, ladder in ladders.items()}})
    return rows


def winning_footprint(rows: list[dict], against: str, key: str = "mse", method: str = "N") -> float | None:
    """Smallest footprint (texels) from which ``method``'s ``key`` (``mse`` at the report's spp, or
    ``bias``: the error floor that more samples do not remove) is below ``against``'s at every larger one."""
    win = None
    for row in reversed(rows):
        if row.get(method) is None or row.get(against) is None:
            break
        if row[method][key] <= row[against][key]:
            win = row["texels"]
        else:
            break
    return win


def verdict_all_lights(per_light: dict[str, float | None]) -> dict:
    """The footprint from which a per-light verdict holds under every light (None: under some light,
    never), and the lights under which it does not hold from the smallest per-light footprint."""
    values = list(per_light.values())
    if not values or any(v is None for v in values):
        holds = None
    else:
        holds = max(values)
    best = min((v for v in values if v is not None), default=None)
    fails = [light for light, v in per_light.items() if v is None or best is None or v > best]
    return {"from": holds, "per_light": per_light, "fails_under": fails}


def _present(headline_rows: dict[str, list[dict]], method: str) -> bool:
    return any(row.get(method) for rows in headline_rows.values() for row in rows)


def verdicts(headline_rows: dict[str, list[dict]]) -> dict:
    """Per judged neural method present, for each classical method and key: where the neural method
    beats it, per light and under every light (``{method: {"C_mse": ..., "C_bias": ..., ...}}``)."""
    out = {}
    for method in JUDGED:
        if not _present(headline_rows, method):
            continue
        out[method] = {}
        for against in ("C", "Cmip"):
            for key in ("mse", "bias"):
                per_light = {light: winning_footprint(rows, against, key, method) for light, rows in headline_rows.items()}
                out[method][f"{against}_{key}"] = verdict_all_lights(per_light)
    return out


OFFSET_LEVELS = (0, 2)
"""Distance levels (1 and 4 map texels) of the close-up checks, under every light."""
CLOSE_UP_VIEWS = tuple(v.name for v in DISTANCE_VIEWS if v.level in OFFSET_LEVELS)
"""The close-ups under every light: where a neural method is checked against C (the issue's goal:
MSE at most half C's, FLIP below C's)."""
OFFSET_VIEWS = CLOSE_UP_VIEWS + tuple(v.name for v in EXTRA_VIEWS[:2])
"""Views where the offset's gain is checked: the close-ups under every light and the grazing views."""
HIGHLIGHT_VIEW = "low_light"
"""The view whose highlights are checked (a light 5 degrees above the horizon)."""


def close_up_checks(material_result: dict, spp: int) -> dict:
    """What the close-ups show, per judged neural method X present: ``{X: checks}`` (see :func:`close_up`)."""
    present = [m for m in JUDGED if any(main_entry(res, m, spp) for res in material_result.values())]
    return {m: close_up(material_result, spp, m) for m in present}


def close_up(material_result: dict, spp: int, method: str) -> dict:
    """The offset's gain (the method's no-offset ablation's MSE / the method's, :data:`NO_OFFSET`) per
    view of :data:`OFFSET_VIEWS`, the smallest gain over them (the gain that holds under every light)
    and the views where the offset loses; the method's MSE / C's in every close-up and the largest of
    them, and in how many close-ups its FLIP is below C's; its mean and 99th-percentile luminance
    against R's under the low light."""
    def entry(view: str, m: str) -> dict | None:
        res = material_result.get(view)
        return main_entry(res, m, spp) if res else None

    def ratio(a: dict | None, b: dict | None) -> float | None:
        return a["mse"] / b["mse"] if a and b and b["mse"] > 0 else None

    gain = {v: ratio(entry(v, NO_OFFSET[method]), entry(v, method)) for v in OFFSET_VIEWS}
    known = {v: g for v, g in gain.items() if g is not None}
    over_c = {v: ratio(entry(v, method), entry(v, "C")) for v in CLOSE_UP_VIEWS}
    flips = [(entry(v, method), entry(v, "C")) for v in CLOSE_UP_VIEWS]
    flips = [x["flip"] < c["flip"] for x, c in flips if x and c]
    low = entry(HIGHLIGHT_VIEW, method)
    return {"offset_gain": gain, "offset_gain_min": min(known.values(), default=None),
            "offset_loses": [v for v, g in known.items() if g < 1.0],
            "mse_over_c": over_c, "mse_over_c_max": max((r for r in over_c.values() if r is not None), default=None),
            "flip_below_c": [sum(flips), len(flips)],
            "low_light_mean": low and low["mean_ratio"], "low_light_p99": low and low["p99_ratio"]}
