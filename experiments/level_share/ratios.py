"""A lever's report against its control's, summed up: the geometric mean (and range) of the views' image MSE ratios
lever / control at 64 spp, and of their FLIP ratios, up close (1 and 4 map texels) and far (16-256), for the model
each report renders as "Nmaps" (run.sh: the lever's file).

    python experiments/level_share/ratios.py MATERIAL CONTROL_REPORT LEVER_REPORT
    python experiments/level_share/ratios.py MATERIAL REPORT      # one report: its "Nmaps" against its "N"

With `--views`, each view's MSE, FLIP and 99th-percentile luminance ratio to R, beside C's and Cmip's. With
`--method N`, two reports' "N" are compared instead of their "Nmaps".
"""

from __future__ import annotations

import json
import math
import sys

GROUPS = {"close": ("level0", "level2"), "far": ("level4", "level6", "level8")}


def views(report: str, material: str, method: str = "Nmaps") -> dict:
    d = json.load(open(f"{report}/results.json"))["materials"][material]
    return {v: d[v]["methods"][method]["64"] for v in d if v.startswith("level")}


def geomean(values: list[float]) -> float:
    return math.exp(sum(map(math.log, values)) / len(values))


def main() -> None:
    method = sys.argv[sys.argv.index("--method") + 1] if "--method" in sys.argv else "Nmaps"
    args = [a for i, a in enumerate(sys.argv[1:], 1) if a not in ("--views", "--method") and sys.argv[i - 1] != "--method"]
    material, control, lever = (args + [None])[:3]
    a, b = (views(control, material, method), views(lever, material, method)) if lever else (
        views(control, material, "N"), views(control, material))
    if "--views" in sys.argv:
        c, cmip = views(lever or control, material, "C"), views(lever or control, material, "Cmip")
        print(f"{'view':14s} {'control':>9s} {'lever':>9s} {'ratio':>6s} {'C':>9s} {'Cmip':>9s}   FLIP: control lever C Cmip"
              "   p99: control lever C")
        for v in a:
            print(f"{v:14s} {a[v]['mse']:9.2e} {b[v]['mse']:9.2e} {b[v]['mse'] / a[v]['mse']:6.2f} {c[v]['mse']:9.2e} "
                  f"{cmip[v]['mse']:9.2e}   {a[v]['flip']:.3f} {b[v]['flip']:.3f} {c[v]['flip']:.3f} {cmip[v]['flip']:.3f}"
                  f"   {a[v]['p99_ratio']:.2f} {b[v]['p99_ratio']:.2f} {c[v]['p99_ratio']:.2f}")
    for name, levels in GROUPS.items():
        keys = [v for v in a if v.split("_")[0] in levels]
        mse = [b[v]["mse"] / a[v]["mse"] for v in keys]
        flip = [b[v]["flip"] / a[v]["flip"] for v in keys]
        print(f"{material} {name}: MSE {geomean(mse):.2f} (views {min(mse):.2f}-{max(mse):.2f}), FLIP {geomean(flip):.2f}")


if __name__ == "__main__":
    main()
