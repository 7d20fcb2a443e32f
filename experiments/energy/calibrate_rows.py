"""`neumip calibrate` with more of the data set's rows than the product reads (`loop.energy.ENERGY_QUERIES`, 4 M),
and optionally other bins: does a quieter energy table move the far views?

    .venv/bin/python experiments/energy/calibrate_rows.py MODEL DATA OUT [--rows N] [--bins B]

DATA is a data set of the model's material made apart from its training data (here `neumip generate M --coarse-spp
64 --seed 7`: footprints of 8 texels and wider traced with 64 samples instead of 16). The file at OUT is then
reported as its control was (`neumip report --materials M --models DIR --skip stability tradeoff`) and compared with
`experiments/level_share/ratios.py M CONTROL_REPORT LEVER_REPORT --method N --views`.
"""

from __future__ import annotations

import argparse

from neumip.training.loop import calibrate, energy


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("data")
    parser.add_argument("out")
    parser.add_argument("--rows", type=int, default=1 << 30, help="rows of the training split the fit reads")
    parser.add_argument("--bins", type=int, default=None, help="bins of each direction axis (default: the model's)")
    args = parser.parse_args()
    original = energy.fit_rows
    calibrate.fit_rows = lambda train_idx, seed: original(train_idx, seed, args.rows)
    calibrate.calibrate_file(args.model, args.data, args.out, bins=args.bins)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
