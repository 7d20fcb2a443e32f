"""`neumip calibrate`: the command line of `loop/calibrate.py` (registered by `client.cli`)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="fit a model's energy table on its data (the coarse levels' lost energy back, no retraining)",
        description="Write MODEL with its energy table (`MaterialConfig.energy_bins`: a gain per level of detail, "
        "half-vector angle and light elevation, the data's mean over the answers' mean in each cell) fitted on the training split of "
        "DATA, the data set it was trained on (split by --seed, as `neumip train` splits it), and its validation "
        "table recomputed on the held-out split. A model trained with --energy-bins has its table fitted already; "
        "this is for a model made without one, or refitting on more data.",
    )
    p.add_argument("model", type=Path, help="exported .onnx material (not trimmed: trim after calibrating)")
    p.add_argument("--data", type=Path, required=True, help="the data set it was trained on (neumip generate)")
    p.add_argument("-o", "--output", type=Path, required=True, help=".onnx to write (may be MODEL with --force)")
    p.add_argument("--bins", type=int, help="bins of each direction axis, the half vector's angle and the "
                   "light's elevation (default: the model's, else 6)")
    p.add_argument("--azimuths", type=int, help="bins of the half vector's azimuth, the table's fourth axis "
                   "(MaterialConfig.energy_azimuths; 0: none; default: the model's where it has a table, else 16)")
    p.add_argument("--luminance", action=argparse.BooleanOptionalAction, default=None,
                   help="one gain a cell for the three channels, the luminances' ratio (MaterialConfig.energy_luminance: "
                   "a third of the table's reads; default: the model's own)")
    p.add_argument("--seed", type=int, default=0, help="the training seed whose split the model was trained on")
    p.add_argument("--force", action="store_true", help="replace the output if it exists")
    p.set_defaults(func=_calibrate)


def _calibrate(args: argparse.Namespace) -> int:
    from neumip.core.errors import CommandError
    from neumip.training.loop.calibrate import calibrate_file

    if not args.model.is_file():
        raise CommandError(f"model {args.model} does not exist")
    if not (args.data / "meta.json").is_file():
        raise CommandError(f"{args.data} is not a data set (no meta.json): make one with `neumip generate`")
    if args.output.exists() and not args.force:
        raise CommandError(f"{args.output} exists: pass --force to replace it, or choose another --output")
    try:
        validation = calibrate_file(args.model, args.data, args.output, args.bins, args.seed, args.azimuths,
                                    args.luminance)
    except (OSError, ValueError) as exc:  # a trimmed or unreadable model, a broken data set
        raise CommandError(f"cannot calibrate {args.model}: {exc}") from exc
    overall = validation["overall"]
    print(f"wrote {args.output}: held-out MSE {overall['mse']:.4g}, data / answer "
          f"{overall['target_mean'] / max(overall['answer_mean'], 1e-30):.3f} on {overall['n']:,} queries")
    return 0
