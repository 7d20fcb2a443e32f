"""The `report` subcommand (registered by neumip.client.cli)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    from .config import MATERIALS

    p = sub.add_parser(
        "report", help="regenerate the evidence report (images against the real geometry, error vs time, stability)",
        description="Render every material with every method, score it against the real microgeometry, and write "
        "OUT/report.md, its charts and OUT/results.json. Renders and trained configurations are cached "
        "(--cache): an interrupted run continues.",
    )
    p.add_argument("-o", "--output", type=Path, default=Path("docs/report"), help="report folder (default docs/report)")
    p.add_argument("--materials", nargs="+", default=list(MATERIALS), help=f"materials (default: {' '.join(MATERIALS)})")
    p.add_argument("--quick", action="store_true", help="the same pipeline at tiny sizes")
    p.add_argument("--models", type=Path, default=Path("models"), help="folder of the shipped .onnx models")
    p.add_argument("--cache", type=Path, default=None, help="cache folder (default runs/report[-quick])")
    p.add_argument("--skip", nargs="*", default=[], choices=("images", "stability", "tradeoff"), help="stages to leave out")
    p.set_defaults(func=_report)


def _report(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .config import FULL, QUICK
    from .run import Progress, run_report

    class Bar(Progress):
        bar = None

        def stage(self, name: str, total: int) -> None:
            if self.bar is not None:
                self.bar.close()
            self.bar = tqdm(total=total, desc=name, unit="step", dynamic_ncols=True)

        def tick(self) -> None:
            self.bar.update(1)

    config = QUICK if args.quick else FULL
    cache = args.cache or Path("runs") / ("report-quick" if args.quick else "report")
    stages = tuple(s for s in ("images", "stability", "tradeoff") if s not in args.skip)
    progress = Bar()
    try:
        results = run_report(args.output, args.materials, config, args.models, cache, progress, stages)
    finally:
        if progress.bar is not None:
            progress.bar.close()
    print(f"wrote {args.output / 'report.md'} and results.json in {results['seconds'] / 60:.1f} min")
    return 0
