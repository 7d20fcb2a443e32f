"""How good a teacher a model's own fine footprints are for its coarse ones: on a reference data set (a `neumip
generate` set traced with many samples), per level of detail, the model's direct answers and the mean of its
answers at a finer footprint over K aim points jittered across the rest of the query's (Gaussians compose: the
targets `neumip fit --distil K` trains on, `training/loop/distil.py`), each
against the reference: mean and 99th-percentile luminance ratio (reference / answer; > 1: darker) and MSE.

    neumip generate turtle -o runs/uref/turtle --queries 16384 --spp 256 --seed 1 --resolution 256 \\
        --directions solid_angle --max-zenith 85 --level-fraction 1.0 --heavy-fraction 0 --sub-texel-levels 1
    .venv/bin/python experiments/distil/teacher.py runs/uref/turtle models/turtle.onnx --samples 32 --texels 1

A level is floor(log2(sigma R) + lod_bias) of the model's config, as experiments/level_share/brightness.py counts.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def main() -> None:
    from neumip.core import contract as C
    from neumip.core.config import MaterialConfig
    from neumip.engines.local import load_material
    from neumip.groundtruth.dataset import open_dataset
    from neumip.training.loop.distil import distilled_targets

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reference")
    p.add_argument("model")
    p.add_argument("--samples", type=int, default=32, help="aim points a query (even: antithetic pairs)")
    p.add_argument("--texels", type=float, default=1.0, help="the finer footprint sigma, in finest texels")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--min-cos-light", type=float, default=0.0,
                   help="only the reference's queries whose light has wi_z at least this (0.2: above 11.5 degrees)")
    args = p.parse_args()
    data = open_dataset(args.reference)
    q, t = np.array(data.queries), np.asarray(data.rgb, np.float64) @ LUMINANCE
    keep = np.sqrt(np.maximum(1.0 - (q[:, C.WI_X:C.WI_Y + 1].astype(np.float64) ** 2).sum(1), 0.0)) >= args.min_cos_light
    q, t = q[keep], t[keep]
    material = load_material(args.model)
    config = material.config if isinstance(material.config, MaterialConfig) else MaterialConfig.from_dict(material.config)
    res = config.resolution
    level = np.clip(np.floor(np.log2(np.maximum(q[:, C.SIGMA], 1e-12) * res) + config.lod_bias), 0,
                    config.levels).astype(int)
    direct = material.run(q).astype(np.float64) @ LUMINANCE

    def answer(sub: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(material.run(sub.numpy()))

    # the training's own distilled targets (`--distil`), at every level
    taught = distilled_targets(answer, torch.from_numpy(q), args.samples, torch.Generator().manual_seed(args.seed),
                               args.texels / res).numpy().astype(np.float64) @ LUMINANCE
    print(f"{args.reference} against {args.model}: the finer footprint {args.texels} texel(s), {args.samples} "
          f"aim points; {len(q)} queries with wi_z >= {args.min_cos_light}; reference / answer, mean [p99]; MSE x1e-3")
    print("level  queries     direct mean [p99]    taught mean [p99]   MSE direct  MSE taught")
    for lv in range(config.levels + 1):
        rows = level == lv
        if rows.sum() < 100:
            continue
        cells = []
        for a in (direct, taught):
            cells.append(f"{t[rows].mean() / a[rows].mean():7.3f} [{np.percentile(t[rows], 99) / np.percentile(a[rows], 99):6.3f}]")
        mse = [np.mean((t[rows] - a[rows]) ** 2) * 1e3 for a in (direct, taught)]
        print(f"{lv:5d}  {rows.sum():7d}  {cells[0]:>19s}  {cells[1]:>19s}  {mse[0]:10.3f}  {mse[1]:10.3f}")


if __name__ == "__main__":
    main()
