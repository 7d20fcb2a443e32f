"""Server subcommands: `neumip serve`."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve",
        help="serve every material of a model folder over HTTP (msgpack /v1 and Open Inference Protocol /v2)",
        description="Serve the *.onnx materials of a folder with uvicorn. Every setting is also an "
        "environment variable NEUMIP_<NAME> (see neumip.server.settings.Settings); options given here win.",
    )
    p.add_argument("--host", help="address to bind (NEUMIP_HOST, default 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (NEUMIP_PORT, default 8000)")
    p.add_argument("--model-dir", help="folder of .onnx materials (NEUMIP_MODEL_DIR, default models)")
    p.add_argument("--list-settings", action="store_true", help="print every NEUMIP_* setting and exit")
    p.set_defaults(func=serve)


def serve(args: argparse.Namespace) -> int:
    from .uvicorn_run import run

    if args.list_settings:
        from .settings import Settings

        print(Settings.describe())
        return 0
    overrides = {"host": args.host, "port": args.port, "model_dir": args.model_dir}
    return run({k: v for k, v in overrides.items() if v is not None})
