"""Training-side subcommands: `export` (later: `generate`, `train`). Torch is imported lazily."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="export a training checkpoint to an ONNX material")
    p.add_argument("checkpoint", help="checkpoint file written by `neumip train`")
    p.add_argument("-o", "--output", required=True, help="output .onnx path (e.g. models/NAME.onnx)")
    p.add_argument("--description", default="", help="short description stored in the metadata")
    p.set_defaults(func=_export)


def _export(args: argparse.Namespace) -> int:
    from .export import export_checkpoint

    path = export_checkpoint(args.checkpoint, args.output, args.description)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0
