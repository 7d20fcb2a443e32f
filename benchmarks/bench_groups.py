"""Benchmark: the kernel engine on query groups of K lights, evaluated as groups of at most W lights.

A renderer sends a shading point's lights as one query group (next-event estimation towards each emitter
plus the BSDF sample: K = emitters + 1). The server's kernel engine traces only the widths it warmed up
(`neumip.server.engine.WARM_LIGHTS`) and runs a wider group as groups of the widest (`in_groups`). Each
group computes its position's lookups (relief march, offset, pyramid, base maps) once and the decoder once
per light, so the width decides how often the lookups run. This prints answers/s of random groups of each
K, in process (`KernelMaterial.run`: what the server's worker calls), evaluated whole (W = K, traced for K)
and as groups of at most W for each ``--widths`` W, in interleaved rounds (medians), and each one's ratio to
the whole group. Every way answers with the same bits (checked).

    .venv/bin/python benchmarks/bench_groups.py                          # rock, K 2-6, W 2 and 3
    .venv/bin/python benchmarks/bench_groups.py --models rock,yarn --lights 3,4 --widths 1,2,3

The first call of each width compiles its kernel (seconds; drjit caches it on disk): untimed.

``--load``: instead, what the warm-up's widths cost a server's loading: `Registry.load` of each model alone
with the kernel engine and each ``--warm`` set of widths (default 1,2 and 1,2,3), in a new process with an
empty drjit cache (a new ``HOME``: a new machine or container) and again with that cache filled.

    .venv/bin/python benchmarks/bench_groups.py --load --models rock
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from neumip.core import contract as C


def groups_of(n: int, lights: int, seed: int) -> np.ndarray:
    """(n, 5 + 2 lights) random valid query groups (`contract.random_queries`, further lights' wi)."""
    extra = [C.random_queries(n, seed=seed * 100 + j)[:, C.WI_X:C.WI_Y + 1] for j in range(1, lights)]
    return np.ascontiguousarray(np.hstack([C.random_queries(n, seed=seed), *extra]))


def load_seconds(path: Path, widths: tuple[int, ...]) -> float:
    """Seconds `Registry.load` takes for the one model `path` with the kernel engine warming `widths`."""
    from neumip.server import registry
    from neumip.server.engine import Engine

    registry.WARM_LIGHTS = widths
    engine = Engine.kernel()
    engine.start()
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copy(path, tmp)
        start = time.perf_counter()
        loaded = registry.Registry.load(Path(tmp), engine)
        seconds = time.perf_counter() - start
    if list(loaded.materials) != [path.stem]:
        sys.exit(f"{path.name} did not load: {loaded.errors}")
    return seconds


def loading(args) -> None:
    print(f"## Registry.load of one model, kernel engine, warm-up widths; an empty drjit cache, then filled   "
          f"[load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores]")
    for name in args.models:
        for widths in args.warm:
            with tempfile.TemporaryDirectory() as home:
                child = [sys.executable, __file__, "--load-child", str(args.folder / f"{name}.onnx"),
                         "--warm", ",".join(map(str, widths))]
                seconds = [float(subprocess.run(child, env={**os.environ, "HOME": home}, check=True,
                                                capture_output=True, text=True).stdout) for _ in range(2)]
            print(f"  {name:10s} widths {','.join(map(str, widths)):6s} empty cache {seconds[0]:6.2f} s   "
                  f"filled {seconds[1]:5.2f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--folder", type=Path, default=Path("models"))
    parser.add_argument("--models", type=lambda t: t.split(","), default=["rock"])
    parser.add_argument("--lights", type=lambda t: [int(x) for x in t.split(",")], default=[2, 3, 4, 5, 6])
    parser.add_argument("--widths", type=lambda t: [int(x) for x in t.split(",")], default=[2, 3])
    parser.add_argument("--answers", type=int, default=2**18, help="answers a call (groups: answers // K)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="drjit's pool")
    parser.add_argument("--load", action="store_true", help="the warm-up's cost when a server loads a model")
    parser.add_argument("--warm", type=lambda t: [tuple(int(x) for x in w.split(",")) for w in t.split(";")],
                        default=[(1, 2), (1, 2, 3)], help="--load: sets of widths, e.g. '1,2;1,2,3'")
    parser.add_argument("--load-child", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.load_child:
        print(load_seconds(args.load_child, args.warm[0]))
        return
    if args.load:
        loading(args)
        return

    import drjit as dr

    from neumip.engines.kernel import KernelMaterial
    from neumip.server.engine import in_groups

    dr.set_thread_count(args.threads)
    print(f"## groups of K lights as groups of at most W, kernel engine in process, {args.answers} answers a call, "
          f"{args.threads} drjit threads; median of {args.rounds} interleaved rounds   "
          f"[load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores]")
    for name in args.models:
        material = KernelMaterial(args.folder / f"{name}.onnx")
        ways: dict[tuple[int, int], object] = {}
        batches: dict[int, np.ndarray] = {}
        for lights in args.lights:
            batches[lights] = groups_of(args.answers // lights, lights, seed=lights)
            ways[lights, lights] = material.run
            for width in args.widths:
                if width < lights:
                    ways[lights, width] = lambda q, w=width: in_groups(material.run, q, w)
        for (lights, width), run in ways.items():  # compile each width, and check the bits
            answer = run(batches[lights])
            whole = material.run(batches[lights])
            if not np.array_equal(answer, whole):
                sys.exit(f"{name}: K {lights} as groups of {width} answers other bits than the whole group")
        seconds: dict[tuple[int, int], list[float]] = {key: [] for key in ways}
        for _ in range(args.rounds):
            for key, run in ways.items():
                start = time.perf_counter()
                run(batches[key[0]])
                seconds[key].append(time.perf_counter() - start)
        print(f"{name}:")
        for (lights, width), times in seconds.items():
            rate = len(batches[lights]) * lights / statistics.median(times)
            ratio = statistics.median(t / w for t, w in zip(seconds[lights, lights], times))
            how = "whole" if width == lights else f"as groups of {width}"
            print(f"  K {lights}  {how:18s} {rate / 1e6:6.2f} M answers/s   {ratio:5.2f}x the whole group's rate")
    print(f"[load average {os.getloadavg()[0]:.2f}]")


if __name__ == "__main__":
    main()
