"""Is the far views' azimuthal error the shared decoder's capacity, or the coarse data's weight in the loss? A probe on
a trained map model's checkpoint, everything but one decoder frozen (its textures computed once), trained further
on the training data's coarse queries only (level of detail >= K - 1, ``--from-level K``) with the training loss
(comb2), then scored by `azimuth_sweep.py`'s configurations at 64 texels against that sweep's printed estimator
(the same positions: the sweep's random generator replayed):

- ``shared``: the model's own decoder trained so (it also answers the fine levels: what weighting the loss towards
  the coarse footprints would do, without the fine levels' data pulling back);
- ``coarse``: a second decoder, a copy of the first, trained so and blended in by w = clamp(lod - K, 0, 1) (the
  fine levels keep the first: a coarse-level decoder, the model-class lever).

If either flattens the sweep's error (the shipped model 0.05 mean |log|), the features hold the azimuthal change
and the decoder or the loss lost it; if neither does, noisy coarse targets under this loss do not teach it. The
``shape`` score takes each light's mean ratio out (a brightness shift, which the log loss moves on its own): what
is left is the azimuthal error.

    .venv/bin/python experiments/energy/coarse_decoder.py CHECKPOINT DATA \
        experiments/energy/results/azimuth_ctl_L6.txt --seconds 420

CHECKPOINT: a `neumip fit` run's ``checkpoint.pt`` (``--work``); DATA: its training data; the sweep printout must be of
the same material at ``--level`` (its first model column is not read).
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import numpy as np
import torch

from azimuth_sweep import LIGHTS, configurations, read_estimates, shape_score  # this folder's

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


class Blend(torch.nn.Module):
    """The decoder call of `NeuMIPMaterial.forward`: the first decoder, or its blend with a second one by the
    weights (N, 1) set before each call."""

    def __init__(self, first: torch.nn.Module, second: torch.nn.Module | None) -> None:
        super().__init__()
        self.first, self.second, self.weight = first, second, None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.first(x)
        if self.second is None:
            return out
        return out + self.weight * (self.second(x) - out)


def sweep(answer, estimates: dict, level: int, resolution: int) -> list[float]:
    """Each configuration's answers' mean over the estimator's (`azimuth_sweep.read_estimates`), at the sweep's own
    positions."""
    return [float((answer(q) @ LUMINANCE).mean()) / estimates[light, phi][0]
            for light, phi, q in configurations(list(estimates), level, resolution)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("data", type=Path, help="the model's training data (queries.npy, rgb.npy)")
    parser.add_argument("sweep", type=Path, help="azimuth_sweep.py's printout at --level for this material")
    parser.add_argument("--level", type=int, default=6)
    parser.add_argument("--from-level", type=int, default=4, help="K: the coarse decoder's blend starts at lod K")
    parser.add_argument("--seconds", type=float, default=420.0, help="training time of each arm")
    parser.add_argument("--batch", type=int, default=8192)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--arms", default="shared,coarse")
    args = parser.parse_args()

    from neumip.training.loop.checkpoint import load
    from neumip.training.loop.losses import comb2
    from neumip.training.model.pyramid import level_of_detail

    estimates = read_estimates(args.sweep)
    queries = np.load(args.data / "queries.npy", mmap_mode="r")
    targets = np.load(args.data / "rgb.npy", mmap_mode="r")

    def lod_of(material, sigma: torch.Tensor) -> torch.Tensor:
        return level_of_detail(sigma, material.config.resolution, material.config.lod_bias)

    def answerer(material, blend: Blend):
        levels, otex = material.textures()

        @torch.no_grad()
        def answer(q: np.ndarray) -> np.ndarray:
            x = torch.from_numpy(q)
            blend.weight = torch.clamp(lod_of(material, x[:, 2]) - args.from_level, 0.0, 1.0)[:, None]
            return material(x, pyramid=levels, offset_texture=otex).numpy()
        return answer

    base, _ = load(args.checkpoint)
    resolution = base.config.resolution
    sigma = torch.from_numpy(np.ascontiguousarray(queries[:, 2]))
    coarse_rows = torch.nonzero(lod_of(base, sigma) >= args.from_level - 1).squeeze(1).numpy()
    print(f"{args.checkpoint}: {len(coarse_rows)} of {len(queries)} training queries at lod >= {args.from_level - 1}; "
          f"each arm {args.seconds:.0f} s, batches of {args.batch}, Adam lr {args.lr}, comb2")
    fine_rows = np.sort(np.random.default_rng(2).choice(
        torch.nonzero(lod_of(base, sigma) < args.from_level - 1).squeeze(1).numpy(), 100000, replace=False))
    fine_x = torch.from_numpy(np.asarray(queries[fine_rows]))
    fine_y = np.asarray(targets[fine_rows], np.float64)
    results = {}
    for arm in ["before"] + [a for a in args.arms.split(",") if a]:
        material, _ = load(args.checkpoint)
        material.eval()
        for p in material.parameters():
            p.requires_grad_(False)
        second = copy.deepcopy(material.decoder) if arm == "coarse" else None
        blend = Blend(material.decoder, second)
        material.decoder = blend
        trained = {"shared": blend.first, "coarse": second}.get(arm)
        steps, losses = 0, []
        if trained is not None:
            for p in trained.parameters():
                p.requires_grad_(True)
            with torch.no_grad():
                levels, otex = material.textures()
            opt = torch.optim.Adam(trained.parameters(), lr=args.lr)
            rng = np.random.default_rng(1)
            start = time.perf_counter()
            while time.perf_counter() - start < args.seconds:
                pick = np.sort(coarse_rows[rng.integers(0, len(coarse_rows), args.batch)])
                x = torch.from_numpy(np.asarray(queries[pick]))
                y = torch.from_numpy(np.asarray(targets[pick], np.float32))
                blend.weight = torch.clamp(lod_of(material, x[:, 2]) - args.from_level, 0.0, 1.0)[:, None]
                loss = comb2(material(x, pyramid=levels, offset_texture=otex, ceiling=False), y)
                opt.zero_grad()
                loss.backward()
                opt.step()
                losses.append(loss.item())
                steps += 1
        answer = answerer(material, blend)
        ratios = sweep(answer, estimates, args.level, resolution)
        fine_mse = float(((answer(fine_x.numpy()) - fine_y) ** 2).mean())
        logs = np.log(ratios)
        results[arm] = ratios
        per_light = logs.reshape(len(LIGHTS), -1)  # the sweep's order: light by light, its turns in a row
        shape = shape_score(logs, len(LIGHTS))
        tail = f"; {steps} steps, loss {np.mean(losses[:50]):.4f} -> {np.mean(losses[-50:]):.4f}" if steps else ""
        print(f"  {arm:7s} mean |log(answer / estimator)| {np.abs(logs).mean():.4f}, largest {np.abs(logs).max():.4f}; "
              f"shape (each light's turns about their mean log) {shape:.4f}; mean ratio by light "
              + " ".join(f"{x:.3f}" for x in np.exp(per_light.mean(1))) + f"; MSE on 100,000 finer training queries "
              f"{fine_mse * 1e3:.4f}e-3" + tail, flush=True)
    for i, ((light, phi), (truth, _)) in enumerate(estimates.items()):
        print(f"  {light:5s} phi {phi:5.1f}: estimator {truth:.4f}  "
              + "  ".join(f"{arm} {r[i]:.3f}" for arm, r in results.items()))


if __name__ == "__main__":
    main()
