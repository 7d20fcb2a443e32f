"""Benchmark: render the demo scene in-process and through a real `neumip serve` process.

Prints, for each path: total render time, time inside neural evaluation, query rows evaluated, and
the HTTP / in-process time ratio (targets: <= 60 s in-process at 512 x 512, 64 spp on 2 cores; HTTP
<= 1.3x). Both renders use the same seed, so the images must agree; their largest difference is
printed too. A small warm-up render first compiles the kernels (drjit caches them in ~/.drjit).
CPU seconds (this process, plus the server process for HTTP) are printed beside wall time: on a
shared machine they are the steadier figure.

    .venv/bin/python benchmarks/bench_render.py                      # materials from models/
    .venv/bin/python benchmarks/bench_render.py --stand-in           # untrained stand-ins (needs neumip[train])

``--stand-in`` builds constant-colour materials of the default architecture (256^2 pyramid,
neural offset) into a temporary folder: evaluation costs what a trained material costs, the
picture does not look like one.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "demo.xml"
DEMO_MATERIALS = {"yarn": (0.55, 0.2, 0.12), "rock": (0.4, 0.37, 0.33), "turtle": (0.2, 0.45, 0.2),
                  "foam": (0.8, 0.8, 0.72)}


def stand_in_models(folder: Path) -> Path:
    """Write constant-colour materials of the default architecture under the demo's names."""
    from neumip.training.config import MaterialConfig
    from neumip.training.export import build_onnx, constant_weights, save_onnx

    cfg = MaterialConfig()
    for name, rgb in DEMO_MATERIALS.items():
        weights = constant_weights(cfg, [c / np.pi for c in rgb])
        save_onnx(build_onnx(cfg, weights, f"benchmark stand-in ({name})"), folder / f"{name}.onnx")
    return folder


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds a process has used so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def render(evaluator, args, size: int, spp: int, server_pid: int | None = None):
    """Render the demo; returns (result, CPU seconds of this process plus the server's)."""
    from neumip.client.mitsuba.render import RenderConfig, load_scene, render_scene

    scene = load_scene(SCENE, resx=str(size), resy=str(size), spp=str(spp))
    cpu = time.process_time() + (process_cpu_seconds(server_pid) if server_pid else 0.0)
    result = render_scene(scene, evaluator, RenderConfig(spp=spp, seed=args.seed, max_lanes=args.max_lanes))
    cpu = time.process_time() + (process_cpu_seconds(server_pid) if server_pid else 0.0) - cpu
    return result, cpu


def report(label: str, result, cpu: float) -> None:
    s = result.stats
    print(
        f"{label:>11}: {result.seconds:6.1f} s total ({cpu:6.1f} CPU s) | {s.seconds:6.1f} s neural evaluation "
        f"({100 * s.seconds / result.seconds:4.1f} %) | {s.queries:>12,} queries in {s.calls} calls | "
        f"{result.passes} passes | {s.queries / max(s.seconds, 1e-9) / 1e6:.2f} M queries/s evaluated",
        flush=True,
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", type=Path, default=ROOT / "models", help="model folder")
    parser.add_argument("--stand-in", action="store_true", help="use untrained stand-in materials")
    parser.add_argument("--size", type=int, default=512, help="image width and height")
    parser.add_argument("--spp", type=int, default=64, help="samples per pixel")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-lanes", type=int, default=2**21, help="lanes per render pass")
    parser.add_argument("--no-http", action="store_true", help="skip the server run")
    args = parser.parse_args()

    sys.path.insert(0, str(ROOT))
    from neumip.client.local import LocalMaterials

    with tempfile.TemporaryDirectory() as tmp:
        models = stand_in_models(Path(tmp)) if args.stand_in else args.models
        local = LocalMaterials(models)
        print(f"demo scene {SCENE.name}, {args.size}x{args.size}, {args.spp} spp; materials from {models}: "
              f"{', '.join(local.materials())}", flush=True)
        render(local, args, 64, 2)  # warm-up: compile (or load cached) kernels
        in_process, cpu_local = render(local, args, args.size, args.spp)
        report("in-process", in_process, cpu_local)
        if args.no_http:
            return 0

        from neumip.client.http import MaterialClient
        from tests.client.mitsuba.server_process import ServerProcess

        server = ServerProcess(models)
        try:
            with MaterialClient(server.url) as client:
                render(client, args, 64, 2)
                remote, cpu_remote = render(client, args, args.size, args.spp, server.proc.pid)
        finally:
            server.stop()
        report("HTTP", remote, cpu_remote)
        diff = np.abs(remote.image - in_process.image)
        print(f"HTTP / in-process: {remote.seconds / in_process.seconds:.2f}x wall time, "
              f"{cpu_remote / cpu_local:.2f}x CPU time (client + server); "
              f"image difference max {diff.max():.2e}, mean {diff.mean():.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
