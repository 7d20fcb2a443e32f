"""The coarse-level study's tables: each distance view's image MSE x1e-3 at 64 spp (and FLIP) of the shipped
map-informed file, the lever's runs, the paper's model from the committed report, C and Cmip.

    python experiments/coarse_levels/tables.py MATERIAL REPORT_S0 [REPORT_S1]   # run.sh's report folders
    LABEL=lf0.6 python experiments/coarse_levels/tables.py ...                  # another lever's (level_share)
    LABEL=control,energy python experiments/coarse_levels/tables.py MATERIAL REPORT_A REPORT_B   # a name each
"""

from __future__ import annotations

import json
import os
import sys


def views(path: str, material: str) -> dict:
    d = json.load(open(path))["materials"][material]
    return {v: {m: d[v]["methods"][m]["64"] for m in ("N", "Nmaps", "C", "Cmip") if m in d[v]["methods"]}
            for v in d if v.startswith("level")}


def _labels(n: int) -> list[str]:
    """The lever runs' column heads: LABEL (default res16) with the run's number, or LABEL's comma-separated names."""
    names = os.environ.get("LABEL", "res16").split(",")
    return names if len(names) == n else [f"{names[0]} s{k}" for k in range(n)]


def main() -> int:
    material, runs = sys.argv[1], sys.argv[2:]
    lever = [views(f"{r}/results.json", material) for r in runs]
    committed = f"docs/report/{material}/results.json"  # a companion report's (planks), else the main one's
    paper = views(committed if os.path.isfile(committed) else "docs/report/results.json", material)
    heads = ["paper N", "shipped"] + _labels(len(lever)) + ["C", "Cmip"]
    print(f"{material}: image MSE x1e-3 (FLIP) at 64 spp; 'shipped' and the lever's from the same report run")
    print(f"{'view':14s} " + " ".join(f"{h:>15s}" for h in heads))
    for v in lever[0]:
        cells = [paper[v]["N"], lever[0][v]["N"]] + [run[v]["Nmaps"] for run in lever] + [lever[0][v]["C"], lever[0][v]["Cmip"]]
        print(f"{v:14s} " + " ".join(f"{c['mse'] * 1e3:7.3f} ({c.get('flip', float('nan')):.3f})" for c in cells))
    return 0


if __name__ == "__main__":
    sys.exit(main())
