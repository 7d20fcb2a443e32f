"""The energy table's coarse cells refitted: to the model's own finest level, averaged over the footprint (a target
without the coarse data's noise), or with `--data` to a calibration data set of their own.

    .venv/bin/python experiments/energy/teacher_table.py MODEL OUT [--from-level 3] [--queries 400000] [--samples 32]
    .venv/bin/python experiments/energy/teacher_table.py MODEL OUT --data DATA [--prior 256]

With `--data`, the cells from `--from-level` up are fitted on the data set's queries at those levels and their
targets (made apart from the training data: `neumip generate M -o DATA --queries 4000000 --spp 64
--level-fraction 1.0 --heavy-fraction 0 --seed 11`: levels uniform, where the training data put most queries at the
finest level), with `--prior` queries' worth of right answers a cell (the product's 256).

A query at footprint sigma answers the material filtered by a Gaussian of std sigma. Gaussians compose, so that is
also the mean of its answers at the finest footprint sigma' over aim points jittered by sqrt(sigma^2 - sigma'^2)
(`training/loop/distil.py`'s `distilled_targets`, here with the model file's own answers through ONNX Runtime,
its table included). The finest level is fitted to most of the data, whose targets there are quiet, and averaged so
it was closer to a 256-sample reference than the coarse levels' own answers ([distil](../distil/)). Here the table's
cells from level `--from-level` up are refitted (`model.energy.fit_energy`, the product's fit, on random queries at
those levels: u, v uniform over the tile, directions uniform on the projected disc to 85 degrees) with that mean as
the target; the cells below keep the file's table, so close-ups read the same gains. The model at OUT is reported as
its control was (`neumip report --materials M --models DIR --skip stability tradeoff`).
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np
import onnx
import torch

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.engines.local import load_material, run_chunked
from neumip.training.export.graph import build_onnx, save_onnx
from neumip.training.export.read import read_model
from neumip.training.loop.distil import distilled_targets
from neumip.groundtruth.dataset import open_dataset
from neumip.training.model.energy import ENERGY_PRIOR, fit_energy, ones_table
from neumip.training.model.pyramid import level_of_detail


def coarse_queries(n: int, resolution: int, lod_bias: int, from_level: float, seed: int) -> np.ndarray:
    """(n, 7) queries with u, v uniform over the tile, the level of detail uniform in [from_level - 0.5, log2 R]
    (so the cells at `from_level` get their share of the trilinear weights) and wi, wo uniform on the projected
    disc up to 85 degrees."""
    q = C.random_queries(n, seed=seed, u_range=(0.0, 1.0))
    rng = np.random.default_rng([seed, 1])
    lod = rng.uniform(max(from_level - 0.5, 0.0), math.log2(resolution), n)
    q[:, C.SIGMA] = (2.0 ** lod / (resolution * 2.0 ** lod_bias)).astype(np.float32)
    return q


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("out")
    parser.add_argument("--from-level", type=int, default=3, help="the first level whose cells are refitted")
    parser.add_argument("--queries", type=int, default=400_000)
    parser.add_argument("--samples", type=int, default=32, help="finest-level answers averaged a query (even)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", help="a calibration data set: fit to its targets instead of the teacher")
    parser.add_argument("--prior", type=float, default=None, help="the fit's prior (default: the product's)")
    parser.add_argument("--bins", type=int, default=0,
                        help="a table of B half-vector and elevation bins instead of the file's: every level refitted, "
                             "the levels below --from-level to the file's own answers (its table), the rest to the teacher")
    args = parser.parse_args()
    config, weights, meta, finest = read_model(onnx.load(args.model), args.model)
    if not config.energy_bins:
        raise SystemExit(f"{args.model} has no energy table")
    owned = {C.META_CONTRACT, C.META_CONFIG, C.META_DESCRIPTION}
    rest = {k: v for k, v in meta.items() if k not in owned}

    def model(table: np.ndarray, table_config=config) -> onnx.ModelProto:
        return build_onnx(table_config, {**weights, W.ENERGY: table}, meta.get(C.META_DESCRIPTION, ""), rest)

    def answers(graph: onnx.ModelProto, queries: np.ndarray) -> np.ndarray:
        material = load_material(args.model, data=graph.SerializeToString())
        return run_chunked(material.run, np.ascontiguousarray(queries, np.float32))

    shipped = weights[W.ENERGY]
    as_is = model(shipped)
    if args.bins:
        return finer_table(args, config, as_is, answers, model)
    if args.data:
        data = open_dataset(args.data)
        lod = level_of_detail(torch.from_numpy(np.asarray(data.queries[:, C.SIGMA])), config.resolution,
                              config.lod_bias).numpy()
        rows = np.flatnonzero(lod >= max(args.from_level - 0.5, 0.0))
        q, teacher = np.asarray(data.queries[rows]), np.asarray(data.rgb[rows])
        source = f"{args.data}'s {len(rows)} queries"
    else:
        q = coarse_queries(args.queries, config.resolution, config.lod_bias, args.from_level, args.seed)
        finer = 1.0 / (config.resolution * 2.0 ** config.lod_bias)  # the finest level's footprint
        teacher = distilled_targets(lambda x: torch.from_numpy(answers(as_is, x.numpy())), torch.from_numpy(q),
                                    args.samples, torch.Generator().manual_seed(args.seed), finer).numpy()
        source = f"{args.queries} queries, {args.samples} finest answers each"
    plain = answers(model(ones_table(config)), q)
    prior = ENERGY_PRIOR if args.prior is None else args.prior
    fitted = fit_energy(config, torch.from_numpy(np.asarray(q, np.float32)), torch.from_numpy(plain),
                        torch.from_numpy(np.asarray(teacher, np.float32)), prior=prior).numpy()
    rows_a_level = len(shipped) // (config.levels + 1)
    table = shipped.copy()
    table[args.from_level * rows_a_level:] = fitted[args.from_level * rows_a_level:]
    direct = answers(as_is, q)
    lum = np.asarray(C.LUMINANCE)
    print(f"{args.model}: {source} at levels {max(args.from_level - 0.5, 0):g}-{config.levels}, prior {prior:g}; "
          f"the targets' mean luminance / the model's as is "
          f"{float((teacher @ lum).mean() / (direct @ lum).mean()):.4f}; refitted cells' gains "
          f"{fitted[args.from_level * rows_a_level:].min():.3f}-{fitted[args.from_level * rows_a_level:].max():.3f}, "
          f"the file's {shipped[args.from_level * rows_a_level:].min():.3f}-{shipped[args.from_level * rows_a_level:].max():.3f}")
    save_onnx(model(table), args.out)
    print(f"wrote {args.out}")
    return 0


def finer_table(args, config, as_is, answers, model) -> int:
    """`--bins`: the whole table at another number of bins, each query's target the file's own answer below
    `--from-level` and the teacher's (its finest level averaged over the footprint) from there."""
    config = dataclasses.replace(config, energy_bins=args.bins)
    q = coarse_queries(args.queries, config.resolution, config.lod_bias, 0.5, args.seed)
    lod = level_of_detail(torch.from_numpy(q[:, C.SIGMA].copy()), config.resolution, config.lod_bias).numpy()
    coarse = lod >= args.from_level - 0.5
    target = answers(as_is, q)
    finer = 1.0 / (config.resolution * 2.0 ** config.lod_bias)
    target[coarse] = distilled_targets(lambda x: torch.from_numpy(answers(as_is, x.numpy())),
                                       torch.from_numpy(q[coarse]), args.samples,
                                       torch.Generator().manual_seed(args.seed), finer).numpy()
    plain = answers(model(ones_table(config), config), q)
    prior = ENERGY_PRIOR if args.prior is None else args.prior
    table = fit_energy(config, torch.from_numpy(q), torch.from_numpy(plain), torch.from_numpy(target),
                       prior=prior).numpy()
    print(f"{args.model}: {args.bins} bins, {len(q)} queries ({int(coarse.sum())} from level {args.from_level - 0.5:g} "
          f"to the teacher), prior {prior:g}; gains {table.min():.3f}-{table.max():.3f}")
    save_onnx(model(table, config), args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
