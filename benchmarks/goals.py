"""Issue 25's goals, read from one or more report results.json files: one row per material and judged method.

Columns (every figure is the report's own, `report/analysis.py`):
- close-ups: the largest image MSE over C's in the six close-ups (1 and 4 map texels, three lights; goal <= 0.5),
  and in how many of them the method's FLIP is below C's;
- noise / C: in the close-up where MSE / C is largest, the method's and R's render noise over C's MSE (what a model
  without bias would still score there); bias / C: the largest of the method's bias over C's in the close-ups;
- parallax: the least MSE gain of the parallax stages (X0's MSE over X's) at 1 and 4 texels, every light (goal >= 2;
  the report's own minimum also takes the grazing views);
- low light: mean and 99th-percentile luminance over R's under the light 5 degrees above the horizon (goal 0.9-1.1);
- time to error: R's seconds to reach the method's error over the method's seconds, the least over the side light's
  footprints at 1 spp, and at 1 texel at the report's spp (goal >= 2 at every footprint).

    .venv/bin/python benchmarks/goals.py docs/report/results.json docs/report/planks/results.json
"""

from __future__ import annotations

import argparse
import json

JUDGED = ("N", "Nmaps")
NAN = float("nan")


def rows(results: dict):
    spp = str(results["config"]["spp"])
    for material, views in results["materials"].items():
        close_up = views.get("close_up", {})
        for method in JUDGED:
            checks = close_up.get(method)
            if not checks or not checks.get("mse_over_c"):
                continue
            worst = max(checks["mse_over_c"], key=checks["mse_over_c"].get)
            scores = views[worst]["methods"]
            c, own = scores["C"][spp], scores[method][spp]
            noise = (own["noise"] + own["reference_noise"]) / c["mse"]
            biases = [views[v]["methods"][method][spp]["bias"] / views[v]["methods"]["C"][spp]["bias"]
                      for v in checks["mse_over_c"] if views[v]["methods"]["C"][spp]["bias"] > 0]
            bias = max(biases, default=NAN)
            gains = [g for v, g in (checks.get("offset_gain") or {}).items() if v.startswith("level") and g is not None]
            ladder = [t for t in views.get("time_to_error", []) if t["method"] == method]
            at_one_spp = min((t["rungs"]["1"] for t in ladder if "1" in t["rungs"]), default=NAN)
            at_one_texel = next((t["ratio"] for t in ladder if t["texels"] == 1.0), NAN)
            figures = (checks["mse_over_c_max"], noise, bias, min(gains, default=None),
                       checks.get("low_light_mean"), checks.get("low_light_p99"), at_one_spp, at_one_texel)
            yield material, method, worst, checks["flip_below_c"], [NAN if x is None else x for x in figures]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", nargs="+")
    args = parser.parse_args()
    print(f"{'material':10s} {'method':6s} {'MSE/C max':>9s} {'(view)':14s} {'FLIP<C':>6s} {'noise/C':>7s} "
          f"{'bias/C':>6s} {'parallax':>8s} {'low mean':>8s} {'low p99':>7s} {'TTE 1spp':>8s} {'TTE 1tx':>7s}")
    for path in args.results:
        with open(path) as f:
            results = json.load(f)
        for material, method, worst, flip, figures in rows(results):
            mse_c, noise, bias, gain, mean, p99, tte1, tte_texel = figures
            print(f"{material:10s} {method:6s} {mse_c:9.2f} {worst:14s} {flip[0]:>2d} / {flip[1]:<1d} {noise:7.2f} "
                  f"{bias:6.2f} {gain:8.2f} {mean:8.2f} {p99:7.2f} {tte1:8.2f} {tte_texel:7.2f}")


if __name__ == "__main__":
    main()
