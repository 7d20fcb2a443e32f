"""Ground truth on Ray against one process, and a projection to N machines.

1. Interleaved rounds on this machine: the same data set (one material, `--chunks` chunks) written by
   one process (drjit on every core) and by a local Ray with `--workers` workers of one drjit thread
   each. Each round uses its own seed for both, so both build their scenes in every run, as a fresh
   `neumip generate` does. The figure is the median ratio Ray / single-process wall time; every
   round also checks the two data sets are bit-identical.
2. The cost of one chunk to a worker: CPU seconds of `trace_chunk` on one drjit thread.
3. The driver's cost per chunk: Ray tasks that return a chunk's arrays at once (no tracing),
   collected in order and written by `DatasetWriter` as `neumip generate --ray` does; and the write
   alone.
4. Projection: N machines of `--cores` cores trace `N * cores / cost` chunks per second; the driver
   takes at most `1 / driver cost` of them. Where those meet, the driver is the bottleneck.

    .venv/bin/python benchmarks/bench_ray.py                   # turtle 64^2, 8 chunks of 16384, 16 spp
    .venv/bin/python benchmarks/bench_ray.py --rounds 5 --cores 32
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from neumip.client.mitsuba.runtime import import_mitsuba
from neumip.core import cluster
from neumip.core.cluster import RayConfig
from neumip.groundtruth.dataset import DatasetWriter
from neumip.groundtruth.description import find_description, resolve
from neumip.groundtruth.generate import GenerateSettings, generate, trace_chunk
from neumip.groundtruth.tracer import QueryTracer

FULL_SET = 256 * 256 * 200
"""Queries of a full 256^2 training set at 200 queries per texel (the paper's size)."""


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--material", default="turtle")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--chunk", type=int, default=1 << 14, help="queries per chunk in the comparison")
    p.add_argument("--chunks", type=int, default=8)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--workers", type=int, default=2, help="CPUs of the local Ray (one drjit thread each)")
    p.add_argument("--project-chunk", type=int, default=1 << 16, help="chunk size of the projection (the default)")
    p.add_argument("--cores", type=int, default=16, help="cores per machine in the projection")
    p.add_argument("--gbps", type=float, default=1.0, help="assumed network into the driver, Gbit/s")
    return p.parse_args()


def timed(fn) -> tuple[float, object]:
    start = time.perf_counter()
    result = fn()
    return time.perf_counter() - start, result


def compare(args, desc, folder: Path, ray_config: RayConfig) -> tuple[list, list, bool]:
    """Interleaved rounds; returns single and Ray wall times and whether every round was identical."""
    single, on_ray, identical = [], [], True
    for r in range(args.rounds):
        settings = GenerateSettings(queries=args.chunk * args.chunks, spp=args.spp, seed=100 + r, chunk=args.chunk)
        order = [("single", None), ("ray", ray_config)]
        runs = {}
        for name, config in order if r % 2 == 0 else order[::-1]:
            seconds, runs[name] = timed(lambda: generate(desc, folder / f"{name}{r}", settings, ray=config))
            (single if name == "single" else on_ray).append(seconds)
        identical &= bool(np.array_equal(runs["single"].rgb, runs["ray"].rgb)
                          and np.array_equal(runs["single"].queries, runs["ray"].queries))
        print(f"round {r}: single {single[-1]:.2f} s, Ray {on_ray[-1]:.2f} s, identical {identical}", flush=True)
    return single, on_ray, identical


