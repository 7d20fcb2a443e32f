"""Does the energy table need the view's elevation as a third direction axis?

An isotropic material's answer at one footprint is a function of three directions' numbers (the light's and the
view's elevations and their azimuth apart); the shipped table (`training.model.energy`) holds two (the half vector's
angle and the light's elevation), so one cell pools views whose darkness differs. This experiment fits, on a model's
training split (`neumip calibrate`'s rows: `fit_rows`, `split_indices`), the shipped table and a table with the
view's elevation as a fourth axis (z = sqrt(wo_z) (B - 1), quadrilinear, the same prior and clamp), to the answers
of the model without a table, and scores both, and the model without a table, against the training data's own
estimator (`QueryTracer`, 16 samples a query, 20 000 random positions) at the report's view (55 degrees) under its
three lights and lights 10-20 degrees around them, at levels 3, 5, 6 and 8: the luminance of the answers' mean over
the estimator's. And the held-out split's MSE of each.

    .venv/bin/python experiments/energy/view_axis.py MATERIAL DATA MODEL_WITHOUT_TABLE [--bins 6]
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np
import torch


def corners4(config, bins: int, sigma, wi, wo):
    """The shipped corners (`energy.corners`) with a fourth axis, the view's elevation: (N, 16) rows, weights."""
    from neumip.training.model.base import half_direction, lift
    from neumip.training.model.energy import _pair, direction_coordinates
    from neumip.training.model.pyramid import level_of_detail

    x, y = direction_coordinates(half_direction(lift(wi), lift(wo)), lift(wi)[:, 2], bins)
    z = torch.clamp(torch.sqrt(lift(wo)[:, 2]) * (bins - 1), 0.0, bins - 1.0)
    (l, wl), (b, wb), (e, we), (v, wv) = (_pair(level_of_detail(sigma, config.resolution, config.lod_bias),
                                                config.levels), _pair(x, bins - 1), _pair(y, bins - 1),
                                          _pair(z, bins - 1))
    index = (((l[:, :, None, None, None] * bins + b[:, None, :, None, None]) * bins + e[:, None, None, :, None]) * bins
             + v[:, None, None, None, :]).reshape(len(x), 16)
    weight = (wl[:, :, None, None, None] * wb[:, None, :, None, None] * we[:, None, None, :, None]
              * wv[:, None, None, None, :]).reshape(len(x), 16)
    return index, weight


def corners_azimuth(config, bins: int, azimuths: int, sigma, wi, wo):
    """The shipped corners with a fourth axis, the half vector's azimuth in the tile's frame (periodic, `azimuths`
    bins over 360 degrees): (N, 16) rows, weights."""
    from neumip.training.model.base import half_direction, lift
    from neumip.training.model.energy import corners

    index3, weight3 = corners(config, sigma, wi, wo)
    h = half_direction(lift(wi), lift(wo))
    a = torch.remainder(torch.atan2(h[:, 1], h[:, 0]) / (2 * math.pi) * azimuths, azimuths)
    low = torch.floor(a)
    frac = a - low
    ends = torch.stack([low, low + 1], 1).long() % azimuths
    wa = torch.stack([1 - frac, frac], 1)
    index = (index3[:, :, None] * azimuths + ends[:, None, :]).reshape(len(a), 16)
    weight = (weight3[:, :, None] * wa[:, None, :]).reshape(len(a), 16)
    return index, weight


