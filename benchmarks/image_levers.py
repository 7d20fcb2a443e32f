"""Material-quality levers (issue 11) scored in image space: the report's views against its reference.

`train` fits one variant of the current recipe (the `ship` preset on 64^2, 256 queries/texel x 16 spp
data, as models/make_models.sh trains; one change per variant) in-process and exports it as
``RUNS/VARIANT/MATERIAL.onnx`` (variants without the offset as ``MATERIAL_nooffset.onnx``).

`score` renders each variant's model in the report's views with `neumip_path` (64 spp, seed 0, the
report's film) and scores it against the report's reference R (the mean of its two 256-spp seeds,
read from a copy of a report's render cache, or rendered into it): linear MSE, FLIP, and the mean and
99th-percentile luminance over R's. Every camera is placed for the 64^2 finest resolution (``--camera-res``)
so that a 128^2 variant is seen from the same place as a 64^2 one. One JSON line per (variant, view)
is appended to --out; ``--table`` prints them, with N0 / N ratios where a no-offset twin exists.

    # the report's reference renders (read-only in the report's run): copy them first
    cp -r runs/report-final/renders runs/renders
    .venv/bin/python benchmarks/image_levers.py train --data data/rock --runs runs/levers base nooffset yuv
    .venv/bin/python benchmarks/image_levers.py score --material rock --runs runs/levers --cache runs/renders \\
        base nooffset yuv --out benchmarks/results/image_levers.jsonl
    .venv/bin/python benchmarks/image_levers.py --table benchmarks/results/image_levers.jsonl
    # query space: the same model files against a low-noise reference set
    .venv/bin/python benchmarks/image_levers.py query --ref data/rock_ref runs/levers/base/rock.onnx ...

Data variants are folders next to --data: ``_hemi`` (``neumip generate ... --directions solid_angle``),
``_z40`` (``--heavy-fraction 0.3``: 40 % of queries at sigma = 0), ``_r128`` (``--resolution 128``).
benchmarks/results/image_levers.txt has every command and figure of the last run.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from neumip.core.config import MaterialConfig  # noqa: E402
from neumip.training.train_config import PRESETS  # noqa: E402

SHIP = replace(PRESETS["ship"], validate_every=0)
RECIPE = {"resolution": 64, "hidden": 25, "offset_min_cos": 0.6}
"""The architecture the variants change one thing of: the shipped models'."""


def relmse(pred, target, eps: float = 0.01):
    """(N, 3), (N, 3) -> scalar relative MSE (pred - target)^2 / (pred + eps)^2, the denominator held
    constant (Noise2Noise's HDR loss): unbiased under zero-mean target noise, unlike a log-space loss."""
    scale = pred.detach().clamp(min=0.0) + eps
    return ((pred - target) ** 2 / (scale * scale)).mean()


