"""Which direction's azimuth should the energy table's fourth axis be?

The shipped axis is the half vector's azimuth in the tile's frame (`MaterialConfig.energy_azimuths`). Many light and
view pairs share a half vector's azimuth, while a tile's grooves shadow the light and mask the view by their own
azimuths. This experiment fits the table (the shipped rule, `fit_energy`'s ratio) with the fourth axis taken from
the half vector, the light or the view (the same pseudo-angle, `energy.azimuth_coordinate`), or none, on the model's
training split (`neumip calibrate`'s rows) to its answers without a table, and scores each against the data's own
estimator at the configurations of an `azimuth_sweep.py` printout (the estimator's means reused: the same positions),
by the mean |log(answer / estimator)|; and the half vector's table with one gain a cell for the three channels
(`half_lum`, the luminance's ratio: a third of the reads a light).

    .venv/bin/python experiments/energy/azimuth_axes.py MATERIAL DATA MODEL PRINTOUT [PRINTOUT...] [--seed S]

PRINTOUT: `azimuth_sweep.py` printouts of MATERIAL (its level is read from the first line).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).parent))

AXES = ("none", "half", "light", "view")


def corners_of(config, axis: str, sigma, wi, wo):
    """`energy.corners` with the fourth axis the azimuth of `axis`'s direction (none: the 3-axis table)."""
    from neumip.training.model.base import half_direction, lift
    from neumip.training.model.energy import _pair, _periodic_pair, azimuth_coordinate, direction_coordinates
    from neumip.training.model.pyramid import level_of_detail

    bins, az = config.energy_bins, config.energy_azimuths
    wi3, wo3 = lift(wi), lift(wo)
    h = half_direction(wi3, wo3)
    x, y = direction_coordinates(h, wi3[:, 2], bins)
    pairs = [_pair(level_of_detail(sigma, config.resolution, config.lod_bias), config.levels),
             _pair(x, bins - 1), _pair(y, bins - 1)]
    strides = [bins, bins]
    if axis != "none":
        d = {"half": h, "light": wi3, "view": wo3}[axis]
        pairs.append(_periodic_pair(azimuth_coordinate(d, az), az))
        strides.append(az)
    index, weight = pairs[0]
    for (nodes, weights), stride in zip(pairs[1:], strides):
        index = (index[:, :, None] * stride + nodes[:, None, :]).reshape(len(x), -1)
        weight = (weight[:, :, None] * weights[:, None, :]).reshape(len(x), -1)
    return index, weight


