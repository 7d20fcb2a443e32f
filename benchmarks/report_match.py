"""Does a fresh report reproduce the committed one? The largest relative difference of MSE and FLIP (64 spp) at
every distance view between a method of a new report and a method of `docs/report/results.json`.

    python benchmarks/report_match.py OUT/results.json --method N --against Nmaps   # e.g. the shipped map file run as N
"""

from __future__ import annotations

import argparse
import json
import sys


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", help="a new report's results.json")
    parser.add_argument("--method", default="Nmaps", help="its method to compare")
    parser.add_argument("--against", default="Nmaps", help="the committed report's method")
    parser.add_argument("--committed", default="docs/report/results.json")
    args = parser.parse_args()
    new, old = (json.load(open(p))["materials"] for p in (args.results, args.committed))
    for material, views in new.items():
        worst, count = 0.0, 0
        for view in (v for v in views if v.startswith("level")):
            a, b = views[view]["methods"][args.method]["64"], old[material][view]["methods"][args.against]["64"]
            for key in ("mse", "flip"):
                worst = max(worst, abs(a[key] - b[key]) / max(abs(b[key]), 1e-12))
            count += 1
        print(f"{material}: {count} distance views, largest relative difference of MSE and FLIP {worst:.2g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
