"""A lever's report against its control's, summed up: the geometric mean (and range) of the views' image MSE ratios
lever / control at 64 spp, and of their FLIP ratios, up close (1 and 4 map texels) and far (16-256), for the model
each report renders as "Nmaps" (run.sh: the lever's file).

    python experiments/level_share/ratios.py MATERIAL CONTROL_REPORT LEVER_REPORT
    python experiments/level_share/ratios.py MATERIAL REPORT      # one report: its "Nmaps" against its "N"

With `--views`, each view's MSE, FLIP, and 99th-percentile and mean luminance ratios to R, beside C's and Cmip's.
With `--method N`, two reports' "N" are compared instead of their "Nmaps" (one report: always its Nmaps against
its N).
"""

from __future__ import annotations

import argparse
import json
import math

GROUPS = {"close": ("level0", "level2"), "far": ("level4", "level6", "level8")}


def views(report: str, material: str, method: str = "Nmaps") -> dict:
    d = json.load(open(f"{report}/results.json"))["materials"][material]
    return {v: d[v]["methods"][method]["64"] for v in d if v.startswith("level")}


def geomean(values: list[float]) -> float:
    return math.exp(sum(map(math.log, values)) / len(values))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("material")
    parser.add_argument("control", help="the control's report folder (alone: its N against its Nmaps)")
    parser.add_argument("lever", nargs="?", help="the lever's report folder")
    parser.add_argument("--method", default="Nmaps", help="the method compared between two reports")
    parser.add_argument("--views", action="store_true", help="each view's figures too")
    args = parser.parse_args()
    material = args.material
    if args.lever:
        a, b = views(args.control, material, args.method), views(args.lever, material, args.method)
    else:
        a, b = views(args.control, material, "N"), views(args.control, material)
    if args.views:
        report = args.lever or args.control
        c, cmip = views(report, material, "C"), views(report, material, "Cmip")
        print(f"{'view':14s} {'control':>9s} {'lever':>9s} {'ratio':>6s} {'C':>9s} {'Cmip':>9s}   "
              "FLIP: control lever C Cmip   p99: control lever C   mean: control lever C")
        for v in a:
            print(f"{v:14s} {a[v]['mse']:9.2e} {b[v]['mse']:9.2e} {b[v]['mse'] / a[v]['mse']:6.2f} "
                  f"{c[v]['mse']:9.2e} {cmip[v]['mse']:9.2e}   {a[v]['flip']:.3f} {b[v]['flip']:.3f} "
                  f"{c[v]['flip']:.3f} {cmip[v]['flip']:.3f}   {a[v]['p99_ratio']:.2f} {b[v]['p99_ratio']:.2f} "
                  f"{c[v]['p99_ratio']:.2f}   {a[v]['mean_ratio']:.2f} {b[v]['mean_ratio']:.2f} "
                  f"{c[v]['mean_ratio']:.2f}")
    for name, levels in GROUPS.items():
        keys = [v for v in a if v.split("_")[0] in levels]
        mse = [b[v]["mse"] / a[v]["mse"] for v in keys]
        flip = [b[v]["flip"] / a[v]["flip"] for v in keys]
        print(f"{material} {name}: MSE {geomean(mse):.2f} (views {min(mse):.2f}-{max(mse):.2f}), "
              f"FLIP {geomean(flip):.2f}")

if __name__ == "__main__":
    main()
