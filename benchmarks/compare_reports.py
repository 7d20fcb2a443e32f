"""Two evidence reports' image errors side by side: did a change of the models make any view worse?

Reads two `neumip report` results.json files and prints, per material and view both have, a method's
MSE (at each report's own spp) before and after, their ratio, and a count of views better / worse by
more than `--tolerance` (the same views, lights and references: run both reports with one cache).

    .venv/bin/python benchmarks/compare_reports.py OLD/results.json NEW/results.json [--method N] [--against N]

`--against` compares another method of the new report (e.g. Nmaps) with `--method` of the old one.
`--columns old:N old:Nmaps new:N new:C new:Cmip` prints instead each named method's MSE and FLIP, per material,
light and footprint (the views `levelK_LIGHT`: 2^K map texels a pixel), and where the new report's `--method` has a
larger MSE or FLIP than another of the new report's columns.
"""

from __future__ import annotations

import argparse
import json
import math


def view_entry(results: dict, material: str, view: str, method: str) -> dict | None:
    """A method's metrics in a view at the report's own spp (None where the report lacks them)."""
    res = results["materials"].get(material, {}).get(view)
    if not isinstance(res, dict) or "methods" not in res:
        return None
    return res["methods"].get(method, {}).get(str(results["config"]["spp"]))


def view_mse(results: dict, material: str, view: str, method: str) -> float | None:
    entry = view_entry(results, material, view, method)
    return None if entry is None else entry["mse"]


def print_columns(reports: dict[str, dict], columns: list[str], judged: str) -> None:
    """MSE x1e-3 / FLIP of each `report:method` column, per material, light and footprint; and the new report's
    methods with a lower MSE or FLIP than its `judged` method, and how many views have any."""
    cells = [column.split(":", 1) for column in columns]
    print("MSE x1e-3 / FLIP at each report's spp; columns: " + ", ".join(columns))
    new = reports["new"]
    rivals = [method for which, method in cells if which == "new" and method != judged]
    losing = 0
    for material, views in new["materials"].items():
        levels = {}  # light -> {level: view}, from the view names levelK_LIGHT
        for view in views:
            level, _, light = view.removeprefix("level").partition("_")
            if view.startswith("level") and light and level.isdigit():
                levels.setdefault(light, {})[int(level)] = view
        for light, by_level in levels.items():
            for level, view in sorted(by_level.items()):
                texels = 2 ** level
                row = []
                for which, method in cells:
                    entry = view_entry(reports[which], material, view, method)
                    row.append("-" if entry is None else f"{entry['mse'] * 1e3:.4f} / {entry['flip']:.3f}")
                mine = view_entry(new, material, view, judged)
                lost = [] if mine is None else [
                    f"{method} {metric}" for method in rivals for metric in ("mse", "flip")
                    if (entry := view_entry(new, material, view, method)) is not None and entry[metric] < mine[metric]]
                losing += bool(lost)
                print(f"  {material:<8} {light:<6} {texels:>4} | " + " | ".join(row)
                      + (f"   {judged} above: {', '.join(lost)}" if lost else ""))
    if rivals:
        print(f"views where new {judged} has a larger MSE or FLIP than new {', '.join(rivals)}: {losing}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("old")
    p.add_argument("new")
    p.add_argument("--method", default="N", help="method of the old report (default N)")
    p.add_argument("--against", help="method of the new report (default: --method)")
    p.add_argument("--tolerance", type=float, default=0.05, help="relative change counted as better/worse")
    p.add_argument("--columns", nargs="+", metavar="REPORT:METHOD", help="old:M or new:M; print MSE and FLIP instead")
    args = p.parse_args()
    old, new = (json.load(open(path)) for path in (args.old, args.new))
    against = args.against or args.method
    if args.columns:
        bad = [c for c in args.columns if c.split(":", 1)[0] not in ("old", "new") or ":" not in c]
        if bad:
            p.error(f"--columns takes old:METHOD or new:METHOD, not {' '.join(bad)}")
        print_columns({"old": old, "new": new}, args.columns, against)
        return
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
