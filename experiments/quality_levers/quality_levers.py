"""Material-quality levers (issue 11), one change at a time against the current recipe.

Each variant trains one 64^2 material in-process (`neumip.training.loop.train.Trainer`) with one change to
the current recipe (the `ship` preset's schedule at a quarter of its queries, `BASE`, on 256
queries/texel x 16 spp data, as models/make_models.sh generates), then measures its MSE per
level against a low-noise reference query set (>= 256 spp, made by `neumip generate ... --spp 256`).
Levels are always binned at 64^2 (the data's sampling resolution), so a 128^2 model is compared on
the same queries. One JSON line per run is appended to --out; `--table` prints them.

    # data (experiments/quality_levers/quality_levers.txt lists the exact commands used)
    neumip generate docs/materials/stones.toml -o /tmp/q/stones_ref --queries 40000 --spp 256 \
        --seed 1 --resolution 64
    neumip generate docs/materials/stones.toml -o /tmp/q/stones_q256s16 --queries-per-texel 256 \
        --spp 16 --seed 0 --resolution 64
    # runs (1 torch thread each; several processes may run side by side)
    .venv/bin/python experiments/quality_levers/quality_levers.py --data /tmp/q/stones_q256s16 --ref /tmp/q/stones_ref \
        --label stones base yuv cosine ... --out experiments/quality_levers/quality_levers.jsonl
    .venv/bin/python experiments/quality_levers/quality_levers.py --table experiments/quality_levers/quality_levers.jsonl
    # target noise against query count at a fixed sample budget
    .venv/bin/python experiments/quality_levers/quality_levers.py --noise docs/materials/stones.toml
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from neumip.core import contract as C  # noqa: E402
from neumip.core.config import MaterialConfig  # noqa: E402
from neumip.training.loop.config import PRESETS  # noqa: E402

GRAZING_DEG = 70.0
"""Views further than this from the normal count as grazing (reported apart: the offset's weak spot)."""

BIN_RESOLUTION = 64
"""Levels of detail are binned at this finest resolution for every variant."""

BASE = replace(PRESETS["quick"], batch=8192, validate_every=0)
"""The reduced budget every variant but the long ones gets: the `ship` schedule at half the steps
(1 200, blur half-life 133) and half the batch (8 192): a quarter of `ship`'s queries."""


def _scaled(factor: float, **extra):
    """BASE with steps and blur half-life scaled by `factor` (the same schedule, longer)."""
    return replace(BASE, steps=round(BASE.steps * factor), blur_half_life=BASE.blur_half_life * factor, **extra)


VARIANTS: dict[str, tuple[dict, object, str]] = {
    # name: (MaterialConfig overrides, TrainConfig, data set: "" = --data, else --data with
    # "q256s16" replaced by this)
    "base": ({}, BASE, ""),
    "seed1": ({}, replace(BASE, seed=1), ""),  # run-to-run spread of the measurement itself
    "yuv": ({"head": "yuv"}, BASE, ""),
    "data_q64s64": ({}, BASE, "q64s64"),
    "data_q16s256": ({}, BASE, "q16s256"),
    "cosine": ({}, replace(BASE, lr_schedule="cosine"), ""),
    "nooffset": ({"offset": False}, BASE, ""),
    "long4x": ({}, _scaled(4), ""),
    "batch4x": ({}, replace(_scaled(0.25), batch=BASE.batch * 4), ""),
    "nofreeze": ({}, replace(BASE, offset_freeze=False), ""),
    "mincos_0.3": ({"offset_min_cos": 0.3}, BASE, ""),
    "offset_c3": ({"offset_channels": 3}, BASE, ""),
    "res128": ({"resolution": 128}, BASE, ""),
    "mse": ({}, replace(BASE, loss="mse"), ""),
    "long4x_yuv": ({"head": "yuv"}, _scaled(4), ""),
    "long4x_cosine": ({}, _scaled(4, lr_schedule="cosine"), ""),
    "long4x_q64s64": ({}, _scaled(4), "q64s64"),
    "long4x_res128": ({"resolution": 128}, _scaled(4), ""),
    "quality": ({}, replace(PRESETS["quality"], validate_every=0), ""),  # the recipe kept, full length
    "quality_res128": ({"resolution": 128}, replace(PRESETS["quality"], validate_every=0), ""),
}


def run_variant(name: str, data: str, ref: str, label: str, threads: int) -> dict:
    import torch

    from neumip.groundtruth.dataset import open_dataset
    from neumip.training.loop.train import Trainer
    from neumip.training.loop.validation import predict, validation_table

    torch.set_num_threads(threads)
    overrides, config, data_kind = VARIANTS[name]
    if data_kind:
        data = data.replace("q256s16", data_kind)
    material = MaterialConfig(**{"resolution": 64, "offset_min_cos": 0.6, **overrides})  # the recipe measured
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(data, Path(tmp) / "c.pt", material, config)
        start = time.perf_counter()
        held = trainer.run()
        seconds = time.perf_counter() - start
    reference = open_dataset(ref)
    queries, target = np.asarray(reference.queries), np.asarray(reference.rgb)
    pred = predict(trainer.material, queries)
    table = validation_table(pred, target, queries[:, C.SIGMA], BIN_RESOLUTION)
    wo = queries[:, C.WO_X] ** 2 + queries[:, C.WO_Y] ** 2
    grazing = wo > np.sin(np.radians(GRAZING_DEG)) ** 2
    return {
        "label": label, "variant": name, "bin": BIN_RESOLUTION, "data": data, "ref": ref,
        "data_spp": trainer.data.meta.get("generator", {}).get("spp"), "data_n": len(trainer.data),
        "seconds": round(seconds, 1), "steps": config.steps, "batch": config.batch,
        "held_out_mse": held["overall"]["mse"],
        "ref_levels": [{k: r[k] for k in ("level", "n", "mse", "log_mse")} for r in table["levels"]],
        "ref_all": table["overall"]["mse"], "ref_log_mse": table["overall"]["log_mse"],
        "ref_mean": table["overall"]["target_mean"], "pred_mean": float(pred.mean()),
        "grazing_mse": float(np.mean((pred[grazing] - target[grazing]) ** 2)),
        "other_mse": float(np.mean((pred[~grazing] - target[~grazing]) ** 2)),
    }


def print_table(path: str) -> None:
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    for label in dict.fromkeys(r["label"] for r in rows):
        group = [r for r in rows if r["label"] == label]
        base = next((r for r in group if r["variant"] == "base"), None)
        print(f"\n== {label}: MSE x1e-3 against the low-noise reference, per level "
              f"({group[0].get('bin', 64)}^2 binning); graze: views > {GRAZING_DEG:.0f} degrees")
        print(f"{'variant':<14} {'data':<16} {'train s':>7} {'L0':>7} {'L1':>7} {'L2':>7} {'L3+':>7} {'all':>7} "
              f"{'vs base':>7} {'logMSE':>8} {'mean/ref':>8} {'graze':>7}")
        for r in group:
            lv = {x["level"]: x for x in r["ref_levels"]}
            coarse = [x for x in r["ref_levels"] if x["level"] >= 3]
            l3 = sum(x["mse"] * x["n"] for x in coarse) / max(1, sum(x["n"] for x in coarse))
            cells = [lv[k]["mse"] * 1e3 if k in lv else float("nan") for k in (0, 1, 2)]
            ratio = r["ref_all"] / base["ref_all"] if base else float("nan")
            print(f"{r['variant']:<14} {Path(r['data']).name:<16} {r['seconds']:>7.0f} "
                  + " ".join(f"{c:>7.3f}" for c in cells)
                  + f" {l3 * 1e3:>7.3f} {r['ref_all'] * 1e3:>7.3f} {ratio:>7.2f} {r['ref_log_mse']:>8.5f} "
                  f"{r['pred_mean'] / r['ref_mean']:>8.3f} {r.get('grazing_mse', float('nan')) * 1e3:>7.3f}")


def target_noise(material: str, n: int, spp: int, budget_samples: float) -> None:
    """Per-sample variance of the MBTF estimate on n queries of the default distribution, and the
    target noise (MSE of an s-spp mean) against the query count a fixed sample budget buys."""
    from neumip.groundtruth.description import find_description, resolve
    from neumip.groundtruth.sampling import QuerySampling, sample_queries
    from neumip.groundtruth.tracer import QueryTracer

    desc = find_description(material)
    queries = sample_queries(n, np.random.default_rng(5), BIN_RESOLUTION, QuerySampling())
    start = time.perf_counter()
    samples = QueryTracer(resolve(desc)).samples(queries, spp, seed=11)  # (n, spp, 3)
    seconds = time.perf_counter() - start
    var = float(samples.var(axis=1, ddof=1).mean())
    level = np.rint(C.level_of_detail(queries[:, C.SIGMA].astype(np.float64), BIN_RESOLUTION)).astype(int)
    per_level = {int(k): float(samples[level == k].var(axis=1, ddof=1).mean()) for k in np.unique(level)}
    print(f"== target noise of {desc.name}: {n} queries x {spp} spp traced in {seconds:.1f} s "
          f"({n * spp / seconds / 1e6:.2f} M samples/s)")
    print(f"per-sample variance (mean over queries and RGB): {var:.4g}; per level "
          + ", ".join(f"L{k} {v:.3g}" for k, v in per_level.items()))
    print(f"fixed budget {budget_samples / 1e6:.1f} M path samples (= 256 queries/texel x 16 spp at 64^2):")
    print(f"{'spp':>5} {'queries':>9} {'per texel':>9} {'target noise MSE x1e-3':>22}")
    for s in (4, 8, 16, 32, 64, 128, 256):
        q = budget_samples / s
        print(f"{s:>5} {q:>9.0f} {q / BIN_RESOLUTION**2:>9.0f} {var / s * 1e3:>22.4f}")


def main() -> None:
    global BIN_RESOLUTION
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("variants", nargs="*", help=f"any of: {', '.join(VARIANTS)}")
    parser.add_argument("--data")
    parser.add_argument("--ref")
    parser.add_argument("--label", default="")
    parser.add_argument("--out", default="experiments/quality_levers/quality_levers.jsonl")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--bin", type=int, default=BIN_RESOLUTION,
                        help="finest resolution levels are binned at (the data's sampling resolution)")
    parser.add_argument("--table", metavar="JSONL")
    parser.add_argument("--noise", metavar="MATERIAL")
    args = parser.parse_args()
    BIN_RESOLUTION = args.bin
    if args.table:
        print_table(args.table)
        return
    if args.noise:
        target_noise(args.noise, 2000, 256, 256 * 16 * BIN_RESOLUTION**2)
        return
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown:
        parser.error(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
    for name in args.variants:
        row = run_variant(name, args.data, args.ref, args.label, args.threads)
        with open(args.out, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(f"{args.label} {name}: ref MSE {row['ref_all'] * 1e3:.4f}e-3 in {row['seconds']:.0f} s", flush=True)


if __name__ == "__main__":
    main()
