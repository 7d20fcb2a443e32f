"""How far the report's time-to-error ratio can go at a footprint if the neural material had no bias at all.

Time to error compares R's seconds to reach N's error with N's seconds (`training/report/analysis.time_to_error`).
With no bias, both errors are noise alone, falling as 1 / spp: R reaches N's error in (R's 1-spp MSE / N's 1-spp
MSE) x (R's seconds per spp / N's seconds per spp) of N's time. That product is the most the ratio can reach by
removing N's bias; above it only a cheaper or less noisy sample goes. Read from a report's results.json (the side
light's ladder views: 1-spp MSE of each method and the fitted seconds per spp).

    .venv/bin/python benchmarks/noise_cap.py docs/report/results.json [--method N] [--view level0_side]
"""

from __future__ import annotations

import argparse
import json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results")
    parser.add_argument("--method", default="N")
    parser.add_argument("--view", default="level0_side", help="a ladder view (the side light's)")
    args = parser.parse_args()
    materials = json.loads(open(args.results).read())["materials"]
    print(f"{'material':10s} {'N 1-spp MSE / R':>16s} {'N s per spp / R':>16s} {'cap of R s / N s':>17s}   ({args.view}, {args.method})")
    for name, views in materials.items():
        view = views.get(args.view)
        if not view or args.method not in view.get("fits", {}) or "R" not in view.get("fits", {}):
            continue
        noise = view["methods"][args.method]["1"]["mse"] / view["methods"]["R"]["1"]["mse"]
        cost = view["fits"][args.method]["seconds_per_spp"] / view["fits"]["R"]["seconds_per_spp"]
        print(f"{name:10s} {noise:16.3f} {cost:16.3f} {1 / (noise * cost):17.2f}")


if __name__ == "__main__":
    main()
