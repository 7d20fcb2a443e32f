"""What the report concludes from its numbers (pure functions of the results dictionary)."""

from __future__ import annotations

import math

from .views import DISTANCE_VIEWS, EXTRA_VIEWS

COMPARED = ("N", "N0", "C", "Cmip")


def main_entry(view_result: dict, method: str, spp: int) -> dict | None:
    return view_result["methods"].get(method, {}).get(spp)


def time_to_reach(entries: dict, target: float) -> float | None:
    """Seconds a ladder (spp -> {mse, seconds}) needs to reach MSE ``target``: log-log interpolation
    between the two ladder points around it; None if its last point is still above it."""
    pts = sorted((e["seconds"], e["mse"]) for e in entries.values() if "seconds" in e and "mse" in e)
    pts.sort(key=lambda p: -p[1])  # by decreasing error
    if not pts or pts[-1][1] > target:
        return None
    if pts[0][1] <= target:
        return pts[0][0]
    for (t0, e0), (t1, e1) in zip(pts, pts[1:]):
        if e1 <= target <= e0:
            if e0 == e1 or t0 <= 0 or t1 <= 0:
                return t1
            f = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(t0) + f * (math.log(t1) - math.log(t0)))
    return None


def headline(material_result: dict, spp: int) -> list[dict]:
    """Per distance view: MSE/FLIP of each method at ``spp``, R's time to reach N's error, N's time."""
    rows = []
    for view in DISTANCE_VIEWS:
        res = material_result.get(view.name)
        if res is None:
            continue
        row = {"view": view.name, "texels": view.footprint_texels, "reference_noise": res["reference"]["noise_mse"]}
        for m in COMPARED:
            e = main_entry(res, m, spp)
            row[m] = None if e is None else {k: e[k] for k in ("mse", "flip", "ssim", "mean_ratio", "seconds", "bias", "noise")}
        if row["N"] is not None:
            row["R_seconds_to_N"] = time_to_reach(res["methods"]["R"], row["N"]["mse"])
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


OFFSET_VIEWS = tuple(v.name for v in DISTANCE_VIEWS[:2]) + tuple(v.name for v in EXTRA_VIEWS[:2])
"""Views where the offset's gain is checked: close-ups (1 and 4 texels) and the grazing views."""
HIGHLIGHT_VIEW = "low_light"
"""The view whose highlights are checked (a light 5 degrees above the horizon)."""


def close_up_checks(material_result: dict, spp: int) -> dict:
    """What the close-ups show: the offset's gain (N0's MSE / N's) per view of :data:`OFFSET_VIEWS`,
    and N's mean and 99th-percentile luminance against R's under the low light."""
    gain = {}
    for view in OFFSET_VIEWS:
        res = material_result.get(view)
        n, n0 = (main_entry(res, m, spp) if res else None for m in ("N", "N0"))
        gain[view] = n0["mse"] / n["mse"] if n and n0 and n["mse"] > 0 else None
    low = material_result.get(HIGHLIGHT_VIEW)
    n = main_entry(low, "N", spp) if low else None
    return {"offset_gain": gain, "low_light_mean": n and n["mean_ratio"], "low_light_p99": n and n["p99_ratio"]}
