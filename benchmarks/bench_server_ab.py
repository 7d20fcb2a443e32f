"""A/B of two versions of the inference server on this machine: the working tree against a git revision.

    .venv/bin/python benchmarks/bench_server_ab.py --base 90ce182     # about 3 minutes

Starts two `neumip serve` processes side by side on loopback - the checked-out code and `--base`
(checked out into a temporary git worktree and put first on PYTHONPATH) - serving the same model
(the default `MaterialConfig`, 256^2, random weights), and talks to both with the current
`MaterialClient`, so that only the servers differ. Prints, in interleaved rounds:

- one 10^6-query msgpack request (the renderer's largest), against in-process `LocalMaterials`;
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


from neumip.core import contract as C
from neumip.client.http import ClientConfig, MaterialClient
from neumip.engines.local import LocalMaterials
from neumip.server.process import ServerProcess
from neumip.server.uvicorn_run import ServeError

from bench_server import p50_16_rows  # this folder is on sys.path when run as a script

ROOT = Path(__file__).resolve().parents[1]
AREAS = ("client", "server", "training")
"""Folders that map onto `neumip.<area>` (pyproject's package-dir)."""


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--base", required=True, help="git revision of the other server")
    p.add_argument("--big-rounds", type=int, default=7, help="interleaved rounds of the 10^6-query request")
    p.add_argument("--slow-runs", type=int, default=5, help="runs of 100 16-row requests, per server and case")
    return p.parse_args()


def base_package(revision: str, scratch: Path) -> Path:
    """A PYTHONPATH entry whose `neumip.*` is the code of `revision`."""
    tree = scratch / "base"
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(tree), revision], check=True)
    package = scratch / "pythonpath" / "neumip"
    package.mkdir(parents=True)
    for area in AREAS:
        (package / area).symlink_to(tree / area)
    return package.parent


def start(folder: Path, pythonpath: Path | None, log: Path) -> ServerProcess:
    """`neumip serve` of the working tree, or of the code on `pythonpath`."""
    try:
        return ServerProcess.start(folder, log, env={"PYTHONPATH": str(pythonpath)} if pythonpath else None,
                                   cwd=log.parent)
    except ServeError as exc:
        sys.exit(str(exc))


def main() -> None:
    args = parse_args()
    from neumip.core.config import MaterialConfig
    from neumip.training.export.graph import build_onnx, random_weights, save_onnx

    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(tmp)
        folder = scratch / "models"
        folder.mkdir()
        config = MaterialConfig()
        save_onnx(build_onnx(config, random_weights(config, seed=0), "benchmark"), folder / "bench256.onnx")
        base_path = base_package(args.base, scratch)
        servers = {}
        try:
            servers[f"base ({args.base})"] = start(folder, base_path, scratch / "base.log")
            servers["working tree"] = start(folder, None, scratch / "current.log")
            local = LocalMaterials(folder)
            q = C.random_queries(1_000_000, seed=7)
            pool = C.random_queries(1 << 14, seed=1)
            clients = {k: MaterialClient(server.url, ClientConfig(timeout_s=120)) for k, server in servers.items()}
            kinds = {"in-process": lambda: local.evaluate("bench256", q)}
            kinds.update({k: (lambda c=c: c.evaluate("bench256", q)) for k, c in clients.items()})
            for fn in kinds.values():
                fn()  # warm-up
            times = {k: [] for k in kinds}
            for _ in range(args.big_rounds):
                for kind, fn in kinds.items():
                    start_t = time.perf_counter()
                    fn()
                    times[kind].append(time.perf_counter() - start_t)
            print(f"## One 10^6-query msgpack request through MaterialClient, {args.big_rounds} interleaved rounds "
                  f"(load avg {os.getloadavg()[0]:.2f})")
            for kind, ts in times.items():
                ratio = statistics.median(a / b for a, b in zip(times["in-process"], ts))
                print(f"{kind:28s} median {statistics.median(ts):6.3f} s   vs in-process {ratio:4.0%}")
            runs = {(k, case): [] for k in servers for case in ("alone", "beside a slow uploader")}
            for _ in range(args.slow_runs):
                for k, case in runs:
                    runs[(k, case)].append(p50_16_rows(servers[k].url, "bench256", pool, case != "alone"))
            print(f"\n## 16-row requests, p50 (ms), median of {args.slow_runs} interleaved runs of 100 "
                  f"(load avg {os.getloadavg()[0]:.2f})")
            for (k, case), values in runs.items():
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
