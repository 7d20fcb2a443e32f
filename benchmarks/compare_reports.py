"""Two evidence reports' image errors side by side: did a change of the models make any view worse?

Reads two `neumip report` results.json files and prints, per material and view both have, a method's
MSE (at each report's own spp) before and after, their ratio, and a count of views better / worse by
more than `--tolerance` (the same views, lights and references: run both reports with one cache).

    .venv/bin/python benchmarks/compare_reports.py OLD/results.json NEW/results.json [--method N] [--against N]

`--against` compares another method of the new report (e.g. Nmaps) with `--method` of the old one.
"""

from __future__ import annotations

import argparse
import json
import math


def view_mse(results: dict, material: str, view: str, method: str) -> float | None:
    res = results["materials"].get(material, {}).get(view)
    if not isinstance(res, dict) or "methods" not in res:
        return None
    entry = res["methods"].get(method, {}).get(str(results["config"]["spp"]))
    return None if entry is None else entry["mse"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("old")
    p.add_argument("new")
    p.add_argument("--method", default="N", help="method of the old report (default N)")
    p.add_argument("--against", help="method of the new report (default: --method)")
    p.add_argument("--tolerance", type=float, default=0.05, help="relative change counted as better/worse")
    args = p.parse_args()
    old, new = (json.load(open(path)) for path in (args.old, args.new))
    against = args.against or args.method
    better = worse = same = 0
    print(f"image MSE x1e-3: old {args.method} -> new {against} (ratio new / old)")
    for material in new["materials"]:
        ratios = []
        for view in new["materials"][material]:
            before, after = view_mse(old, material, view, args.method), view_mse(new, material, view, against)
            if before is None or after is None:
                continue
            ratio = after / before
            better += ratio < 1 - args.tolerance
            worse += ratio > 1 + args.tolerance
            same += abs(ratio - 1) <= args.tolerance
            ratios.append(ratio)
            print(f"  {material:<8} {view:<14} {before * 1e3:9.4f} -> {after * 1e3:9.4f}  ({ratio:.2f}x)")
        if ratios:
            print(f"  {material}: geometric mean {math.exp(sum(map(math.log, ratios)) / len(ratios)):.3f}, better "
                  f"{sum(r < 1 - args.tolerance for r in ratios)}, worse {sum(r > 1 + args.tolerance for r in ratios)} "
                  f"of {len(ratios)}")
    print(f"better by more than {args.tolerance:.0%}: {better}; worse: {worse}; within: {same}")


if __name__ == "__main__":
    main()