def chunk_cpu_seconds(args, desc) -> float:
    """CPU seconds of one chunk of `args.chunk` queries traced on one drjit thread (after a warm-up)."""
    import_mitsuba()
    import drjit as dr

    threads = dr.thread_count()
    dr.set_thread_count(1)
    tracer = QueryTracer(resolve(desc))
    settings = GenerateSettings(spp=args.spp, seed=1)
    trace_chunk(tracer, settings, args.resolution, 0, args.chunk // 4)  # kernel compilation
    start = time.process_time()
    for index in range(2):
        trace_chunk(tracer, settings, args.resolution, index, args.chunk)
    dr.set_thread_count(threads)
    return (time.process_time() - start) / 2


def arrays(size: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(size)
    return rng.random((size, 7), np.float32) * 0.5, rng.random((size, 3), np.float32)


def driver_seconds(size: int, chunks: int, folder: Path, config: RayConfig) -> tuple[float, float]:
    """Per chunk: (Ray task returning the arrays + in-order collection + write, the write alone)."""
    q, rgb = arrays(size)
    writer = DatasetWriter(folder / "alone", size * chunks, size, {"bench": "write"})
    write, _ = timed(lambda: [writer.write_chunk(i, q, rgb) for i in range(chunks)])
    writer = DatasetWriter(folder / "ray", size * chunks, size, {"bench": "ray"})
    jobs = [(size,)] * chunks
    list(cluster.ordered(arrays, jobs[:4], config))  # workers warm
    start = time.perf_counter()
    for index, (q, rgb) in enumerate(cluster.ordered(arrays, jobs, config)):
        writer.write_chunk(index, q, rgb)
    return (time.perf_counter() - start) / chunks, write / chunks


def main() -> None:
    args = parse_args()
    desc = find_description(args.material)
    desc.resolution = args.resolution
    ray = cluster.import_ray()
    import os

    print(f"{args.material} {args.resolution}^2, {args.chunks} chunks of {args.chunk} queries, {args.spp} spp; "
          f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start")
    start_up, _ = timed(lambda: ray.init(address="local", num_cpus=args.workers, include_dashboard=False,
                                         logging_level="WARNING"))
    print(f"local Ray start-up: {start_up:.1f} s (once per `neumip generate --ray` without an address)")
    config = RayConfig(cpus_per_task=1)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        single, on_ray, identical = compare(args, desc, folder, config)
        ratio = statistics.median(r / s for r, s in zip(on_ray, single))
        print(f"median wall time: single {statistics.median(single):.2f} s, Ray {statistics.median(on_ray):.2f} s; "
              f"Ray / single = {ratio:.2f} (median of per-round ratios); bit-identical in every round: {identical}")

        cost = chunk_cpu_seconds(args, desc) * args.project_chunk / args.chunk
        driver, write = driver_seconds(args.project_chunk, 24, folder, config)
        print(f"per chunk of {args.project_chunk} queries at {args.spp} spp: worker {cost:.2f} CPU-s; driver "
              f"{driver * 1e3:.1f} ms (task result + write), of which the write {write * 1e3:.1f} ms")
    ray.shutdown()
    project(args, cost, driver)


def project(args, cost: float, driver: float) -> None:
    """Chunks per second of N machines against the driver, and the time of a full 256^2 set."""
    network = args.gbps * 1e9 / 8 / (args.project_chunk * 40)  # chunks/s into the driver, 40 B a query
    driver_rate = min(1 / driver, network)
    chunks = FULL_SET / args.project_chunk
    print(f"\nprojection, {args.cores} cores per machine, full 256^2 set ({FULL_SET / 1e6:.1f} M queries, "
          f"{chunks:.0f} chunks); driver takes {1 / driver:.0f} chunks/s measured, "
          f"{network:.0f} chunks/s at an assumed {args.gbps:g} Gbit/s:")
    print(f"{'machines':>8} {'chunks/s':>9} {'full set':>9}  bound")
    for n in (1, 2, 4, 8, 16, 32, 64, 128, 256, 512):
        traced = n * args.cores / cost
        rate = min(traced, driver_rate)
        print(f"{n:8d} {rate:9.1f} {chunks / rate:8.1f}s  {'workers' if traced < driver_rate else 'driver'}")
    for what, rate in (("its measured cost", 1 / driver), (f"{args.gbps:g} Gbit/s into it", network)):
        print(f"the driver becomes the bottleneck, by {what}, at about {rate * cost / args.cores:.1f} machines "
              f"({rate * cost:.0f} cores, {rate * args.project_chunk / 1e6:.1f} M queries/s)")


if __name__ == "__main__":
    main()
