"""Training throughput: queries per second of one full training step, and what a 256^2 run costs.

A step is what `Trainer.step` does: blur the textures, draw a batch from a memory-mapped data
set, forward, comb2 loss, backward, Adam. Three implementations are timed in the same run:

- reference: the straightforward autograd version (the lookup as first written: `atlas[rows]`
  gather with autograd's index_put backward, wrap's floor() inside the graph, convolution blur),
- eager: the shipped implementation (index_add gather backward, floors outside the graph,
  circulant-matrix blur),
- compiled: the same through torch.compile (`TrainConfig.compile`).

Wall-clock figures on a shared machine are noisy, so CPU seconds per step are printed too
(queries per CPU-second, with the process's CPU time; the ratio between implementations is what
to compare). Run: .venv/bin/python benchmarks/bench_train.py [--resolution 128] [--batch 65536]

`--threads-sweep 1,2 [--extra-load 2]` times the `quick` preset at 64^2 with each torch thread count
instead (the figures behind `neumip train`'s threads; run it with and without OMP_WAIT_POLICY=PASSIVE,
which `neumip train` sets).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import tempfile
import time
from dataclasses import replace

import numpy as np
import torch

import neumip.training.loop.blur as blur_mod
import neumip.training.model.pyramid as pyramid_mod
from neumip.core.contract import random_queries
from neumip.core.config import MaterialConfig
from neumip.groundtruth.dataset import write_dataset
from neumip.training.loop.train import Trainer
from neumip.training.loop.config import QUICK, SHIP


def reference_gather_blend(atlas, rows, weights):
    """The straightforward lookup: fancy-index gather (autograd backward via index_put)."""
    return torch.einsum("nk,nkc->nc", weights, atlas[rows])


def reference_wrap(u):
    return u - torch.floor(u)


def reference_blur_texture(texture, sigma):
    """Two circular 1-D convolutions (the first version of blur_texture)."""
    size, _, channels = texture.shape
    kernel = blur_mod.gaussian_kernel(sigma, texture.dtype, texture.device)
    if (kernel.shape[0] - 1) // 2 >= size:
        return blur_mod.blur_texture(texture, sigma)
    x = blur_mod._blur_rows(texture.permute(0, 2, 1).reshape(size * channels, size), kernel)
    y = blur_mod._blur_rows(x.reshape(size, channels, size).permute(1, 2, 0).reshape(channels * size, size), kernel)
    return y.reshape(channels, size, size).permute(2, 1, 0)


@contextlib.contextmanager
def reference_implementation():
    """Swap the straightforward lookup and blur in (module attributes, restored afterwards)."""
    saved = (pyramid_mod.gather_blend, pyramid_mod.wrap, blur_mod.blur_texture)
    pyramid_mod.gather_blend = reference_gather_blend
    pyramid_mod.wrap = reference_wrap
    blur_mod.blur_texture = reference_blur_texture
    import neumip.training.loop.train as train_mod

    train_saved = train_mod.blur_texture
    train_mod.blur_texture = reference_blur_texture
    try:
        yield
    finally:
        pyramid_mod.gather_blend, pyramid_mod.wrap, blur_mod.blur_texture = saved
        train_mod.blur_texture = train_saved


def synthetic_data(path: str, n: int) -> str:
    """n random queries with a smooth RGB answer (training speed does not depend on the values)."""
    q = random_queries(n, seed=0, max_zenith_deg=84.3, u_range=(0.0, 1.0), log2_sigma_range=(-8.0, 0.0))
    rgb = (0.2 + 0.1 * np.sin(6.28 * q[:, :3])).astype(np.float32)
    write_dataset(path, q, rgb, {"material": "bench-synthetic", "generator": "bench_train"})
    return path


def time_steps(trainer: Trainer, steps: int) -> tuple[float, float]:
    """-> (wall seconds per step, CPU seconds per step) over `steps` steps."""
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(steps):
        trainer.step()
    return (time.perf_counter() - w0) / steps, (time.process_time() - c0) / steps


def implementation(mode: str):
    return reference_implementation() if mode == "reference" else contextlib.nullcontext()


def busy_loop() -> None:
    """Burn one core (an `--extra-load` process)."""
    while True:
        pass


def threads_section(args) -> None:
    """Wall and CPU seconds per step of the `quick` preset at 64^2 (the shipped models' size) for each
    torch thread count in `--threads-sweep`, interleaved round by round, with `--extra-load` busy
    processes beside it: what `neumip train --threads` trades on a shared machine."""
    import multiprocessing

    counts = [int(t) for t in args.threads_sweep.split(",")]
    hogs = [multiprocessing.Process(target=busy_loop, daemon=True) for _ in range(args.extra_load)]
    for hog in hogs:
        hog.start()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            data = synthetic_data(os.path.join(tmp, "data"), 400_000)
            config = replace(QUICK, device="cpu")
            trainer = Trainer(data, os.path.join(tmp, "t.pt"), MaterialConfig(resolution=64), config)
            trainer.state.step = 300  # inside the blur schedule, as most of a quick run is
            trainer.step()  # warm-up
            samples: dict[int, list[tuple[float, float]]] = {t: [] for t in counts}
            for _ in range(args.rounds):
                for t in counts:
                    torch.set_num_threads(t)
                    samples[t].append(time_steps(trainer, args.steps))
    finally:
        for hog in hogs:
            hog.terminate()
    policy = os.environ.get("OMP_WAIT_POLICY", "unset: threads spin")
    print(f"quick preset, 64^2, batch {QUICK.batch}; OMP_WAIT_POLICY {policy}; {args.extra_load} extra busy "
          f"processes; load average {os.getloadavg()[0]:.2f} after; {os.cpu_count()} cores")
    for t, values in samples.items():
        wall, cpu = (float(np.median([v[i] for v in values])) for i in (0, 1))
        print(f"  {t} torch threads: {wall * 1e3:7.1f} ms/step wall, {cpu * 1e3:7.1f} ms/step CPU "
              f"({QUICK.steps} steps: {QUICK.steps * wall:5.0f} s; "
              f"medians of {args.rounds} rounds of {args.steps})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--batch", type=int, default=1 << 16)
    parser.add_argument("--steps", type=int, default=2, help="timed steps per implementation and round")
    parser.add_argument("--rounds", type=int, default=5, help="rounds (implementations interleaved)")
    parser.add_argument("--modes", default="reference,eager,compiled")
    parser.add_argument("--no-offset", action="store_true")
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's choice)")
    parser.add_argument("--threads-sweep", help="instead: time the quick preset at 64^2 with these torch "
                        "thread counts, e.g. 1,2")
    parser.add_argument("--extra-load", type=int, default=0,
                        help="with --threads-sweep: busy processes beside it")
    args = parser.parse_args()
    if args.threads_sweep:
        threads_section(args)
        return
    if args.threads:
        torch.set_num_threads(args.threads)

    torch.manual_seed(0)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, load average {os.getloadavg()}")
    material = MaterialConfig(resolution=args.resolution, offset=not args.no_offset)
    modes = args.modes.split(",")
    samples: dict[str, list[tuple[float, float]]] = {m: [] for m in modes}
    with tempfile.TemporaryDirectory() as tmp:
        data = synthetic_data(os.path.join(tmp, "data"), max(4 * args.batch, 200_000))
        trainers = {}
        for mode in modes:
            config = replace(SHIP, batch=args.batch, compile=mode == "compiled", device="cpu")
            trainers[mode] = Trainer(data, os.path.join(tmp, f"{mode}.pt"), material, config)
            trainers[mode].state.step = 500  # inside the blur schedule: the blur is part of the cost
            with implementation(mode):
                t0 = time.perf_counter()
                trainers[mode].step()  # warm-up (compiles)
                print(f"{mode:>9}: first step {time.perf_counter() - t0:5.1f} s")
        # rounds interleave the implementations, so load changes on the shared machine hit all alike
        for _ in range(args.rounds):
            for mode in modes:
                with implementation(mode):
                    samples[mode].append(time_steps(trainers[mode], args.steps))
    results = {m: tuple(float(np.median([s[i] for s in samples[m]])) for i in (0, 1)) for m in modes}
    for mode, (wall, cpu) in results.items():
        print(
            f"{mode:>9}: {args.batch / wall / 1e6:6.3f} M queries/s wall ({wall * 1e3:7.1f} ms/step), "
            f"{args.batch / cpu / 1e6:6.3f} M queries per CPU-s (medians of {args.rounds} rounds)"
        )
    if "reference" in results:
        for mode, (wall, cpu) in list(results.items())[1:]:
            print(f"speed-up of {mode} over reference: wall {results['reference'][0] / wall:4.2f}x, "
                  f"CPU {results['reference'][1] / cpu:4.2f}x")
    best = min(results, key=lambda m: results[m][0])
    wall = results[best][0]
    # the shipped 64^2 materials saw SHIP.steps * SHIP.batch / 64^2 training queries per finest texel
    per_texel = SHIP.steps * SHIP.batch / 64**2
    total = per_texel * args.resolution**2
    print(
        f"projection ({best}, {args.resolution}^2): the shipped models' {per_texel:.0f} training queries per "
        f"finest texel are {total / 1e6:.0f} M queries, {total * wall / args.batch / 60:.1f} min wall at this "
        f"rate; the paper preset (30 000 x 2^20 = 31.5 G queries) would take "
        f"{30_000 * (1 << 20) * wall / args.batch / 3600:.1f} h"
    )


if __name__ == "__main__":
    main()