def fit(index, weight, rows, answers, targets, prior=256.0):
    from neumip.training.model.energy import ENERGY_RANGE

    def sums(values):
        spread = (weight.double()[:, :, None] * values[:, None, :]).reshape(-1, 3)
        return torch.zeros(rows, 3, dtype=torch.float64).index_add_(0, index.reshape(-1), spread)

    mean = answers.mean(0)
    return torch.nan_to_num((sums(targets) + prior * mean) / (sums(answers) + prior * mean), nan=1.0).clamp(*ENERGY_RANGE)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material")
    parser.add_argument("data")
    parser.add_argument("model", help="the model without a table (its answers are what the tables are fitted to)")
    parser.add_argument("--bins", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0, help="the training seed the data were split with")
    parser.add_argument("--azimuths", type=int, default=16, help="bins of the half vector's azimuth (the azimuth table)")
    args = parser.parse_args()

    from neumip.core import contract as C
    from neumip.core.config import MaterialConfig
    from neumip.engines.local import load_material
    from neumip.groundtruth.dataset import open_dataset
    from neumip.groundtruth.description import find_description, resolve
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.tracer import QueryTracer
    from neumip.training.loop.energy import fit_rows
    from neumip.training.loop.train import TrainConfig, split_indices
    from neumip.training.model.energy import corners

    model = load_material(args.model)
    config = MaterialConfig.from_dict(model.config) if isinstance(model.config, dict) else model.config
    config = dataclasses.replace(config, energy_bins=args.bins)
    data = open_dataset(args.data)
    train_idx, held_idx = split_indices(len(data), TrainConfig(seed=args.seed))
    rows = fit_rows(train_idx, args.seed)
    q, t = np.asarray(data.queries[rows]), torch.from_numpy(np.asarray(data.rgb[rows], np.float64))
    a = torch.from_numpy(model.run(q).astype(np.float64))
    print(f"{args.model}: fitted on {len(rows)} queries of {args.data}, {args.bins} bins", flush=True)

    def cells(queries, four):
        qt = torch.from_numpy(np.asarray(queries, np.float32))
        sig, wi, wo = qt[:, C.SIGMA], qt[:, C.WI_X:C.WI_Y + 1], qt[:, C.WO_X:C.WO_Y + 1]
        if four == "azimuth":
            return corners_azimuth(config, args.bins, args.azimuths, sig, wi, wo)
        return corners4(config, args.bins, sig, wi, wo) if four else corners(config, sig, wi, wo)

    tables = {}
    sizes = {False: args.bins**2, True: args.bins**3, "azimuth": args.bins**2 * args.azimuths}
    for name, four in (("3-D", False), ("4-D", True), ("azim", "azimuth")):
        index, weight = cells(q, four)
        tables[name] = (fit(index, weight, (config.levels + 1) * sizes[four], a, t), four)
        tab = tables[name][0]
        print(f"  {name} table: {tab.shape[0]} cells, gains {tab.min():.3f}-{tab.max():.3f}", flush=True)

    def answer(name, queries, raw):
        if name == "none":
            return raw
        table, four = tables[name]
        index, weight = cells(queries, four)
        return raw * (table[index] * weight[:, :, None].double()).sum(1).numpy()

    held = np.sort(np.random.default_rng(1).choice(held_idx, min(len(held_idx), 1 << 21), replace=False))
    hq, ht = np.asarray(data.queries[held]), np.asarray(data.rgb[held], np.float64)
    raw = model.run(hq).astype(np.float64)
    print("  held-out MSE x1e-3: " + ", ".join(f"{n} {np.mean((answer(n, hq, raw) - ht) ** 2) * 1e3:.4f}"
                                                  for n in ("none", "3-D", "4-D", "azim")), flush=True)

    geo = resolve(find_description(args.material))
    settings = GenerateSettings()
    tracer = QueryTracer(geo, settings.tracer, settings.tiling)
    lum = np.array([0.2126, 0.7152, 0.0722])
    rng = np.random.default_rng(0)

    def direction(zenith, azimuth):  # azimuth from the direction towards the camera (-y), as report.views
        z, az = math.radians(zenith), math.radians(azimuth)
        return math.sin(z) * math.sin(az), -math.sin(z) * math.cos(az)

    print("  the answers' mean / the estimator's (luminance), levels 3, 5, 6, 8; none 3-D 4-D azim")
    worst = {n: [] for n in ("none", "3-D", "4-D", "azim")}
    for light, (zen, az) in {"high": (20, 45), "side": (60, 90), "front": (50, 135)}.items():
        for dz, daz in ((0, 0), (0, 15), (0, 30), (0, 45), (-10, 0), (10, 0)):
            cols = []
            for level in (3, 5, 6, 8):
                qq = np.zeros((20000, 7), np.float32)
                qq[:, C.U], qq[:, C.V] = rng.random(20000), rng.random(20000)
                qq[:, C.SIGMA] = 2.0**level / config.resolution
                # daz turns the whole configuration (light and view) about the normal
                qq[:, C.WI_X:C.WI_Y + 1] = direction(zen + dz, az + daz)
                qq[:, C.WO_X:C.WO_Y + 1] = direction(55, daz)
                truth = (tracer.estimate(qq, 16, level) @ lum).mean()
                raw_q = model.run(qq).astype(np.float64)
                ratios = {n: (answer(n, qq, raw_q) @ lum).mean() / truth for n in worst}
                for n, r in ratios.items():
                    worst[n].append(abs(math.log(r)))
                cols.append(" ".join(f"{ratios[n]:.3f}" for n in worst))
            print(f"    {light:5s} zenith {zen + dz:2d} turned {daz:3d}: " + " | ".join(cols), flush=True)
    for n, w in worst.items():
        print(f"  {n}: mean |log ratio| {np.mean(w):.4f}, largest {np.max(w):.4f}")


if __name__ == "__main__":
    main()