VARIANTS: dict[str, tuple[dict, object, str]] = {
    # name: (MaterialConfig overrides, TrainConfig, data folder suffix: "" = --data itself)
    "base": ({}, SHIP, ""),
    "nooffset": ({"offset": False}, SHIP, ""),
    "seed1": ({}, replace(SHIP, seed=1), ""),  # run-to-run spread of the measurement itself
    "yuv": ({"head": "yuv"}, SHIP, ""),
    "mincos0.3": ({"offset_min_cos": 0.3}, SHIP, ""),
    "mincos0.15": ({"offset_min_cos": 0.15}, SHIP, ""),
    "hemi_mincos0.3": ({"offset_min_cos": 0.3}, SHIP, "_hemi"),
    "mincos0.3_seed1": ({"offset_min_cos": 0.3}, replace(SHIP, seed=1), ""),
    "hidden48_mincos0.3": ({"hidden": 48, "offset_min_cos": 0.3}, SHIP, ""),
    "hidden48_mincos0.3_seed1": ({"hidden": 48, "offset_min_cos": 0.3}, replace(SHIP, seed=1), ""),
    "hidden48_nooffset": ({"hidden": 48, "offset": False}, SHIP, ""),
    "hidden64_mincos0.3": ({"hidden": 64, "offset_min_cos": 0.3}, SHIP, ""),
    "mse": ({}, replace(SHIP, loss="mse"), ""),
    "relmse": ({}, SHIP, ""),  # trains with `relmse` (see `train`)
    "hemi": ({}, SHIP, "_hemi"),
    "hemi_nooffset": ({"offset": False}, SHIP, "_hemi"),
    "ch12": ({"channels": 12}, SHIP, ""),
    "hidden48": ({"hidden": 48}, SHIP, ""),
    "hidden48_seed1": ({"hidden": 48}, replace(SHIP, seed=1), ""),
    "hemi_ch12": ({"channels": 12}, SHIP, "_hemi"),
    "z40": ({}, SHIP, "_z40"),  # data: 40 % of queries at sigma = 0 (heavy_fraction 0.3), not 10 %
    "z40_seed1": ({}, replace(SHIP, seed=1), "_z40"),
    "z40_nooffset": ({"offset": False}, SHIP, "_z40"),
    "z40_mincos0.3": ({"offset_min_cos": 0.3}, SHIP, "_z40"),
    "res128_d64": ({"resolution": 128}, SHIP, ""),
    "res128": ({"resolution": 128}, SHIP, "_r128"),
    "res128_nooffset": ({"offset": False, "resolution": 128}, SHIP, "_r128"),
}

VIEW_NAMES = ("level0", "level2", "low_light", "grazing75", "grazing85")
SPP, SEED = 64, 0


def model_path(runs: Path, variant: str, material: str) -> Path:
    overrides = VARIANTS[variant][0]
    name = material if overrides.get("offset", True) else f"{material}_nooffset"
    return runs / variant / f"{name}.onnx"


def train(variant: str, data: str, runs: Path, threads: int) -> None:
    import torch

    from neumip.training.export import export_material
    from neumip.training.train import Trainer

    torch.set_num_threads(threads)
    overrides, config, suffix = VARIANTS[variant]
    if variant.startswith("relmse"):
        import neumip.training.train as T

        T.training_loss = lambda pred, target, _config: relmse(pred, target)
    data = data.rstrip("/") + suffix
    material = MaterialConfig(**{**RECIPE, **overrides})
    out = model_path(runs, variant, Path(data.removesuffix(suffix)).name)
    checkpoint = runs / variant / "checkpoint.pt"
    trainer = Trainer(data, checkpoint, material, config)
    start = time.perf_counter()
    held = trainer.run()
    seconds = time.perf_counter() - start
    held["train_seconds"] = round(seconds, 1)
    export_material(trainer.material, out, f"image_levers {variant}", held)
    checkpoint.unlink(missing_ok=True)
    print(f"{variant}: trained in {seconds:.0f} s, held-out MSE {held['overall']['mse'] * 1e3:.4f}e-3 -> {out}",
          flush=True)


