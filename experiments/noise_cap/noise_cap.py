"""How far the report's time-to-error ratio can go at a footprint if the neural material had no bias at all, and
how far its bias must fall for the issue's 2x.

Time to error compares R's seconds to reach the method's error with the method's seconds, at the report's spp
(`report/analysis.time_to_error`). The method's error there is bias + its render noise + R's (the reference's)
noise, each measured by the report (the noise from two renders with different seeds). With the bias at 0, R
reaches the remaining noise in some seconds: that ratio is the most any model rendered at the same cost and noise
can reach ("cap"); above it only a cheaper or less noisy sample goes. The 2x goal holds if the method's error is at
most R's after twice the method's seconds; less the two noises, that is the bias it may keep ("bias for 2x").
R's error between its ladder's rungs is interpolated log-log, and beyond its last rung it falls as 1 / time above
the reference's noise, as the report does. Read from a report's results.json (the side light's ladder views).

    .venv/bin/python experiments/noise_cap/noise_cap.py docs/report/results.json [--method Nmaps] [--view level0_side]
"""

from __future__ import annotations

import argparse
import json
import math

from neumip.report.analysis import time_to_reach

GOAL_RATIO = 2.0


def error_at(ladder: dict, seconds: float, floor: float) -> float:
    """The MSE a timed ladder (spp -> {mse, seconds}) reaches after ``seconds`` (the inverse of `time_to_reach`)."""
    pts = sorted((e["seconds"], e["mse"]) for e in ladder.values() if e.get("seconds", 0) > 0)
    if seconds <= pts[0][0]:
        return pts[0][1]
    for (t0, e0), (t1, e1) in zip(pts, pts[1:]):
        if t0 <= seconds <= t1:
            f = (math.log(seconds) - math.log(t0)) / (math.log(t1) - math.log(t0))
            return math.exp(math.log(e0) + f * (math.log(e1) - math.log(e0)))
    t, e = pts[-1]
    return floor + (e - floor) * t / seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results")
    parser.add_argument("--method", default="N")
    parser.add_argument("--view", default="level0_side", help="a ladder view (the side light's)")
    args = parser.parse_args()
    results = json.loads(open(args.results).read())
    spp = str(results["config"]["spp"])
    print(f"{args.view}, {args.method} at {spp} spp; MSE x1e-3")
    print(f"{'material':10s} {'noise / R':>9s} {'s / R':>6s} {'ratio':>6s} {'cap':>6s} {'bias':>7s} "
          f"{'bias for 2x':>11s} {'to fall':>8s}")
    for name, views in results["materials"].items():
        view = views.get(args.view)
        if not view or args.method not in view["methods"] or "R" not in view["methods"]:
            continue
        own, ladder = view["methods"][args.method][spp], view["methods"]["R"]
        floor = view["reference"]["noise_mse"]
        cap = time_to_reach(ladder, own["noise"] + own["reference_noise"], floor)
        ratio = time_to_reach(ladder, own["mse"], floor)
        allowed = error_at(ladder, GOAL_RATIO * own["seconds"], floor) - own["noise"] - own["reference_noise"]
        fall = f"{own['bias'] / allowed:7.1f}x" if allowed > 0 else "   never"
        print(f"{name:10s} {own['noise'] / ladder[spp]['noise']:9.3f} {own['seconds'] / ladder[spp]['seconds']:6.3f} "
              f"{ratio / own['seconds']:6.2f} {cap / own['seconds']:6.2f} {own['bias'] * 1e3:7.4f} "
              f"{max(allowed, 0.0) * 1e3:11.4f} {fall:>8s}")


if __name__ == "__main__":
    main()
