"""Does a model's energy-table cell hide a gain that changes with the view? Fit the table (`model.energy.fit_energy`)
on two halves of a data set's queries split by the view's elevation (wo_z below / above its median), and on two
random halves of the same sizes (the noise of a half's fit); print, per level of detail, the halves' disagreement:
the cells' mean |log(gain_low / gain_high)|, luminance-weighted, over cells both halves fill.

    .venv/bin/python experiments/energy/view_split.py DATA MODEL_WITHOUT_TABLE.onnx [MODEL2.onnx ...]

A model "without a table" is its file with every gain 1 (the answers the table is fitted to); the answers come from
ONNX Runtime on every query of DATA (the held-out split too: a fit reads the training split alone).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

import onnx
import onnxruntime as ort

from neumip.core import contract as C
from neumip.groundtruth.dataset import open_dataset
from neumip.training.export.read import read_model
from neumip.training.model.energy import corners, fit_energy


def disagreement(config, queries, answers, targets, left: np.ndarray) -> np.ndarray:
    """Per level: the mean |log(gain of `left` / gain of the rest)| over cells both halves fill (weight > 1 query)."""
    q, a, t = (torch.from_numpy(np.asarray(x, np.float32)) for x in (queries, answers, targets))
    halves = [fit_energy(config, q[m], a[m], t[m], prior=0.0).numpy() for m in (left, ~left)]
    index, weight = corners(config, q[:, C.SIGMA], q[:, C.WI_X:C.WI_Y + 1], q[:, C.WO_X:C.WO_Y + 1])
    rows = (config.levels + 1) * config.energy_bins ** 2
    filled = [np.bincount(index[m].reshape(-1).numpy(), weight[m].reshape(-1).numpy(), rows) > 1
              for m in (torch.from_numpy(left), torch.from_numpy(~left))]
    luminance = np.asarray([0.2126, 0.7152, 0.0722])
    gap = np.abs(np.log(np.clip(halves[0], 1e-3, None) @ luminance) - np.log(np.clip(halves[1], 1e-3, None) @ luminance))
    per_level = gap.reshape(config.levels + 1, -1)
    both = (filled[0] & filled[1]).reshape(config.levels + 1, -1)
    return np.asarray([per_level[k][both[k]].mean() if both[k].any() else np.nan for k in range(config.levels + 1)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data")
    parser.add_argument("models", nargs="+")
    args = parser.parse_args()
    data = open_dataset(args.data)
    queries, targets = np.asarray(data.queries), np.asarray(data.rgb)
    wo_z = np.sqrt(np.clip(1.0 - queries[:, C.WO_X] ** 2 - queries[:, C.WO_Y] ** 2, 0.0, 1.0))
    low_view = wo_z < np.median(wo_z)
    random_half = np.random.default_rng(0).permutation(len(queries)) < low_view.sum()
    for path in args.models:
        config = read_model(onnx.load(path), path)[0]
        session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
        answers = np.concatenate([session.run(None, {C.ONNX_INPUT: queries[lo:lo + (1 << 16)]})[0]
                                  for lo in range(0, len(queries), 1 << 16)])
        by_view = disagreement(config, queries, answers, targets, low_view)
        by_chance = disagreement(config, queries, answers, targets, random_half)
        print(f"## {path}: per level of detail 0..{config.levels}, mean |log gain ratio| of the halves")
        print("  view's elevation: " + " ".join(f"{v:.3f}" for v in by_view))
        print("  random halves:    " + " ".join(f"{v:.3f}" for v in by_chance))


if __name__ == "__main__":
    main()
