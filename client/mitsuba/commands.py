"""Subcommands of this area (registered by neumip.client.cli): `render`."""

from __future__ import annotations

import argparse
from pathlib import Path

from neumip.client.commands import DEFAULT_MODELS


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render",
        help="render a Mitsuba scene with neural materials (in-process, or through a server)",
        description="Render SCENE (Mitsuba 3 XML using <bsdf type=\"neumip\"> and the neumip_path "
        "integrator) to OUT (.png or .exr). Neural materials are evaluated in this process from "
        "--models unless --server is given.",
    )
    p.add_argument("scene", type=Path, help="Mitsuba 3 XML scene")
    p.add_argument("-o", "--output", type=Path, required=True, help="image to write (.png or .exr)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel (default: the scene's)")
    p.add_argument("--server", default=None, help="evaluate on this server (e.g. http://127.0.0.1:8000)")
    p.add_argument("--protocol", choices=("msgpack", "v2"), default="msgpack",
                   help="with --server: msgpack /v1, or the Open Inference Protocol's binary tensors (v2: "
                   "neumip serve, Triton, KServe)")
    p.add_argument("--models", type=Path, default=Path(DEFAULT_MODELS),
                   help="folder of .onnx materials (in-process)")
    p.add_argument(
        "--fallback", action="store_true",
        help="with --server: if the server becomes unreachable, continue in-process from --models",
    )
    p.add_argument("--max-lanes", type=int, default=None, help="most pixels x samples per pass (memory bound)")
    p.add_argument(
        "-D", dest="params", action="append", default=[], metavar="NAME=VALUE",
        help="set a scene parameter ($NAME in the XML), e.g. -D resx=256; repeatable",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the first pass")
    p.add_argument("--threads", type=int, default=0, help="evaluation threads in-process (0: all cores)")
    p.set_defaults(func=_render)


def _render(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from neumip.client.cli import CommandError
    from neumip.client.http import ServerError

    from .runtime import MitsubaUnavailable

    if args.scene.is_dir():
        scenes = ", ".join(sorted(p.name for p in args.scene.glob("*.xml"))) or "none"
        raise CommandError(
            f"{args.scene} is a directory: give a Mitsuba XML scene file (XML files there: {scenes})"
        )
    if args.fallback and not args.server:
        raise CommandError("--fallback needs --server (it names what to fall back from)")
    if args.spp is not None and args.spp < 1:
        raise CommandError(f"--spp must be >= 1, got {args.spp}")
    try:
        from . import render as R
    except MitsubaUnavailable as exc:
        raise CommandError(str(exc)) from exc
    if args.output.suffix.lower() not in R.IMAGE_SUFFIXES:
        raise CommandError(f"output must end in {' or '.join(R.IMAGE_SUFFIXES)}, got {args.output.name}")

    params = {}
    for item in args.params:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise CommandError(f"-D takes NAME=VALUE, got {item!r}")
        params[name] = value
    try:
        evaluator = _evaluator(args)
    except ValueError as exc:  # a malformed --server URL
        raise CommandError(str(exc)) from exc
    config = R.RenderConfig(spp=args.spp, seed=args.seed)
    if args.max_lanes:
        config.max_lanes = args.max_lanes
    scene = R.load_scene(args.scene, **params)
    with tqdm(desc="render passes", unit="pass", total=None) as bar:

        def on_pass(done: int, total: int) -> None:
            bar.total = total
            bar.update(1)

        try:
            result = R.render_scene(scene, evaluator, config, on_pass=on_pass)
        except LookupError as exc:
            where = f"the server {args.server}" if args.server else f"{args.models}/ as <name>.onnx"
            raise CommandError(f"{exc}; put the trained materials in {where} (no image written)") from exc
        except (R.RenderError, ServerError) as exc:
            raise CommandError(f"{exc} (no image written)") from exc
    path = R.write_image(result.image, args.output)
    s = result.stats
    if getattr(evaluator, "switched", None):
        print(f"warning: the server became unavailable; the rest was evaluated in-process ({evaluator.switched})")
    print(f"wrote {path.resolve()}")
    print(
        f"{result.image.shape[1]}x{result.image.shape[0]} at {result.spp} spp in {result.passes} pass(es): "
        f"{result.seconds:.1f} s total, {s.seconds:.1f} s neural evaluation, {s.queries:,} queries"
    )
    return 0


def _evaluator(args: argparse.Namespace):
    """The in-process evaluator over --models, or a MaterialClient for --server."""
    from neumip.client.local import LocalMaterials

    if not args.server:
        return LocalMaterials(args.models, threads=args.threads)
    from neumip.client.http import FallbackEvaluator, MaterialClient

    client = MaterialClient(args.server, protocol=args.protocol)
    if args.fallback:
        return FallbackEvaluator(client, LocalMaterials(args.models, threads=args.threads))
    return client
