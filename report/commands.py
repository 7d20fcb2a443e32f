"""The `report` subcommand (registered by neumip.client.cli)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from neumip.report.config import MATERIALS

    p = sub.add_parser(
        "report", help="regenerate the evidence report (images against the real geometry, error vs time, stability)",
        description="Render every material with every method, score it against the real microgeometry, and write "
        "OUT/report.md, its charts and OUT/results.json. Renders and trained configurations are cached "
        "(--cache): an interrupted run continues.",
    )
    p.add_argument("-o", "--output", type=Path, default=None,
                   help="report folder (default: runs/report/out, or runs/report-quick/out with --quick; the "
                   "committed report is rewritten only when asked: -o docs/report)")
    p.add_argument("--materials", nargs="+", default=list(MATERIALS), metavar="NAME_OR_TOML",
                   help=f"shipped material names or material description files (.toml) (default: {' '.join(MATERIALS)})")
    p.add_argument("--quick", action="store_true", help="a smoke run: the same pipeline at tiny sizes, no timing verdicts")
    p.add_argument("--models", type=Path, default=Path("models"),
                   help="folder of the models: NAME.onnx per material, found by its description's name "
                   "(and NAME_nooffset.onnx, NAME_maps.onnx where present)")
    p.add_argument("--cache", type=Path, default=None, help="cache folder (default runs/report[-quick])")
    p.add_argument("--retime", action="store_true",
                   help="time every ladder view's rungs anew, whatever the cache holds (run it on a quiet machine)")
    p.add_argument("--skip", nargs="*", default=[], choices=("images", "stability", "tradeoff"), help="stages to leave out")
    p.set_defaults(func=_report)


def _report(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from neumip.report.config import FULL, QUICK
    from neumip.report.run import Progress, run_report

    class Bar(Progress):
        bar = None

        def stage(self, name: str, total: int) -> None:
            if self.bar is not None:
                self.bar.close()
            self.bar = tqdm(total=total, desc=name, unit="step", dynamic_ncols=True)

        def tick(self) -> None:
            self.bar.update(1)

    config = QUICK if args.quick else FULL
    if args.retime:
        config = dataclasses.replace(config, retime=True)
    runs = Path("runs") / ("report-quick" if args.quick else "report")
    cache = args.cache or runs
    output = args.output or runs / "out"
    stages = tuple(s for s in ("images", "stability", "tradeoff") if s not in args.skip)
    command = " ".join(["neumip report", *sys.argv[2:]]) if sys.argv[1:2] == ["report"] else "neumip report"
    progress = Bar()
    try:
        results = run_report(output, args.materials, config, args.models, cache, progress, stages, command=command)
    finally:
        if progress.bar is not None:
            progress.bar.close()
    print(f"wrote {output / 'report.md'} and results.json in {results['seconds'] / 60:.1f} min")
    return 0
