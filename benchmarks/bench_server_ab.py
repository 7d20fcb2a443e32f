"""A/B of two versions of the inference server on this machine: the working tree against a git revision.

    .venv/bin/python benchmarks/bench_server_ab.py --base 90ce182     # about 3 minutes
    .venv/bin/python benchmarks/bench_server_ab.py --base HEAD --engine kernel --protocol shm \
        --model models/rock.onnx --rows 131072,1048576 --big-rounds 9 --slow-runs 0

Starts two `neumip serve` processes side by side on loopback - the checked-out code and `--base`
(checked out into a temporary git worktree and put first on PYTHONPATH) - serving the same model
(`--model`, default the default `MaterialConfig`, 256^2, random weights) with the same engine
(`--engine`), and talks to both with the current `MaterialClient` (`--protocol`), so that only the
servers differ. Prints, in interleaved rounds:

- one request of each `--rows` queries (default 10^6, the renderer's largest), against the same engine in
  process (`LocalMaterials` or `KernelMaterials`): each server's ratio per round, median and range; with
  ``--clients N``, N client processes send such requests at once for ``--seconds`` (`server_cpu.run_clients`):
  the time a request, all of theirs counted;
- the p50 of 16-row requests alone and beside a slow uploader (another client sending a body one byte
  every 10 ms), median over runs.

Other jobs share the machine: read the printed load average; rounds are interleaved so that both
servers see the same load.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


import tomllib

from neumip.core import contract as C
from neumip.client.http import ClientConfig, MaterialClient
from neumip.engines.local import LocalMaterials
from neumip.server.process import ServerProcess
from neumip.server.uvicorn_run import ServeError

from bench_server import p50_16_rows  # this folder is on sys.path when run as a script
from server_cpu import run_clients, timed

ROOT = Path(__file__).resolve().parents[1]
AREAS = {name.removeprefix("neumip."): folder for name, folder in
         tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"].items()}
"""`neumip.<area>` -> the folder it maps onto (pyproject's package-dir)."""
IDLE_S = 0.05
"""Pause before each timing with the kernel engine: its drjit workers spin for 20 ms after a call (nanothread), on
the cores the next one measured needs (so time several calls a round: ``--calls``)."""


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--base", required=True, help="git revision of the other server")
    p.add_argument("--engine", choices=("onnxruntime", "kernel"), default="onnxruntime", help="both servers' engine")
    p.add_argument("--protocol", choices=("msgpack", "shm"), default="msgpack", help="how the client talks to both")
    p.add_argument("--model", type=Path, help="the model file both serve (default: a random 256^2 one)")
    p.add_argument("--rows", default="1000000", help="comma-separated queries of the large requests")
    p.add_argument("--big-rounds", type=int, default=7, help="interleaved rounds of the large requests")
    p.add_argument("--calls", type=int, default=1, help="requests timed together in a round, back to back")
    p.add_argument("--clients", type=int, default=1,
                   help="client processes sending at once for --seconds (default 1: this process, --calls requests)")
    p.add_argument("--seconds", type=float, default=1.0, help="each timing's length with --clients > 1")
    p.add_argument("--slow-runs", type=int, default=5, help="runs of 100 16-row requests, per server and case")
    return p.parse_args()


def base_package(revision: str, scratch: Path) -> Path:
    """A PYTHONPATH entry whose `neumip.*` is the code of `revision`."""
    tree = scratch / "base"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(tree), revision], check=True)
    package = scratch / "pythonpath" / "neumip"
    package.mkdir(parents=True)
    for area, folder in AREAS.items():
        (package / area).symlink_to(tree / folder)
    return package.parent


def start(folder: Path, pythonpath: Path | None, log: Path, args: argparse.Namespace) -> ServerProcess:
    """`neumip serve` of the working tree, or of the code on `pythonpath`."""
    env = {"NEUMIP_ALLOW_SHARED_MEMORY": "true"}
    if pythonpath:
        env["PYTHONPATH"] = str(pythonpath)
    try:
        return ServerProcess.start(folder, log, env=env, cwd=log.parent, engine=args.engine)
    except ServeError as exc:
        sys.exit(str(exc))


