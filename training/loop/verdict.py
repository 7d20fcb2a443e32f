"""How good a fitted model is, against something a user can judge: the ground truth's own noise.

A training target is the mean of `spp` path samples, so even a perfect model's error against the data is
not 0 but the targets' variance, the noise floor. `noise_check` traces fresh queries of the data's own
distribution with twice the data's samples: the first half's mean is a target like the data's, and the
samples' spread gives the floor, var(sample) / spp. The model's query MSE against those targets is then
the floor plus its own error, and `ratio` = MSE / floor says how far above the noise it sits (1: as good
as the data can show). The ratio is free of the material's brightness, so materials compare by it: the
shipped models carry theirs in their records (NAME.json, ``validation.noise``; `benchmarks/noise_floor.py`).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Callable

import numpy as np

log = logging.getLogger(__name__)

NOISE_QUERIES = 1 << 16
"""Fresh queries the noise check traces (each with twice the data's path samples)."""
NOISE_SEED = 7919
"""Seeds the noise check's queries and paths (another stream than the data's chunks)."""


def noise_floor(samples: np.ndarray, spp: int) -> tuple[np.ndarray, float]:
    """(N, 2 spp, 3) path samples -> (targets (N, 3): the mean of the first `spp`, floor: the mean variance of
    such a mean, var(sample) / spp over queries and channels)."""
    targets = samples[:, :spp].mean(axis=1, dtype=np.float64)
    floor = float(samples.astype(np.float64).var(axis=1, ddof=1).mean() / spp)
    return targets, floor


def noise_check(answers: Callable[[np.ndarray], np.ndarray], description, generator: dict,
                n: int = NOISE_QUERIES) -> dict:
    """The model's query MSE on `n` fresh queries against the ground truth's noise floor.

    `answers`: (N, 7) float32 queries -> (N, 3) the model's answers; `description`: the material
    (`MaterialDescription`); `generator`: the data set's generator settings as its meta.json holds them
    (resolution, spp, sampling). Returns {"queries", "spp", "mse", "noise_floor", "ratio"}.
    """
    from neumip.groundtruth.description import resolve
    from neumip.groundtruth.mesh import TilingConfig
    from neumip.groundtruth.sampling import QuerySampling, sample_queries
    from neumip.groundtruth.tracer import QueryTracer, TracerConfig

    spp = int(generator["spp"])
    sampling = QuerySampling(**generator.get("sampling", {}))
    queries = sample_queries(n, np.random.default_rng(NOISE_SEED), int(generator["resolution"]), sampling)
    tracer = QueryTracer(resolve(description), TracerConfig(**generator.get("tracer", {})),
                         TilingConfig(**generator.get("tiling", {})))
    samples = tracer.samples(queries, 2 * spp, NOISE_SEED)  # (n, 2 spp, 3)
    finite = np.isfinite(samples).all(axis=(1, 2))
    if not finite.all():  # (numerical accidents of the tracer: left out, as its estimates leave them out)
        log.warning("noise check: %d of %d queries had a non-finite sample and were left out", (~finite).sum(), n)
        queries, samples = queries[finite], samples[finite]
    targets, floor = noise_floor(samples, spp)
    mse = float(np.mean((np.asarray(answers(queries), np.float64) - targets) ** 2))
    ratio = mse / floor if floor > 0 else None  # (None: noise-free data, an analytic material)
    return {"queries": int(len(queries)), "spp": spp, "mse": mse, "noise_floor": floor, "ratio": ratio}


def ratio_at(noise: dict, spp: int) -> float:
    """The noise ratio the model would read on data of `spp` samples a query: its own error is the same, the
    floor scales as 1 / spp."""
    floor = noise["noise_floor"] * noise["spp"] / spp
    return (max(noise["mse"] - noise["noise_floor"], 0.0) + floor) / floor


def shipped_ratios(folder: Path | None) -> dict[str, tuple[float, int]]:
    """Name -> (noise ratio, its data's spp) of every model record (NAME.json) in `folder` that has one."""
    if folder is None or not folder.is_dir():
        return {}
    found = {}
    for record in sorted(folder.glob("*.json")):
        try:
            noise = json.loads(record.read_text())["validation"]["noise"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if isinstance(noise, dict) and isinstance(noise.get("ratio"), (int, float)):
            found[record.stem] = (float(noise["ratio"]), int(noise.get("spp", 16)))
    return found


def verdict_line(noise: dict, shipped: dict[str, tuple[float, int]]) -> str:
    """One line: the model's query error against the noise floor, and where that places it among `shipped`
    (each compared at its own data's spp, `ratio_at`)."""
    if noise["ratio"] is None:
        return f"verdict: query MSE {noise['mse']:.3g} against noise-free ground truth"
    own = max(noise["mse"] - noise["noise_floor"], 0.0)
    line = (f"verdict: query MSE {noise['ratio']:.2f}x the ground truth's own noise ({noise['noise_floor'] * 1e3:.3g}e-3 "
            f"at {noise['spp']} spp; 1x is all the data can show), the model's own error {own * 1e3:.3g}e-3")
    if not shipped:
        return line
    ranked = sorted(shipped.items(), key=lambda item: item[1][0])
    closer = sum(ratio < ratio_at(noise, spp) for _, (ratio, spp) in ranked)
    span = f"{ranked[0][0]} {ranked[0][1][0]:.2f}x to {ranked[-1][0]} {ranked[-1][1][0]:.2f}x"
    place = ("closer to the noise than every one" if closer == 0 else "further from it than every one"
             if closer == len(ranked) else f"{closer} of {len(ranked)} closer")
    spps = sorted({spp for _, spp in shipped.values()})
    at = "" if spps == [noise["spp"]] else f" (at their data's {'/'.join(map(str, spps))} spp)"
    return f"{line}; shipped models{at} {span}: {place}"
