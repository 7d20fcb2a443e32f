"""A lever's report against its control's, summed up: the geometric mean (and range) of the views' image MSE ratios
lever / control at 64 spp, and of their FLIP ratios, up close (1 and 4 map texels) and far (16-256), for the model
each report renders as "Nmaps" (run.sh: the lever's file).

    python experiments/level_share/ratios.py MATERIAL CONTROL_REPORT LEVER_REPORT
"""

from __future__ import annotations

import json
import math
import sys

GROUPS = {"close": ("level0", "level2"), "far": ("level4", "level6", "level8")}


def views(report: str, material: str) -> dict:
    d = json.load(open(f"{report}/results.json"))["materials"][material]
    return {v: d[v]["methods"]["Nmaps"]["64"] for v in d if v.startswith("level")}


def geomean(values: list[float]) -> float:
    return math.exp(sum(map(math.log, values)) / len(values))


def main() -> None:
    material, control, lever = sys.argv[1:4]
    a, b = views(control, material), views(lever, material)
    for name, levels in GROUPS.items():
        keys = [v for v in a if v.split("_")[0] in levels]
        mse = [b[v]["mse"] / a[v]["mse"] for v in keys]
        flip = [b[v]["flip"] / a[v]["flip"] for v in keys]
        print(f"{material} {name}: MSE {geomean(mse):.2f} (views {min(mse):.2f}-{max(mse):.2f}), FLIP {geomean(flip):.2f}")


if __name__ == "__main__":
    main()
