"""Server subcommands: `neumip serve`, `neumip export-repository`."""

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
    p.add_argument("--engine", choices=("auto", "onnxruntime", "kernel"),
                   help="what evaluates the materials (NEUMIP_ENGINE, default auto: kernel where it can run, else "
                   "onnxruntime): the file's graph interpreted as drjit LLVM kernels, the renderer's in-process "
                   "engine (pip install 'neumip[kernel]'), or in ONNX Runtime")
    p.add_argument("--allow-shared-memory", action="store_true", default=None,
                   help="let clients on this machine pass queries and answers through shared memory (Triton's "
                   "system shared-memory extension; NEUMIP_ALLOW_SHARED_MEMORY, default off)")
    p.add_argument("--list-settings", action="store_true", help="print every NEUMIP_* setting and exit")
    p.set_defaults(func=serve)
    register_export_repository(sub)


def serve(args: argparse.Namespace) -> int:
    from neumip.server.uvicorn_run import run

    if args.list_settings:
        from neumip.server.settings import Settings

        print(Settings.describe())
        return 0
    overrides = {"host": args.host, "port": args.port, "model_dir": args.model_dir, "engine": args.engine,
                 "allow_shared_memory": args.allow_shared_memory}
    return run({k: v for k, v in overrides.items() if v is not None})


def register_export_repository(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export-repository",
        help="write a Triton / KServe model repository (NAME/config.pbtxt + NAME/1/model.onnx) of a model folder",
        description="Write a Triton model repository of every *.onnx material in MODELS. Batching follows the "
        "server's settings (NEUMIP_MAX_ROWS -> max_batch_size, NEUMIP_CHUNK_ROWS -> preferred batch size, "
        "NEUMIP_MAX_WAIT_MS -> queue delay).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("models", help="folder of exported .onnx materials")
    p.add_argument("-o", "--output", required=True, help="repository folder to write (must not exist or be empty)")
    p.add_argument("--backend", choices=("onnxruntime", "python"), default="onnxruntime",
                   help="Triton backend: onnxruntime, or python (model.py running ONNX Runtime, e.g. for PyTriton)")
    p.add_argument("--instances", type=int, default=1, help="CPU instances of each model")
    p.add_argument("--threads", type=int, default=0,
                   help="ONNX Runtime intra-op threads per instance (0 = one per core); keep instances x threads <= cores")
    p.add_argument("--force", action="store_true", help="replace a non-empty output folder")
    p.set_defaults(func=export_repository_command)


def export_repository_command(args: argparse.Namespace) -> int:
    from neumip.server.model_config import TritonOptions
    from neumip.server.model_repository import RepositoryError, export_repository
    from neumip.server.settings import Settings

    try:
        options = TritonOptions.from_settings(
            Settings(), backend=args.backend, instances=args.instances, intra_op_threads=args.threads
        )
    except ValueError as exc:  # e.g. --instances 0
        raise RepositoryError(str(exc)) from None
    names = export_repository(args.models, args.output, options, force=args.force,
                              command=f"neumip export-repository {args.models} -o {args.output} --backend {args.backend}")
    print(f"wrote {args.output}: {len(names)} material(s) ({', '.join(names)}), backend {args.backend}")
    return 0