def score(variants: list[str], material: str, runs: Path, cache_dir: str, camera_res: int, out: str) -> None:
    from neumip.client.local import LocalMaterials
    from neumip.training.microgeometry.description import find_description, resolve
    from neumip.training.report import metrics as Q
    from neumip.training.report.cache import RenderCache
    from neumip.training.report.config import FULL
    from neumip.training.report.pipeline import REFERENCE_SEEDS
    from neumip.training.report.renderer import MaterialRenderer
    from neumip.training.report.views import VIEWS

    desc = find_description(material)  # a library name or a .toml description
    geo, material = resolve(desc), desc.name
    cache = RenderCache(cache_dir)
    views = [v for v in VIEWS if v.name in VIEW_NAMES]
    references = {}
    for variant in variants:
        path = model_path(runs, variant, material)
        ev = LocalMaterials(path.parent, threads=FULL.threads)
        # MaterialRenderer wants MATERIAL.onnx; a no-offset variant is its own "N" here
        name = path.stem
        renderer = MaterialRenderer(name, desc, geo, path.parent, ev, FULL, cache)
        renderer.resolution = camera_res  # the same cameras for every finest resolution
        held = json.loads(ev.get(name).metadata.get("neumip.validation", "{}") or "{}") \
            if hasattr(ev.get(name), "metadata") else {}
        for view in views:
            if view.name not in references:
                refr = MaterialRenderer(material, desc, geo, path.parent, ev, FULL, cache) \
                    if (path.parent / f"{material}.onnx").exists() else renderer
                refr.resolution = camera_res
                refs = [refr.render(view, "R", FULL.reference_spp, s)[0] for s in REFERENCE_SEEDS]
                refr.release()
                references[view.name] = (refs[0] + refs[1]) / 2
            ref = references[view.name]
            start = time.perf_counter()
            image = renderer.render(view, "N", SPP, SEED)[0]
            seconds = time.perf_counter() - start
            renderer.release()
            s, _ = Q.score(ref, image, Q.exposure_for(ref))
            row = {"material": material, "variant": variant, "view": view.name, "mse": s.mse, "flip": s.flip,
                   "mean_ratio": s.mean_ratio, "p99_ratio": s.p99_ratio,
                   "train_seconds": held.get("train_seconds"), "render_seconds": round(seconds, 1)}
            with open(out, "a") as f:
                f.write(json.dumps(row) + "\n")
            print(f"{variant:<16} {view.name:<10} MSE {s.mse * 1e3:.3f}e-3 FLIP {s.flip:.3f} "
                  f"mean {row['mean_ratio']:.3f} p99 {row['p99_ratio']:.3f}", flush=True)


def query_space(ref: str, models: list[str]) -> None:
    """MSE of each model file against a low-noise reference query set: overall, per level (64^2
    binning), views beyond 70 degrees (wo), lights beyond 75 degrees (wi) with their mean and
    99th-percentile luminance over the reference's."""
    from neumip.core import contract as C
    from neumip.client.local import LocalMaterials
    from neumip.training.dataset import open_dataset
    from neumip.training.validation import validation_table

    data = open_dataset(ref)
    q, t = np.asarray(data.queries), np.asarray(data.rgb)
    weights = np.array([0.2126, 0.7152, 0.0722])
    zenith = {k: np.degrees(np.arcsin(np.minimum(1, np.hypot(q[:, x], q[:, y]))))
              for k, (x, y) in {"wi": (C.WI_X, C.WI_Y), "wo": (C.WO_X, C.WO_Y)}.items()}
    grazing, low = zenith["wo"] > 70, zenith["wi"] > 75
    print(f"== against {ref}: MSE x1e-3; wi>75: mean and p99 luminance / reference's")
    print(f"{'model':<40} {'all':>6} {'L0':>6} {'L1':>6} {'L2':>6} {'wo>70':>6} {'wi>75':>6} {'mean':>6} {'p99':>6}")
    for path in map(Path, models):
        p = LocalMaterials(path.parent, threads=1).evaluate(path.stem, q)
        levels = {r["level"]: r["mse"] for r in validation_table(p, t, q[:, C.SIGMA], 64)["levels"]}
        lp, lt = p[low] @ weights, t[low] @ weights
        cells = [np.mean((p - t) ** 2), levels[0], levels[1], levels[2], np.mean((p[grazing] - t[grazing]) ** 2),
                 np.mean((p[low] - t[low]) ** 2)]
        print(f"{str(path):<40} " + " ".join(f"{c * 1e3:6.3f}" for c in cells)
              + f" {lp.mean() / lt.mean():6.3f} {np.percentile(lp, 99) / np.percentile(lt, 99):6.3f}", flush=True)


def speed(models: list[str], rounds: int = 5, n: int = 1 << 18) -> None:
    """Seconds per n random queries of each model file on one ONNX Runtime thread, interleaved
    round by round, median of the rounds (the cost of a wider MLP per query)."""
    from neumip.core.contract import random_queries
    from neumip.client.local import LocalMaterials

    q = random_queries(n, seed=0, max_zenith_deg=80.0)
    evaluators = [(Path(m), LocalMaterials(Path(m).parent, threads=1)) for m in models]
    times: dict = {m: [] for m, _ in evaluators}
    for _ in range(rounds):
        for path, ev in evaluators:
            start = time.perf_counter()
            ev.evaluate(path.stem, q)
            times[path].append(time.perf_counter() - start)
    base = np.median(times[evaluators[0][0]])
    for path, t in times.items():
        print(f"{str(path):<40} {np.median(t):.3f} s per {n} queries ({np.median(t) / base:.2f}x the first), "
              f"load average {os.getloadavg()[0]:.1f}")


