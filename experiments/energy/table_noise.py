"""How much of the energy table's azimuth axis is noise?

The table's cells with the azimuth axis (`MaterialConfig.energy_azimuths`) hold 16x fewer queries than without it. A
coarse level's targets are noisy (a footprint of many texels holds a few glints that 16 samples hit or miss), so a
cell's ratio of sums carries noise that a far view shows as a brightness shift of a few percent. This experiment
fits the table on two disjoint halves of a model's training split (`neumip calibrate`'s rows) with each fit rule
(`ratio`: `fit_energy`'s, each cell its own ratio pulled towards 1 by a prior of 256 queries; `shrink`:
`fit_shrink`; `window`: `fit_window`; `balanced`: `fit_balanced`) and
compares the halves cell by cell, at the levels of detail from `--from-level` on:

- noise: the rms of log(gain_A / gain_B) / sqrt 2, one half's fit noise (a fit on the whole split: that / sqrt 2);
- spread: the rms of log(gain) about the cell's mean over the azimuths (signal and noise);
- cross-half: each rule fitted on one half and scored on the other by the measure below, both ways, averaged;
- held-out: each rule fitted on the whole split, scored on the held-out split by the mean over cells of
  (log(data's sum / answers' sum))^2, each cell's sums weighted as in the fit and the cells weighted by their queries
  (what is left of the cells' bias, plus the held-out split's own noise, the same for every rule).

    .venv/bin/python experiments/energy/table_noise.py DATA MODEL [--seed S] [--from-level 3]

MODEL: the model file (its own table is replaced: the rules fit the answers with every gain 1).
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import torch


CHI2_MEDIAN = 0.4549364
"""The median of chi-squared with one degree of freedom (a squared standard normal's)."""


def fit_shrink(config, queries, answers, targets):
    """A rule not kept: each azimuth's cell its own ratio shrunk towards the gain pooled over the azimuths (the table
    without the azimuth axis, `fit_energy`'s prior) by the empirical-Bayes weight (`shrink_azimuths`)."""
    from neumip.core import contract as C
    from neumip.core.weights import energy_rows
    from neumip.training.model.energy import ENERGY_PRIOR, ENERGY_RANGE, FIT_CHUNK, corners

    answers, targets = answers.double(), targets.double()
    columns = [targets, answers, targets * targets, targets * answers, answers * answers, torch.ones_like(answers[:, :1])]
    sums = torch.zeros(energy_rows(config), 16, dtype=torch.float64)
    for lo in range(0, len(queries), FIT_CHUNK):
        part = queries[lo:lo + FIT_CHUNK]
        index, weight = corners(config, part[:, C.SIGMA], part[:, C.WI_X:C.WI_Y + 1], part[:, C.WO_X:C.WO_Y + 1])
        w = weight.double()[:, :, None]
        spread = [(w if i < 2 else w * w) * c[lo:lo + FIT_CHUNK, None, :] for i, c in enumerate(columns)]
        sums.index_add_(0, index.reshape(-1), torch.cat(spread, 2).reshape(index.numel(), -1))
    sums = sums.reshape(config.levels + 1, config.energy_bins, config.energy_bins, config.energy_azimuths, 16)
    st, sa = sums[..., 0:3], sums[..., 3:6]
    mean, prior = answers.mean(0), ENERGY_PRIOR
    pooled = (st.sum(3, keepdim=True) + prior * mean) / (sa.sum(3, keepdim=True) + prior * mean)
    table = shrink_azimuths(st, sa, sums[..., 6:], pooled)
    table[:, 0] = pooled[:, 0]
    return torch.nan_to_num(table.reshape(-1, 3), nan=1.0).clamp(*ENERGY_RANGE).float()


def shrink_azimuths(st: torch.Tensor, sa: torch.Tensor, moments: torch.Tensor, pooled: torch.Tensor) -> torch.Tensor:
    """The azimuth cells' gains: each its own ratio r = sum w t / sum w a shrunk towards its pooled gain p by the
    empirical-Bayes weight tau^2 / (tau^2 + v) (James-Stein), where
    - v is the ratio's sampling variance s^2 sum w^2 / (sum w a)^2, s^2 the queries' residual variance about their
      cell's r a pooled over the azimuths (sum w^2 (t - r a)^2 / sum w^2; a cell's own would be too noisy where a
      few glints decide it);
    - tau^2 is the spread of the true gains about p, per level and channel: the cells' median (r - p)^2 over the
      median of chi-squared with one degree of freedom, less their median v (the method of moments, made robust: a
      few cells where the answers are near 0 have ratios and variances orders above the rest).
    A rough material's cells, whose gains differ by azimuth less than their noise, keep the pooled gain; an
    anisotropic one's azimuths keep what their data say. `st`, `sa` (L+1, B, B, A, 3) and `moments` (L+1, B, B, A, 10)
    from `energy_sums`."""
    tt, ta, aa, ww = moments[..., 0:3], moments[..., 3:6], moments[..., 6:9], moments[..., 9:10]
    p = pooled
    has = sa > 0
    r = torch.where(has, st / sa.clamp(min=1e-300), p)
    resid = (tt - 2 * r * ta + r * r * aa).sum(3, keepdim=True)  # about each cell's own ratio, pooled
    s2 = resid / ww.sum(3, keepdim=True).clamp(min=1e-300)
    v = torch.where(has, s2 * ww / (sa * sa).clamp(min=1e-300), torch.full_like(r, float("inf")))
    usable = has[:, 1:] & torch.isfinite(v[:, 1:])
    nan = torch.full_like(r[:, 1:], float("nan"))
    dev = torch.where(usable, (r[:, 1:] - p[:, 1:]) ** 2, nan).flatten(1, 3).nanmedian(1).values
    noise = torch.where(usable, v[:, 1:], nan).flatten(1, 3).nanmedian(1).values
    tau2 = torch.nan_to_num(dev / CHI2_MEDIAN - noise, nan=0.0).clamp(min=0.0)[:, None, None, None, :]
    share = torch.where(torch.isfinite(v), tau2 / (tau2 + v).clamp(min=1e-300), torch.zeros_like(v))
    return p + share * (r - p)


def fit_window(config, queries, answers, targets):
    """A rule not kept: each azimuth's modulation of the pooled gain p (`fit_energy`'s) from the sums of its level and
    the two next to it, (sum t + prior m) / (sum p a + prior m) over the three (the modulation changes slowly with
    the level: split halves' modulations correlate as well across neighbouring levels as within one)."""
    from neumip.training.model.energy import ENERGY_PRIOR, ENERGY_RANGE, energy_sums

    answers, targets = answers.double(), targets.double()
    sums = energy_sums(config, queries, answers, targets)
    st, sa = sums[..., 0:3], sums[..., 3:6]
    mean, prior = answers.mean(0), ENERGY_PRIOR
    pooled = (st.sum(3, keepdim=True) + prior * mean) / (sa.sum(3, keepdim=True) + prior * mean)
    win = lambda x: x + torch.cat([x[1:], torch.zeros_like(x[:1])]) + torch.cat([torch.zeros_like(x[:1]), x[:-1]])  # noqa: E731
    table = pooled * (win(st) + prior * mean) / (win(pooled * sa) + prior * mean)
    table[:, 0] = pooled[:, 0]
    return torch.nan_to_num(table.reshape(-1, 3), nan=1.0).clamp(*ENERGY_RANGE).float()


def fit_balanced(config, queries, answers, targets, floor: float = 0.1):
    """A rule not kept: the ratio of sums with each query's weight divided by (a + a0), a0 = `floor` times the
    answers' mean: about the mean of the queries' ratios t / a where a >> a0 (every query of a cell counts alike,
    not by its brightness: a cell's ratio of sums leans towards its brightest configurations, the highlights, which
    the log loss darkens most), the ratio of sums where a << a0 (no query near 0 decides a cell). The prior and the
    normal's cells as `fit_energy`'s."""
    from neumip.training.model.energy import fit_energy

    answers, targets = answers.double(), targets.double()
    scale = 1.0 / (answers + floor * answers.mean(0))
    return fit_energy(config, queries, answers * scale, targets * scale)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("data")
    parser.add_argument("model")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--from-level", type=int, default=3)
    parser.add_argument("--rules", default="ratio,shrink,window,balanced",
                        help="comma-separated fit rules: ratio (fit_energy's) or one of RULES")
    args = parser.parse_args()

    import onnx

    from neumip.core import contract as C
    from neumip.core import weights as W
    from neumip.engines.local import load_material
    from neumip.groundtruth.dataset import open_dataset
    from neumip.training.export.graph import build_onnx
    from neumip.training.export.read import read_model
    from neumip.training.loop.energy import fit_rows
    from neumip.training.loop.train import TrainConfig, split_indices
    from neumip.training.model.energy import corners, fit_energy, ones_table

    config, weights, meta, _ = read_model(onnx.load(args.model), args.model)
    config = dataclasses.replace(config, energy_bins=config.energy_bins or 6, energy_azimuths=config.energy_azimuths or 16)
    graph = build_onnx(config, {**weights, W.ENERGY: ones_table(config)}, "", {})
    model = load_material(args.model, data=graph.SerializeToString())
    data = open_dataset(args.data)
    train_idx, held_idx = split_indices(len(data), TrainConfig(seed=args.seed))
    rows = fit_rows(train_idx, args.seed)
    q = torch.from_numpy(np.asarray(data.queries[rows], np.float32))
    t = torch.from_numpy(np.asarray(data.rgb[rows], np.float32))
    a = torch.from_numpy(model.run(q.numpy()))
    half = torch.from_numpy(np.random.default_rng(7).random(len(rows)) < 0.5)
    held = np.sort(np.random.default_rng(1).choice(held_idx, min(len(held_idx), 1 << 21), replace=False))
    hq = torch.from_numpy(np.asarray(data.queries[held], np.float32))
    ht = torch.from_numpy(np.asarray(data.rgb[held], np.float64))
    ha = torch.from_numpy(model.run(hq.numpy()).astype(np.float64))
    hindex, hweight = corners(config, hq[:, C.SIGMA], hq[:, C.WI_X:C.WI_Y + 1], hq[:, C.WO_X:C.WO_Y + 1])
    levels, bins, az = config.levels + 1, config.energy_bins, config.energy_azimuths
    print(f"{args.model} on {args.data}: {len(rows):,} fit queries, {len(held):,} held out; {levels} levels x {bins}"
          f" x {bins} x {az} cells; levels {args.from_level}+ scored", flush=True)

    def held_score(table: torch.Tensor) -> float:
        return score(table, hindex, hweight, ht, ha)

    def score(table, hindex, hweight, ht, ha) -> float:
        gain = (table.double()[hindex] * hweight.double()[:, :, None]).sum(1)
        lum = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)
        rows_ = table.shape[0]
        st = torch.zeros(rows_, dtype=torch.float64).index_add_(0, hindex.reshape(-1),
                                                                 (hweight.double() * (ht @ lum)[:, None]).reshape(-1))
        sa = torch.zeros(rows_, dtype=torch.float64).index_add_(0, hindex.reshape(-1),
                                                                 (hweight.double() * ((ha * gain) @ lum)[:, None]).reshape(-1))
        n = torch.zeros(rows_, dtype=torch.float64).index_add_(0, hindex.reshape(-1), hweight.double().reshape(-1))
        level = torch.arange(rows_) // (bins * bins * az)
        keep = (level >= args.from_level) & (st > 0) & (sa > 0) & (n > 50)
        return float(((torch.log(st[keep] / sa[keep]) ** 2) * n[keep]).sum() / n[keep].sum())

    def cross(table: torch.Tensor, sel: torch.Tensor) -> float:  # the cell bias^2 of a table on the queries `sel`
        return score(table, index[sel], weight[sel], t[sel].double(), a[sel].double())

    index, weight = corners(config, q[:, C.SIGMA], q[:, C.WI_X:C.WI_Y + 1], q[:, C.WO_X:C.WO_Y + 1])
    for rule in args.rules.split(","):
        fit = RULES.get(rule, fit_energy)
        fa, fb, full = fit(config, q[half], a[half], t[half]), fit(config, q[~half], a[~half], t[~half]), fit(config, q, a, t)
        crossed = (cross(fa, ~half) + cross(fb, half)) / 2
        cells = lambda x: torch.log(x).reshape(levels, bins, bins, az, 3)[args.from_level:, 1:]  # noqa: E731
        la, lb, lf = cells(fa), cells(fb), cells(full)
        noise = float(((la - lb) ** 2).mean().sqrt() / np.sqrt(2))
        spread = float(((lf - lf.mean(3, keepdim=True)) ** 2).mean().sqrt())
        per_level = " ".join(f"{float(((la[i] - lb[i]) ** 2).mean().sqrt() / np.sqrt(2)):.3f}" for i in range(la.shape[0]))
        print(f"  {rule:10s} noise (one half) {noise:.4f}  spread about the azimuths' mean {spread:.4f}  "
              f"cross-half cell bias^2 {crossed:.6f}  held-out {held_score(full):.5f}  gains {float(full.min()):.3f}-{float(full.max()):.3f}"
              f"  noise by level {per_level}", flush=True)
    flat = ones_table(config)
    flat = torch.from_numpy(flat)
    print(f"  {'none':10s} cross-half cell bias^2 {(cross(flat, half) + cross(flat, ~half)) / 2:.6f}  held-out "
          f"{held_score(flat):.5f}", flush=True)


RULES = {"shrink": fit_shrink, "window": fit_window, "balanced": fit_balanced}
"""The rules of this experiment beside `fit_energy`'s."""


if __name__ == "__main__":
    main()