def in_process(folder: Path, engine: str):
    """The materials of `folder` evaluated in this process by `engine`, as its server does."""
    if engine == "onnxruntime":
        return LocalMaterials(folder)
    import drjit as dr

    from neumip.engines.kernel import KernelMaterials
    from neumip.server.settings import available_cores

    dr.set_thread_count(available_cores())  # as the server's kernel engine sizes drjit's pool
    return KernelMaterials(folder)


def main() -> None:
    args = parse_args()
    from neumip.core.config import MaterialConfig
    from neumip.training.export.graph import build_onnx, random_weights, save_onnx

    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(tmp)
        folder = scratch / "models"
        folder.mkdir()
        if args.model:
            name = args.model.stem
            (folder / args.model.name).symlink_to(args.model.resolve())
        else:
            name = "bench256"
            config = MaterialConfig()
            save_onnx(build_onnx(config, random_weights(config, seed=0), "benchmark"), folder / f"{name}.onnx")
        base_path = base_package(args.base, scratch)
        servers = {}
        try:
            servers[f"base ({args.base})"] = start(folder, base_path, scratch / "base.log", args)
            servers["working tree"] = start(folder, None, scratch / "current.log", args)
            local = in_process(folder, args.engine)
            pool = C.random_queries(1 << 14, seed=1)
            clients = {k: MaterialClient(server.url, ClientConfig(timeout_s=120), protocol=args.protocol)
                       for k, server in servers.items()}
            for rows in map(int, args.rows.split(",")):
                q = C.random_queries(rows, seed=7)
                kinds = {"in-process": lambda: local.evaluate(name, q)}
                kinds.update({k: (lambda c=c: c.evaluate(name, q)) for k, c in clients.items()})
                for fn in kinds.values():
                    fn()  # warm-up
                times = {k: [] for k in kinds}
                for _ in range(args.big_rounds):
                    for kind, fn in kinds.items():
                        if args.engine == "kernel":
                            time.sleep(IDLE_S)
                        if args.clients > 1:  # seconds a request, all clients' counted; in process, one caller's
                            requests, wall = (run_clients(servers[kind].url, name, rows, args.protocol,
                                                          args.clients, args.seconds)
                                              if kind in servers else timed(fn, args.seconds))[:2]
                            times[kind].append(wall / requests)
                            continue
                        start_t = time.perf_counter()
                        for _ in range(args.calls):
                            fn()
                        times[kind].append((time.perf_counter() - start_t) / args.calls)
                sent = f"{args.clients} client processes at once" if args.clients > 1 else f"rounds of {args.calls}"
                print(f"## {rows}-query {args.protocol} requests through MaterialClient, {args.engine} engine, "
                      f"{name}, {args.big_rounds} interleaved rounds, {sent} (load avg {os.getloadavg()[0]:.2f})")
                for kind, ts in times.items():
                    ratios = [a / b for a, b in zip(times["in-process"], ts)]
                    print(f"{kind:28s} median {statistics.median(ts) * 1e3:8.2f} ms   vs in-process "
                          f"{statistics.median(ratios):.3f} ({min(ratios):.3f}-{max(ratios):.3f})")
            runs = {(k, case): [] for k in servers for case in ("alone", "beside a slow uploader")}
            for _ in range(args.slow_runs):
                for k, case in runs:
                    runs[(k, case)].append(p50_16_rows(servers[k].url, name, pool, case != "alone"))
            if args.slow_runs:
                print(f"\n## 16-row requests, p50 (ms), median of {args.slow_runs} interleaved runs of 100 "
                      f"(load avg {os.getloadavg()[0]:.2f})")
            for (k, case), values in runs.items() if args.slow_runs else ():
                print(f"{k:28s} {case:24s} {statistics.median(values):6.2f}   (runs: "
                      f"{', '.join(f'{v:.2f}' for v in values)})")
            for client in clients.values():
                client.close()
        finally:
            for server in servers.values():
                server.stop()
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(scratch / "base")], check=False)


if __name__ == "__main__":
    main()
