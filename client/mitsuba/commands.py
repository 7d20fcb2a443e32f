"""Subcommands of this area (registered by neumip.client.cli): `render`, `budget`."""

from __future__ import annotations

import argparse
from pathlib import Path

from neumip.client.commands import DEFAULT_MODELS

VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
"""Mitsuba variants `neumip render` runs (`neumip_path` needs a JIT variant; the answers are RGB)."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render",
        help="render a Mitsuba scene with neural materials (in-process, or through a server)",
        description="Render SCENE (Mitsuba 3 XML using <bsdf type=\"neumip\"> and the neumip_path "
        "integrator) to OUT (.png or .exr). Neural materials are evaluated in this process from "
        "--models (inside the render's own kernels, or with --engine onnxruntime) unless --server is given.",
    )
    p.add_argument("scene", type=Path, help="Mitsuba 3 XML scene")
    p.add_argument("-o", "--output", type=Path, required=True, help="image to write (.png or .exr)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel (default: the scene's)")
    p.add_argument("--server", default=None, help="evaluate on this server (e.g. http://127.0.0.1:8000)")
    p.add_argument("--protocol", choices=("auto", "msgpack", "v2", "shm"), default="auto",
                   help="with --server: msgpack /v1, the Open Inference Protocol's binary tensors (v2: "
                   "neumip serve, Triton, KServe), v2 with the rows in shared memory (shm: a server on this "
                   "machine started with --allow-shared-memory, or Triton with --allow-client-shm), or auto: shm "
                   "where the server offers it on this machine, else msgpack")
    p.add_argument("--models", type=Path, default=Path(DEFAULT_MODELS),
                   help="folder of .onnx materials (in-process); several as DIR1:DIR2, the first holding a "
                        "name serves it (e.g. mine:models: your materials beside the shipped ones)")
    p.add_argument(
        "--fallback", action="store_true",
        help="with --server: if the server becomes unreachable, continue in-process from --models",
    )
    p.add_argument("--max-lanes", type=int, default=None, help="most pixels x samples per pass (memory bound)")
    _scene_params(p)
    p.add_argument("--seed", type=int, default=0, help="seed of the render (renders of different seeds share no pass)")
    p.add_argument("--engine", choices=("kernel", "onnxruntime"), default="kernel",
                   help="in-process evaluation: the material's ONNX graph traced into the render's drjit "
                   "kernels (default), or run by ONNX Runtime (the server's engine)")
    p.add_argument("--threads", type=int, default=0,
                   help="ONNX Runtime evaluation threads in-process (0: all cores)")
    p.add_argument("--variant", choices=VARIANTS, default=None,
                   help="Mitsuba variant: llvm_ad_rgb (CPU, the default) or cuda_ad_rgb (an NVIDIA GPU; there "
                   "larger passes keep it busy, e.g. --max-lanes 16777216, ~11 GB)")
    p.set_defaults(func=_render)

    b = sub.add_parser(
        "budget",
        help="which pyramid levels a scene reads of each neural material (no neural evaluation)",
        description="Trace SCENE at a few samples per pixel with the footprints of neumip_path and the "
        "materials' preview BSDF; report per neural material the levels its queries read, the finest "
        "level that matters, the bytes a model trimmed to it would save, and the finest training "
        "resolution the scene's closest views need.",
    )
    b.add_argument("scene", type=Path, help="Mitsuba 3 XML scene")
    b.add_argument("--models", type=Path, default=Path(DEFAULT_MODELS), help="folder of the .onnx materials")
    b.add_argument("--spp", type=int, default=4, help="samples per pixel traced (default 4)")
    b.add_argument("--render-spp", type=int, default=None,
                   help="spp of the render to budget for: it sets each sample's footprint "
                   "(default: the scene's)")
    b.add_argument("--coverage", type=float, default=0.999,
                   help="share of queries the finest level that matters must serve (default 0.999)")
    b.add_argument("--plot", type=Path, default=None, help="write the per-level histograms to this image")
    b.add_argument("--json", action="store_true", help="print machine-readable JSON (for neumip trim --budget)")
    _scene_params(b)
    b.add_argument("--seed", type=int, default=0, help="sampler seed")
    b.set_defaults(func=_budget)


def _scene_params(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "-D", dest="params", action="append", default=[], metavar="NAME=VALUE",
        help="set a scene parameter ($NAME in the XML), e.g. -D resx=256; repeatable",
    )


def _parse_params(items: list[str]) -> dict[str, str]:
    from neumip.core.errors import CommandError

    params = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise CommandError(f"-D takes NAME=VALUE, got {item!r}")
        params[name] = value
    return params


def _scene_file(path: Path) -> None:
    from neumip.core.errors import CommandError

    if path.is_dir():
        scenes = ", ".join(sorted(p.name for p in path.glob("*.xml"))) or "none"
        raise CommandError(f"{path} is a directory: give a Mitsuba XML scene file (XML files there: {scenes})")


def _budget(args: argparse.Namespace) -> int:
    from neumip.core.errors import CommandError

    from neumip.client.mitsuba.runtime import MitsubaUnavailable

    _scene_file(args.scene)
    for flag, value in (("--spp", args.spp), ("--render-spp", args.render_spp)):
        if value is not None and value < 1:
            raise CommandError(f"{flag} must be >= 1, got {value}")
    if not 0 < args.coverage <= 1:
        raise CommandError(f"--coverage must be in (0, 1], got {args.coverage}")
    params = _parse_params(args.params)
    try:
        from neumip.client.mitsuba import budget as B
        from neumip.client.mitsuba import render as R
    except MitsubaUnavailable as exc:
        raise CommandError(str(exc)) from exc
    try:
        scene = R.load_scene(args.scene, **params)
        result = B.scene_budget(scene, args.models, args.spp, args.coverage, args.seed, args.render_spp)
    except R.RenderError as exc:
        raise CommandError(str(exc)) from exc
    if args.plot:
        try:
            B.plot_budget(result, args.plot)
        except ImportError as exc:
            raise CommandError(str(exc)) from exc
    print(result.to_json() if args.json else B.format_budget(result))
    if args.plot and not args.json:
        print(f"wrote {args.plot.resolve()}")
    return 0


def _render(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from neumip.core.errors import CommandError
    from neumip.client.http import ServerError

    from neumip.client.mitsuba.runtime import MitsubaUnavailable

    _scene_file(args.scene)
    if args.fallback and not args.server:
        raise CommandError("--fallback needs --server (it names what to fall back from)")
    if args.spp is not None and args.spp < 1:
        raise CommandError(f"--spp must be >= 1, got {args.spp}")
    try:
        if args.variant:
            _select_variant(args.variant)
        from neumip.client.mitsuba import render as R
    except MitsubaUnavailable as exc:
        raise CommandError(str(exc)) from exc
    if args.output.suffix.lower() not in R.IMAGE_SUFFIXES:
        raise CommandError(f"output must end in {' or '.join(R.IMAGE_SUFFIXES)}, got {args.output.name}")

    params = _parse_params(args.params)
    try:
        evaluator = _evaluator(args)
    except ValueError as exc:  # a malformed --server URL
        raise CommandError(str(exc)) from exc
    config = R.RenderConfig(spp=args.spp, seed=args.seed)
    if args.max_lanes:
        config.max_lanes = args.max_lanes
    scene = R.load_scene(args.scene, **params)
    if not args.server:
        _load_scene_materials(evaluator, scene)
    bars = []  # the bar, made at the first pass, when the number of passes is known (never an empty "0pass")

    def on_pass(done: int, total: int) -> None:
        if not bars:
            bars.append(tqdm(desc="render passes", unit="pass", total=total))
        bars[0].total = total
        bars[0].update(done - bars[0].n)

    try:
        result = R.render_scene(scene, evaluator, config, on_pass=on_pass)
    except LookupError as exc:
        where = f"the server {args.server}" if args.server else f"{args.models}/ as <name>.onnx"
        raise CommandError(f"{exc}; put the trained materials in {where} (no image written)") from exc
    except (R.RenderError, ServerError) as exc:
        raise CommandError(f"{exc} (no image written)") from exc
    finally:
        for bar in bars:
            bar.close()
        client = getattr(evaluator, "primary", evaluator)  # a FallbackEvaluator's client
        if hasattr(client, "close"):  # a MaterialClient: its connection, its shared-memory regions unregistered
            client.close()
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


def _load_scene_materials(evaluator, scene) -> None:
    """Load the scene's neural materials from the model folder before rendering (the evaluators load
    lazily): model files that fail are reported now, all of them, as the server reports them at
    start-up, never in the middle of a render."""
    from neumip.core.errors import CommandError
    from neumip.engines.local import ModelError

    from neumip.client.mitsuba.shading import scene_materials

    load = getattr(evaluator, "kernel", None) or evaluator.get
    failed = {}
    for name in set(scene_materials(scene)) & set(evaluator.materials()):
        try:
            load(name)
        except ModelError as exc:
            failed[name] = str(exc)
    if failed:
        reasons = "; ".join(f"{name}: {reason}" for name, reason in sorted(failed.items()))
        raise CommandError(f"{len(failed)} of the scene's materials failed to load from {evaluator.folder} "
                           f"({reasons}); no image written")


def _select_variant(variant: str) -> None:
    """Render with Mitsuba `variant` (before the renderer's plugins load, which keep a JIT variant
    already set); raises MitsubaUnavailable if it cannot run here, CommandError if this process
    already renders with another one."""
    import sys

    from neumip.core.errors import CommandError

    from neumip.client.mitsuba.runtime import import_mitsuba

    loaded = sys.modules.get("neumip.client.mitsuba.bsdf")
    if loaded is not None and loaded.mi.variant() != variant:
        raise CommandError(f"this process already renders with Mitsuba variant {loaded.mi.variant()}, "
                           f"not {variant}: run the command in a new process")
    import_mitsuba(variant)


def _evaluator(args: argparse.Namespace):
    """The in-process evaluator over --models (--engine), or a MaterialClient for --server."""
    from neumip.engines.local import LocalMaterials

    if not args.server and args.engine == "kernel":
        from neumip.engines.kernel import KernelMaterials, namespace_of

        from neumip.client.mitsuba.render import mi

        return KernelMaterials(args.models, backend=namespace_of(mi.Float))  # the variant's arrays
    if not args.server:  # lazy: only the scene's materials load
        return LocalMaterials(args.models, threads=args.threads, lazy=True)
    from neumip.client.http import FallbackEvaluator, MaterialClient

    client = MaterialClient(args.server, protocol=args.protocol)
    if args.fallback:
        return FallbackEvaluator(client, LocalMaterials(args.models, threads=args.threads))
    return client