def fit(config, axis, queries, answers, targets, prior=256.0, scalar=False):
    """The shipped rule's table with `axis`'s azimuth (the normal's bin not tied: a direction's azimuth is defined
    there unless it is the half vector's); `scalar`: one gain a cell for the three channels, the ratio of the
    luminances' sums (a third of the reads a light)."""
    from neumip.core import contract as C
    from neumip.training.model.energy import ENERGY_RANGE

    a, t = torch.as_tensor(answers, dtype=torch.float64), torch.as_tensor(targets, dtype=torch.float64)
    if scalar:  # the luminance in every channel: the three gains come out equal
        from neumip.core.contract import LUMINANCE

        lum = torch.tensor(LUMINANCE, dtype=torch.float64)
        a, t = (a @ lum)[:, None].expand(-1, 3), (t @ lum)[:, None].expand(-1, 3)
    rows = (config.levels + 1) * config.energy_bins**2 * (config.energy_azimuths if axis != "none" else 1)
    st, sa = torch.zeros(rows, 3, dtype=torch.float64), torch.zeros(rows, 3, dtype=torch.float64)
    for lo in range(0, len(queries), 1 << 17):
        q = queries[lo:lo + (1 << 17)]
        index, weight = corners_of(config, axis, q[:, C.SIGMA], q[:, C.WI_X:C.WI_Y + 1], q[:, C.WO_X:C.WO_Y + 1])
        w = weight.double()[:, :, None]
        st.index_add_(0, index.reshape(-1), (w * t[lo:lo + (1 << 17), None, :]).reshape(-1, 3))
        sa.index_add_(0, index.reshape(-1), (w * a[lo:lo + (1 << 17), None, :]).reshape(-1, 3))
    if axis == "half":  # the normal's bin pooled, as shipped
        shape = (config.levels + 1, config.energy_bins, config.energy_bins, config.energy_azimuths, 3)
        for s in (st, sa):
            cells = s.view(shape)
            cells[:, 0] = cells[:, 0].sum(2, keepdim=True)
    m = a.mean(0)
    return torch.nan_to_num((st + prior * m) / (sa + prior * m), nan=1.0).clamp(*ENERGY_RANGE)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material")
    parser.add_argument("data")
    parser.add_argument("model")
    parser.add_argument("printouts", nargs="+", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    import onnx
    from azimuth_sweep import configurations, read_estimates

    from neumip.core import contract as C
    from neumip.core import weights as W
    from neumip.engines.local import load_material, run_chunked
    from neumip.groundtruth.dataset import open_dataset
    from neumip.groundtruth.description import find_description
    from neumip.training.export.graph import build_onnx
    from neumip.training.export.read import read_model
    from neumip.training.loop.energy import fit_rows
    from neumip.training.loop.train import TrainConfig, split_indices
    from neumip.training.model.energy import ones_table

    config, weights, _, _ = read_model(onnx.load(args.model), args.model)
    config = dataclasses.replace(config, energy_bins=config.energy_bins or 6, energy_azimuths=config.energy_azimuths or 16)
    model = load_material(args.model, data=build_onnx(config, {**weights, W.ENERGY: ones_table(config)}, "", {})
                          .SerializeToString())
    data = open_dataset(args.data)
    train_idx, _ = split_indices(len(data), TrainConfig(seed=args.seed))
    rows = fit_rows(train_idx, args.seed)
    q = np.asarray(data.queries[rows], np.float32)
    a = run_chunked(model.run, q)
    t = np.asarray(data.rgb[rows], np.float32)
    qt = torch.from_numpy(q)
    tables = {axis: fit(config, axis, qt, a, t) for axis in AXES}
    tables["half_lum"] = fit(config, "half", qt, a, t, scalar=True)
    print(f"{args.model} on {args.data}: {len(rows):,} fit queries; the answers' mean / the estimator's, "
          f"tables {', '.join(tables)} (half_lum: the half vector's axis, one gain a cell from the luminance)", flush=True)
    lum = np.array([0.2126, 0.7152, 0.0722])
    resolution = find_description(args.material).resolution
    for printout in args.printouts:
        level = int(re.search(r"footprint 2\^(\d+)", printout.read_text().splitlines()[0]).group(1))
        known = {key: est for key, (est, _) in read_estimates(printout).items()}
        logs = {axis: [] for axis in tables}
        for light, phi, qq in configurations(list(known), level, resolution):
            raw = torch.from_numpy(model.run(qq).astype(np.float64))
            qqt = torch.from_numpy(qq)
            ratios = {}
            for name in tables:
                axis = name.removesuffix("_lum")
                index, weight = corners_of(config, axis, qqt[:, C.SIGMA], qqt[:, C.WI_X:C.WI_Y + 1], qqt[:, C.WO_X:C.WO_Y + 1])
                gain = (tables[name][index] * weight.double()[:, :, None]).sum(1)
                ratios[name] = float(((raw * gain).numpy() @ lum).mean() / known[light, phi])
                logs[name].append(abs(math.log(ratios[name])))
            print(f"  level {level} {light:5s} phi {phi:5.1f}: " + "  ".join(f"{ratios[x]:.3f}" for x in tables), flush=True)
        for axis in tables:
            print(f"  level {level}, {axis}: mean |log(answer / estimator)| {np.mean(logs[axis]):.4f}, "
                  f"largest {np.max(logs[axis]):.4f}")


if __name__ == "__main__":
    main()
