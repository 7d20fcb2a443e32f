"""The seed pairs of seed_judge_results.txt: does the judge order each pair of runs of a material as the truth does, and
what does the run it picks score against the pair's mean (beside the close-up error: the metric `fit --seeds` judges by)?
A pick's figure is its truth (or views' error) over the pair's arithmetic mean; printed is the geometric mean of those
ratios over the pairs, and their range.

    .venv/bin/python experiments/verdict_noise/seed_judge_pairs.py experiments/verdict_noise/seed_judge_results.txt

The runs compared are each material's three seeds (turtle's: runs/rs/ctl, runs/cd/ctl1, runs/sj/turtle_s2).
"""

from __future__ import annotations

import itertools
import math
import re
import sys

SEEDS = {"turtle": ["runs/rs/ctl", "runs/cd/ctl1", "runs/sj/turtle_s2"]}
LINE = re.compile(r"\s+(\S+)\s+judge rms ([\d.]+).*truth rms ([\d.]+).*near log MSE ([\d.]+)e-3"
                  r"\s+views \|model/tracer - 1\| mean ([\d.]+)")


def main() -> int:
    rows: dict[str, dict[str, tuple[float, ...]]] = {}
    for block in open(sys.argv[1]).read().split("\n## ")[1:]:
        lines = block.split("\n")
        if "--no-table" in lines[0]:
            continue
        material = lines[1].split(":")[0]
        for line in lines[2:]:
            if m := LINE.match(line):
                rows.setdefault(material, {})[m.group(1)] = tuple(map(float, m.groups()[1:]))
    judge_truth = near_truth = ties = pairs = 0
    picked: dict[str, list[float]] = {"judge truth": [], "judge views": [], "near truth": [], "near views": []}
    for material, runs in rows.items():
        names = SEEDS.get(material, [f"runs/sj/{material}_s{s}" for s in range(3)])
        for a, b in itertools.combinations([runs[n] for n in names], 2):  # (judge, truth, near, views)
            pairs += 1
            judge_truth += a[0] != b[0] and (a[0] < b[0]) == (a[1] < b[1])
            near_truth += a[2] != b[2] and (a[2] < b[2]) == (a[1] < b[1])
            ties += (a[2] == b[2]) + (a[0] == b[0])
            for by, k in (("judge", 0), ("near", 2)):  # a tie (at the printed digits) picks neither: the pair's mean
                for what, j in (("truth", 1), ("views", 3)):
                    mean = (a[j] + b[j]) / 2
                    pick = mean if a[k] == b[k] else (a if a[k] < b[k] else b)[j]
                    picked[f"{by} {what}"].append(pick / mean)
    print(f"{pairs} pairs of seeds: the judge orders {judge_truth} as the truth does, the close-up error {near_truth} "
          f"({ties} tied at the printed digits, counted as neither)")
    for key, values in picked.items():
        mean = math.exp(sum(map(math.log, values)) / len(values))
        print(f"  picked by {key.split()[0]}: its {key.split()[1]} {mean:.3f}x the pair's mean "
              f"(geometric mean; {min(values):.3f}-{max(values):.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
