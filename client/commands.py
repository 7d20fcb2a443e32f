"""Client-side subcommands: `query`."""

from __future__ import annotations

import argparse

from . import contract as C


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("query", help="evaluate one query on a material (.onnx file) and print RGB")
    p.add_argument("model", help="path to a material's .onnx file")
    for field in C.QUERY_FIELDS:
        p.add_argument(field, type=float)
    p.set_defaults(func=_query)


def _query(args: argparse.Namespace) -> int:
    from .local import load_material, run_chunked

    material = load_material(args.model)
    row = C.as_queries([[getattr(args, f) for f in C.QUERY_FIELDS]])
    r, g, b = run_chunked(material.session, row)[0]
    print(f"{r:.6g} {g:.6g} {b:.6g}")
    return 0
