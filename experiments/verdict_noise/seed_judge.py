"""Can a model's own answers tell which of two training runs got the far views' brightness right? A screen for picking
a seed (`fit --seeds`) by a judge that needs no ground truth at fit time.

    .venv/bin/python experiments/verdict_noise/seed_judge.py turtle runs/rs/ctl runs/cd/ctl1 --views level6_high ...

Each run's coarse levels drift from its finest level in brightness, direction by direction, where the finest level is
within 0.1-2.5 % of the tracer (`direction_check.py`); the drift swings from run to run (turtle's side view at 256
texels, the model's brightness over the tracer's: 1.091 and 1.025 at seeds 0 and 1). The judge: over random pairs of directions (uniform on the projected disc)
and footprints of 2-256 texels (the samples of the 16-256-texel views read an eighth of their pixel's), the rms of
log(finest level's tile mean / the tile mean at the footprint), in luminance, each tile mean over `--positions` random
positions; the finest level reads a quarter texel. The truth it stands for: the same rms with the ground-truth
tracer's tile mean (one sample a position) in place of the finest level's, and the named report views' pixel
luminance against the tracer's (`tile_mean_gain.py`'s "as is"). Every model is scored on the same pairs, positions
and tracer samples. Printed: the truth's own noise (two tracer estimates' log ratio over the square root of 2); per
model, the judge, the truth, the finest level's truth (its tile means against the tracer's: what coarse levels that
followed it would score), the close-ups' error (the MSE of log1p answers, as `fit --seeds` judges, against the
tracer at 64 samples on `--queries` random queries at 0.5-4 texels), and the views' mean |model / tracer - 1|. `--no-table`: the models with their energy
tables' gains set to 1.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from direction_check import LUM, pixel_luminance, view_rows, without_table  # this folder's
from tile_mean_gain import TEACHER_TEXELS
from neumip.core import contract as C
from neumip.engines.kernel import KernelMaterials
from neumip.engines.local import run_chunked
from neumip.groundtruth.description import find_description, resolve
from neumip.groundtruth.tracer import QueryTracer
from neumip.report.views import VIEWS


def tile_rows(pairs: int, positions: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random direction pairs, each repeated at `positions` random positions -> (rows without sigma, log2 texels)."""
    q = C.random_queries(pairs, seed=int(rng.integers(1 << 30)), u_range=(0.0, 1.0))
    rows = np.repeat(q, positions, 0)
    rows[:, C.U], rows[:, C.V] = rng.random(len(rows)), rng.random(len(rows))
    return rows, rng.uniform(1.0, 8.0, pairs)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("material")
    parser.add_argument("models", nargs="+", type=Path, help="folders holding NAME.onnx")
    parser.add_argument("--views", nargs="*", default=[])
    parser.add_argument("--pairs", type=int, default=4096)
    parser.add_argument("--positions", type=int, default=2048)
    parser.add_argument("--queries", type=int, default=16384, help="a view's queries (as direction_check.py), and the close-ups'")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-table", action="store_true", help="the models without their energy tables (gains of 1)")
    args = parser.parse_args()
    desc = find_description(args.material)
    name, resolution = desc.name, desc.resolution
    tracer = QueryTracer(resolve(desc))
    rng = np.random.default_rng(args.seed)
    rows, log_texels = tile_rows(args.pairs, args.positions, rng)
    rms = lambda a: float(np.sqrt(np.mean(a**2)))  # noqa: E731
    far = log_texels >= 4.0  # footprints of 16-256 texels: the coarsest levels
    tile = lambda a: (a.astype(np.float64) @ LUM).reshape(args.pairs, args.positions).mean(1)  # noqa: E731
    fine, coarse = rows.copy(), rows.copy()
    fine[:, C.SIGMA] = TEACHER_TEXELS / resolution
    coarse[:, C.SIGMA] = np.repeat(2.0**log_texels / resolution, args.positions)
    truth = tile(tracer.estimate(coarse, 1, int(rng.integers(1 << 30))))
    again = tile(tracer.estimate(coarse, 1, int(rng.integers(1 << 30))))  # the truth's own noise: a second estimate
    near = C.random_queries(args.queries, seed=int(rng.integers(1 << 30)), u_range=(0.0, 1.0),
                            log2_sigma_range=(math.log2(0.5 / resolution), math.log2(4.0 / resolution)))
    near_truth = np.log1p(tracer.estimate(near, 64, int(rng.integers(1 << 30))).astype(np.float64))
    views = []
    by_name = {v.name: v for v in VIEWS}
    for view_name in args.views:
        direct, env = view_rows(by_name[view_name], resolution, args.queries, rng)
        views.append((view_name, direct, env, pixel_luminance(lambda q: tracer.estimate(q, 64, 11), direct, env)))
    noise = np.log(np.maximum(truth, 1e-9) / np.maximum(again, 1e-9)) / math.sqrt(2)
    print(f"{name}: {args.pairs} pairs x {args.positions} positions at 2-256 texels (far: 16-256), seed {args.seed}; "
          f"the truth's own noise rms {rms(noise):.4f} (far {rms(noise[far]):.4f})")
    for folder in args.models:
        materials = KernelMaterials(without_table(folder, name) if args.no_table else folder)
        model = lambda q: run_chunked(lambda r: materials.evaluate(name, r), q, 1 << 20)  # noqa: E731
        at = tile(model(coarse))
        finest = np.maximum(tile(model(fine)), 1e-9)
        judge = np.log(finest / np.maximum(at, 1e-9))
        error = np.log(np.maximum(truth, 1e-9) / np.maximum(at, 1e-9))
        floor = np.log(np.maximum(truth, 1e-9) / finest)  # what a model whose coarse levels follow its finest would score
        line = (f"  {str(folder):<28} judge rms {rms(judge):.4f} (far {rms(judge[far]):.4f})  "
                f"truth rms {rms(error):.4f} (far {rms(error[far]):.4f}), finest level's {rms(floor):.4f}  "
                f"near log MSE {np.mean((np.log1p(model(near).astype(np.float64)) - near_truth) ** 2) * 1e3:.3f}e-3")
        if views:
            ratios = [pixel_luminance(model, d, e) / t for _, d, e, t in views]
            line += f"  views |model/tracer - 1| mean {np.mean(np.abs(np.array(ratios) - 1)):.4f} ("
            line += ", ".join(f"{v} {r:.3f}" for (v, *_), r in zip(views, ratios)) + ")"
        print(line, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
