"""Would a correction with the directions' full resolution take the far views' brightness error out? A screen, on
the model's answers alone (nothing rendered, nothing in the product).

    .venv/bin/python experiments/verdict_noise/tile_mean_gain.py turtle level8_side level6_front level8_high

A tile's mean answer is the same at every footprint, and the model's finest level gets it within 0.1-2.5 % of the
tracer where its coarse levels are 1-9 % off (`direction_check.py`). Here a small MLP g(wi, wo, log2 footprint) -> RGB
log-gain is fitted to log(finest tile mean / tile mean at the footprint) over random pairs of directions (uniform on
the projected disc to 85 degrees) and footprints of 2-256 texels, each tile mean over `--positions` random
positions (the same ones for both), and blended in from 2 texels (w = clamp(log2 texels - 1, 0, 1)); nothing changes
below. Printed: the fit's error on pairs it did not see, and for each named report view the `direction_check.py`
lines of the model as it is and corrected.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from direction_check import pixel_luminance, unit_directions, view_rows  # this folder's
from neumip.core import contract as C
from neumip.engines.kernel import KernelMaterials
from neumip.engines.local import run_chunked
from neumip.groundtruth.description import find_description, resolve
from neumip.groundtruth.tracer import QueryTracer
from neumip.report.views import VIEWS

TEACHER_TEXELS = 0.25


def features(wi: np.ndarray, wo: np.ndarray, log_texels: np.ndarray) -> torch.Tensor:
    """(n, 3) wi, wo and (n,) log2 footprint in texels -> (n, 10) inputs: wi, wo, their half vector, the footprint."""
    h = wi + wo
    h = h / np.linalg.norm(h, axis=1, keepdims=True)
    return torch.from_numpy(np.concatenate([wi, wo, h, (log_texels / 8.0)[:, None]], 1).astype(np.float32))


def blend(log_texels: np.ndarray) -> np.ndarray:
    return np.clip(log_texels - 1.0, 0.0, 1.0)


def tile_means(model, pairs: int, positions: int, resolution: int, rng, tracer=None) -> tuple:
    """Random direction pairs and footprints -> (wi, wo, log2 texels, log(teacher mean / mean at the footprint)); with
    `tracer`, the teacher is the tracer's mean at the footprint (one sample a position) instead of the finest level's."""
    q = C.random_queries(pairs, seed=int(rng.integers(1 << 30)), u_range=(0.0, 1.0))
    wi = unit_directions(q[:, C.WI_X:C.WI_Y + 1].astype(np.float64))
    wo = unit_directions(q[:, C.WO_X:C.WO_Y + 1].astype(np.float64))
    log_texels = rng.uniform(1.0, 8.0, pairs)
    rows = np.repeat(q, positions, 0)
    rows[:, C.U], rows[:, C.V] = rng.random(len(rows)), rng.random(len(rows))
    rows[:, C.SIGMA] = TEACHER_TEXELS / resolution
    if tracer is None:
        teacher = model(rows).astype(np.float64).reshape(pairs, positions, 3).mean(1)
    rows[:, C.SIGMA] = np.repeat(2.0**log_texels / resolution, positions)
    if tracer is not None:
        teacher = tracer.estimate(rows, 1, int(rng.integers(1 << 30))).astype(np.float64).reshape(pairs, positions, 3).mean(1)
    coarse = model(rows).astype(np.float64).reshape(pairs, positions, 3).mean(1)
    target = np.log(np.maximum(teacher, 1e-6) / np.maximum(coarse, 1e-6))
    return wi, wo, log_texels, target


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("material")
    parser.add_argument("views", nargs="*")
    parser.add_argument("--models", type=Path, default=Path("models"))
    parser.add_argument("--pairs", type=int, default=16384)
    parser.add_argument("--positions", type=int, default=2048)
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--steps", type=int, default=8000)
    parser.add_argument("--queries", type=int, default=16384)
    parser.add_argument("--seed", type=int, default=0, help="the pairs', positions' and fit's seed")
    parser.add_argument("--tracer", action="store_true",
                        help="fit to the ground-truth tracer's tile means (one sample a position) instead of the finest level's")
    args = parser.parse_args()
    desc = find_description(args.material)
    materials = KernelMaterials(args.models)
    name, resolution = desc.name, desc.resolution

    def model(q: np.ndarray) -> np.ndarray:
        return run_chunked(lambda rows: materials.evaluate(name, rows), q, 1 << 20)

    rng = np.random.default_rng(args.seed)
    torch.manual_seed(args.seed)
    tracer = QueryTracer(resolve(desc))
    teacher = tracer if args.tracer else None
    wi, wo, lt, target = tile_means(model, args.pairs, args.positions, resolution, rng, teacher)
    hwi, hwo, hlt, htarget = tile_means(model, args.pairs // 4, args.positions, resolution, rng, teacher)
    g = torch.nn.Sequential(torch.nn.Linear(10, args.hidden), torch.nn.ReLU(), torch.nn.Linear(args.hidden, args.hidden),
                            torch.nn.ReLU(), torch.nn.Linear(args.hidden, 3))
    x, y = features(wi, wo, lt), torch.from_numpy(target.astype(np.float32))
    hx, hy = features(hwi, hwo, hlt), torch.from_numpy(htarget.astype(np.float32))
    opt = torch.optim.Adam(g.parameters(), lr=3e-3)
    for step in range(args.steps):
        batch = torch.randint(0, len(x), (4096,))
        loss = ((g(x[batch]) - y[batch]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        held = g(hx)
    rms = lambda a: float(torch.sqrt((a**2).mean()))  # noqa: E731
    print(f"{name}: {args.pairs} pairs x {args.positions} positions, MLP {args.hidden} wide, seed {args.seed}, "
          f"teacher: {'the tracer' if args.tracer else 'finest level'}; log(teacher / coarse) rms {rms(hy):.4f} on held-out "
          f"pairs, after the fit {rms(held - hy):.4f} (the positions' own noise included)")

    def corrected(q: np.ndarray) -> np.ndarray:
        lt_q = np.log2(np.maximum(q[:, C.SIGMA] * resolution, 1e-6))
        with torch.no_grad():
            gain = np.exp(g(features(unit_directions(q[:, C.WI_X:C.WI_Y + 1].astype(np.float64)),
                                     unit_directions(q[:, C.WO_X:C.WO_Y + 1].astype(np.float64)), lt_q)).numpy())
        return model(q) * (1 + blend(lt_q)[:, None] * (gain - 1))

    by_name = {v.name: v for v in VIEWS}
    rng = np.random.default_rng(12345)  # the views' queries: the same whatever the fit's seed
    for view_name in args.views:
        direct, env = view_rows(by_name[view_name], resolution, args.queries, rng)
        t = pixel_luminance(lambda q: tracer.estimate(q, 64, 11), direct, env)
        line = [f"{label} {pixel_luminance(m, direct, env) / t:.3f}" for label, m in (("as is", model), ("corrected", corrected))]
        print(f"  {view_name}: pixel luminance model / tracer: " + ", ".join(line))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