def no_offset_twin(variant: str) -> str:
    """The variant without the offset that `variant` is compared with: the same name with the
    offset-only settings (mincos) dropped, plus _nooffset ('base' -> 'nooffset')."""
    kept = [t for t in variant.split("_") if not t.startswith("mincos") and t != "base"]
    return "_".join(kept + ["nooffset"])


def print_table(path: str) -> None:
    rows = {}
    for line in Path(path).read_text().splitlines():
        if line.strip():
            r = json.loads(line)
            rows[(r["material"], r["variant"], r["view"])] = r  # the last line of a pair wins
    for material in dict.fromkeys(k[0] for k in rows):
        variants = list(dict.fromkeys(k[1] for k in rows if k[0] == material))
        print(f"\n== {material}: MSE x1e-3 / FLIP per view, 64 spp; low_light: mean and p99 luminance / R's; "
              "offset: N0 MSE / N MSE")
        print(f"{'variant':<16} " + " ".join(f"{v:>15}" for v in VIEW_NAMES)
              + f" {'LL mean':>7} {'LL p99':>7} {'off L0':>6} {'off L2':>6} {'off LL':>6}")
        for variant in variants:
            cells, extra = [], []
            for v in VIEW_NAMES:
                r = rows.get((material, variant, v))
                cells.append(f"{r['mse'] * 1e3:>7.3f}/{r['flip']:.3f}" if r else f"{'-':>15}")
            ll = rows.get((material, variant, "low_light"))
            extra = [f"{ll['mean_ratio']:>7.3f}", f"{ll['p99_ratio']:>7.3f}"] if ll else [f"{'-':>7}"] * 2
            twin = no_offset_twin(variant)
            for v in ("level0", "level2", "low_light"):
                a, b = rows.get((material, variant, v)), rows.get((material, twin, v))
                extra.append(f"{b['mse'] / a['mse']:>6.2f}" if a and b else f"{'-':>6}")
            print(f"{variant:<16} " + " ".join(cells) + " " + " ".join(extra))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--table", metavar="JSONL")
    sub = parser.add_subparsers(dest="command")
    p = sub.add_parser("train")
    p.add_argument("variants", nargs="+", choices=tuple(VARIANTS))
    p.add_argument("--data", required=True)
    p.add_argument("--runs", default="runs/levers")
    p.add_argument("--threads", type=int, default=1)
    p = sub.add_parser("query")
    p.add_argument("models", nargs="+", help="model files")
    p.add_argument("--ref", required=True, help="low-noise reference data set (neumip generate ... --spp 256)")
    p = sub.add_parser("speed")
    p.add_argument("models", nargs="+", help="model files (the first is the baseline)")
    p = sub.add_parser("score")
    p.add_argument("variants", nargs="+", choices=tuple(VARIANTS))
    p.add_argument("--material", required=True)
    p.add_argument("--runs", default="runs/levers")
    p.add_argument("--cache", required=True, help="render cache folder (a copy of a report's renders)")
    p.add_argument("--camera-res", type=int, default=64)
    p.add_argument("--out", default="benchmarks/results/image_levers.jsonl")
    args = parser.parse_args()
    if args.table:
        print_table(args.table)
    elif args.command == "train":
        for variant in args.variants:
            train(variant, args.data, Path(args.runs), args.threads)
    elif args.command == "query":
        query_space(args.ref, args.models)
    elif args.command == "speed":
        speed(args.models)
    elif args.command == "score":
        score(args.variants, args.material, Path(args.runs), args.cache, args.camera_res, args.out)
    else:
        parser.error("give --table, train or score")


if __name__ == "__main__":
    main()
