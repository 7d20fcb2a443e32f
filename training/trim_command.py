"""`neumip trim`: the command line of `trim.py` (registered by `training.commands`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "trim",
        help="drop a model's pyramid levels finer than a scene needs (answers above the cut unchanged)",
        description="Write MODEL without its latent pyramid levels finer than --finest-level (or the level "
        "`neumip budget --json` found for it), and without the levels of its base maps' and relief's pyramids "
        "finer than the same footprint. Queries whose level is at or above the cut get bit-identical answers; "
        "finer queries read the finest level kept. The neural offset texture is kept whole.",
    )
    p.add_argument("model", type=Path, help="exported .onnx material")
    p.add_argument("-o", "--output", type=Path, required=True, help="trimmed .onnx to write")
    level = p.add_mutually_exclusive_group(required=True)
    level.add_argument("--finest-level", type=int, help="finest level to keep (0 = the model's finest)")
    level.add_argument("--budget", type=Path, help="JSON of `neumip budget --json`: its finest level for MODEL's name")
    p.add_argument("--material", help="material name to look up in --budget (default: MODEL's file stem)")
    p.add_argument("--force", action="store_true", help="replace the output if it exists")
    p.set_defaults(func=_trim)


def _trim(args: argparse.Namespace) -> int:
    from neumip.core.errors import CommandError

    from neumip.training.export.trim import finest_level_from_budget, trim_file

    if not args.model.is_file():
        raise CommandError(f"model {args.model} does not exist")
    if args.output.exists() and not args.force:
        raise CommandError(f"{args.output} exists: pass --force to replace it, or choose another --output")
    try:
        if args.budget is not None:
            budget = json.loads(args.budget.read_text())
            level = finest_level_from_budget(budget, args.material or args.model.stem)
        else:
            level = args.finest_level
        record = trim_file(args.model, args.output, level)
    except (OSError, ValueError) as exc:  # TrimError, broken JSON, unreadable model
        raise CommandError(f"cannot trim {args.model}: {exc}") from exc
    before, after = args.model.stat().st_size, args.output.stat().st_size
    print(f"wrote {args.output} (finest level {record.finest_level}, {record.finest_resolution}^2"
          f"{_maps_kept(args.output, record.finest_level)}): "
          f"{before:,} -> {after:,} bytes ({100 * (1 - after / before):.1f} % smaller)")
    return 0


def _maps_kept(path: Path, finest_level: int) -> str:
    """"; base_maps from level 4 (16^2), ..." for the model's other pyramids ("" for none)."""
    from neumip.core import weights as W
    from neumip.core.modelfile import read_model_file
    from neumip.training.export.lod import pyramids

    config = read_model_file(path).config
    kept = []
    for p in pyramids(config):
        if p.texture != W.PYRAMID:
            level = config.pyramid_finest_level(p.config, finest_level)
            kept.append(f"{p.texture} from level {level} ({p.config.level_sizes()[level]}^2)")
    return "; " + ", ".join(kept) if kept else ""
