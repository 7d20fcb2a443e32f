"""Ground-truth throughput: path samples/s and queries/s of `neumip generate`, and the projected time
of a complete training set (default: 256^2 material, 200 queries per finest texel, 16 spp, 4 bounces).

Runs the real generator (query sampling, tracing, chunked writing) on a few chunks per material; the
first chunk (kernel compilation) is reported separately and left out of the rate. "cores used" is
the CPU time of all threads over wall time: on a shared machine it shows how much CPU the run got.

    .venv/bin/python benchmarks/bench_generate.py                      # yarn rock turtle foam
    .venv/bin/python benchmarks/bench_generate.py --materials yarn --chunks 4
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from neumip.groundtruth.description import find_description, resolve
from neumip.groundtruth.generate import GenerateSettings, generate
from neumip.groundtruth.mesh import TilingConfig, query_scene
from neumip.groundtruth.tracer import TracerConfig


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--materials", nargs="+", default=["yarn", "rock", "turtle", "foam"])
    p.add_argument("--resolution", type=int, default=256, help="finest texels per tile side")
    p.add_argument("--queries-per-texel", type=float, default=200.0)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--max-depth", type=int, default=4)
    p.add_argument("--chunk", type=int, default=1 << 16, help="queries per chunk")
    p.add_argument("--chunks", type=int, default=3, help="chunks per material (the first is warm-up)")
    p.add_argument("--lanes", type=int, default=1 << 20)
    p.add_argument("--threads", type=int, default=0, help="drjit threads (0: all cores)")
    return p.parse_args()


def bench(name: str, args: argparse.Namespace, folder: Path) -> dict:
    desc = find_description(name)
    desc.resolution = args.resolution
    geo = resolve(desc)
    from neumip.client.mitsuba.runtime import import_mitsuba

    mi = import_mitsuba()
    start = time.perf_counter()
    scene, margin = query_scene(mi, geo, TilingConfig())
    build = time.perf_counter() - start
    triangles = sum(shape.face_count() for shape in scene.shapes())
    del scene

    settings = GenerateSettings(
        queries=args.chunk * args.chunks, spp=args.spp, seed=0, chunk=args.chunk,
        tracer=TracerConfig(max_depth=args.max_depth, lanes=args.lanes),
    )
    stamps: list[tuple[int, float, float]] = []  # (queries done, wall clock, CPU time of all threads)
    generate(desc, folder / name, settings,
             lambda done, total: stamps.append((done, time.perf_counter(), time.process_time())))
    (_, t0, _), (warm_done, t1, c1), (last_done, t2, c2) = stamps[0], stamps[1], stamps[-1]
    queries_per_s = (last_done - warm_done) / (t2 - t1)
    total = args.queries_per_texel * args.resolution**2
    return {
        "name": name,
        "triangles": triangles,
        "margin": margin,
        "build_s": build,
        "first_chunk_s": t1 - t0,
        "queries_per_s": queries_per_s,
        "samples_per_s": queries_per_s * args.spp,
        "cores_used": (c2 - c1) / (t2 - t1),
        "samples_per_cpu_s": (last_done - warm_done) * args.spp / (c2 - c1),
        "projected_min": (build + total / queries_per_s) / 60,
    }


def main() -> None:
    args = parse_args()
    if args.chunks < 2:
        raise SystemExit("--chunks must be >= 2 (the first one is warm-up)")
    if args.threads:
        import drjit as dr

        dr.set_thread_count(args.threads)
    total = args.queries_per_texel * args.resolution**2
    print(
        f"full set: {args.resolution}^2 texels x {args.queries_per_texel:g} queries/texel = {total / 1e6:.1f} M "
        f"queries x {args.spp} spp = {total * args.spp / 1e6:.0f} M path samples, up to {args.max_depth} bounces"
    )
    header = f"{'material':10s} {'triangles':>10s} {'margin':>7s} {'build s':>8s} {'1st chunk s':>11s} " \
             f"{'M samples/s':>11s} {'k queries/s':>11s} {'full set min':>12s} {'cores used':>10s} {'M samples/cpu-s':>15s}"
    print(header)
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.materials:
            r = bench(name, args, Path(tmp))
            print(
                f"{r['name']:10s} {r['triangles']:10d} {r['margin']:7.2f} {r['build_s']:8.2f} "
                f"{r['first_chunk_s']:11.2f} {r['samples_per_s'] / 1e6:11.3f} {r['queries_per_s'] / 1e3:11.1f} "
                f"{r['projected_min']:12.1f} {r['cores_used']:10.2f} {r['samples_per_cpu_s'] / 1e6:15.3f}"
            )


if __name__ == "__main__":
    main()
