"""What the report concludes from its numbers (pure functions of the results dictionary).

A verdict ("N beats C from 4 texels", "the offset gains 2x") is drawn per light, and the headline
verdict is the one that holds under every light: the largest footprint of the per-light ones, the
smallest gain; the lights under which a stronger claim fails are named beside it.
"""

from __future__ import annotations

import math

from .methods import COMPARED
from .views import DISTANCE_VIEWS, EXTRA_VIEWS, LIGHTS, View

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
    """Per ladder view: each method's seconds to reach N's MSE at ``spp`` (from the timed ladders),
    and the machine's load average during those renders."""
    rows = []
    for view in DISTANCE_VIEWS:
        res = material_result.get(view.name)
        if res is None or not view.ladder or main_entry(res, "N", spp) is None:
            continue
        target = main_entry(res, "N", spp)["mse"]
        floor = res["reference"]["noise_mse"]
        row = {"view": view.name, "texels": view.footprint_texels, "target_mse": target, "seconds": {}, "load": {}}
        for m, entries in res["methods"].items():
            ladder = {s: e for s, e in entries.items() if "seconds" in e}
            if not ladder:
                continue
            row["seconds"][m] = time_to_reach(ladder, target, floor if m == "R" else None)
            row["load"][m] = max(e.get("load", float("nan")) for e in ladder.values())
        rows.append(row)
    return rows


def winning_footprint(rows: list[dict], against: str, key: str = "mse") -> float | None:
    """Smallest footprint (texels) from which N's ``key`` (``mse`` at the report's spp, or ``bias``:
    the error floor that more samples do not remove) is below ``against``'s at every larger one."""
    win = None
    for row in reversed(rows):
        if row["N"] is None or row.get(against) is None:
            break
        if row["N"][key] <= row[against][key]:
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


def verdicts(headline_rows: dict[str, list[dict]]) -> dict:
    """For each classical method and key: where N beats it, per light and under every light."""
    out = {}
    for against in ("C", "Cmip"):
        for key in ("mse", "bias"):
            per_light = {light: winning_footprint(rows, against, key) for light, rows in headline_rows.items()}
            out[f"{against}_{key}"] = verdict_all_lights(per_light)
    return out


OFFSET_LEVELS = (0, 2)
"""Distance levels (1 and 4 map texels) where the offset's gain is checked, under every light."""
OFFSET_VIEWS = tuple(v.name for v in DISTANCE_VIEWS if v.level in OFFSET_LEVELS) + tuple(v.name for v in EXTRA_VIEWS[:2])
"""Views where the offset's gain is checked: the close-ups under every light and the grazing views."""
HIGHLIGHT_VIEW = "low_light"
"""The view whose highlights are checked (a light 5 degrees above the horizon)."""


def close_up_checks(material_result: dict, spp: int) -> dict:
    """What the close-ups show: the offset's gain (N0's MSE / N's) per view of :data:`OFFSET_VIEWS`,
    the smallest gain over them (the gain that holds under every light) and the views where the
    offset loses; N's mean and 99th-percentile luminance against R's under the low light."""
    gain = {}
    for view in OFFSET_VIEWS:
        res = material_result.get(view)
        n, n0 = (main_entry(res, m, spp) if res else None for m in ("N", "N0"))
        gain[view] = n0["mse"] / n["mse"] if n and n0 and n["mse"] > 0 else None
    known = {v: g for v, g in gain.items() if g is not None}
    low = material_result.get(HIGHLIGHT_VIEW)
    n = main_entry(low, "N", spp) if low else None
    return {"offset_gain": gain, "offset_gain_min": min(known.values(), default=None),
            "offset_loses": [v for v, g in known.items() if g < 1.0],
            "low_light_mean": n and n["mean_ratio"], "low_light_p99": n and n["p99_ratio"]}
