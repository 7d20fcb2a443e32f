"""`neumip calibrate` with another fit rule: one of table_noise.py's RULES (shrink, window, balanced), or ratio (the
product's `fit_energy`).

    .venv/bin/python experiments/energy/calibrate_rule.py RULE MODEL DATA OUT [--seed S]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("rule")
    parser.add_argument("model")
    parser.add_argument("data")
    parser.add_argument("out")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    import table_noise

    from neumip.training.loop import calibrate, energy
    from neumip.training.model.energy import fit_energy

    rule = table_noise.RULES.get(args.rule, fit_energy)
    energy.fit_energy = lambda config, queries, answers, targets: rule(config, queries, answers, targets)
    validation = calibrate.calibrate_file(args.model, args.data, args.out, seed=args.seed)
    print(f"wrote {args.out} ({args.rule}): held-out MSE {validation['overall']['mse']:.4g}")


if __name__ == "__main__":
    main()
