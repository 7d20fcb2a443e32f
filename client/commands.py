"""Client-side subcommands: `query`."""

from __future__ import annotations

import argparse
from pathlib import Path

from neumip.core import contract as C

DEFAULT_MODELS = "models"
"""Folder `neumip query` and `neumip render` look material names up in."""

FIELD_HELP = {
    "u": "position on the material, tile units (the material repeats with period 1)",
    "v": "position on the material, tile units",
    "sigma": "std of the Gaussian pixel footprint, tile units (1 finest texel or less: finest level; "
             "1 tile or more: the 1 x 1 level)",
    "wi_x": "x of the direction towards the light, local frame (z = normal, x along +u, y along +v)",
    "wi_y": "y of the direction towards the light (x^2 + y^2 <= 1)",
    "wo_x": "x of the direction towards the viewer, same frame",
    "wo_y": "y of the direction towards the viewer (x^2 + y^2 <= 1)",
}
"""What each of the contract's query values (`contract.QUERY_FIELDS`) means, for `--help`."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "query", help="evaluate one query on a material and print its RGB",
        description="Evaluate one query - the 7 values of the query contract, in order "
        f"({' '.join(C.QUERY_FIELDS)}) - and print the answer as 'r g b': linear RGB, the material's "
        "multi-resolution BTF under unit irradiance, used like a BRDF (a Lambertian plane of albedo a "
        "answers a / pi). Example: neumip query rock 0.3 0.7 0.01 0.2 0.1 -0.3 0.4",
    )
    p.add_argument("material", help="a material's .onnx file, or a material name looked up in --models")
    for field in C.QUERY_FIELDS:
        p.add_argument(field, type=float, help=FIELD_HELP[field])
    p.add_argument("--models", type=Path, default=Path(DEFAULT_MODELS),
                   help="folder of .onnx materials (for a name)")
    p.set_defaults(func=_query)


def model_path(material: str, models: Path) -> Path:
    """`material` as given (a .onnx file) or looked up by name in `models`; a clear error otherwise."""
    from neumip.core.errors import CommandError

    path = Path(material)
    if path.is_dir():
        raise CommandError(f"{path} is a directory: give a material's .onnx file, or a material name "
                           f"with --models {path}")
    if path.suffix == ".onnx" or path.exists():
        if not path.exists():
            raise CommandError(f"{path} does not exist")
        return path
    candidate = models / f"{material}.onnx"
    if not candidate.is_file():
        from neumip.engines.folder import list_models

        names = sorted(list_models(models)[0]) if models.is_dir() else []
        there = f"materials there: {', '.join(names)}" if names else "no .onnx files there"
        raise CommandError(f"no material {material!r} in {models} ({there})")
    return candidate


def _query(args: argparse.Namespace) -> int:
    from neumip.engines.local import load_material, run_chunked

    material = load_material(model_path(args.material, args.models))
    row = C.as_queries([[getattr(args, f) for f in C.QUERY_FIELDS]])
    r, g, b = run_chunked(material.run, row)[0]
    print(f"{r:.6g} {g:.6g} {b:.6g}")
    return 0
