"""Does the classical base follow a far view's azimuthal change, and would an anisotropic LEAN lobe keep it at a
coarse level? The configurations of `azimuth_sweep.py` (the report's three lights and the 55-degree view turned
together about the normal by phi), answered by the base alone (no decoder), averaged over every texel of a level:

- ``fine``: the shipped base's finest level, every texel: what a perfect filter of the base answers far away;
- ``iso``: the shipped base's level (its lobe widened by the slopes' variance, one number a texel: isotropic LEAN);
- ``aniso``: the same level with the slopes' 2 x 2 covariance instead (anisotropic LEAN: GGX of the alpha matrix
  A = roughness^4 I + 2 Sigma, which is the shipped alpha^2 where Sigma is isotropic; Smith's G1 with A projected
  on each direction's azimuth);
- ``fine_unlit``: ``fine`` with every texel's light visible (no horizon map): how much of ``fine``'s change is the
  height field's shadows;
- ``iso_vis``: ``iso`` with each texel's visibility of the light the mean of its finest texels' (the ideal filter
  of the horizon map's shadows, where the shipped level thresholds its texels' mean horizon);
- ``iso_vis_mask``: ``iso_vis`` times its finest texels' mean visibility of the view by the same horizon map (the
  masking the base leaves to Smith's G1).

Each column is printed over its own mean across phi (the shape of the azimuthal change) beside the estimator's from
a sweep's output (``--sweep``: `azimuth_sweep.py`'s printout, its first model's ratio giving the model's shape too).
The base ignores interreflection and its visibility is a horizon map, so ``fine`` itself may miss the estimator's
change: then no filtering of the base can give it back.

    .venv/bin/python experiments/energy/base_azimuth.py turtle --sweep experiments/energy/results/azimuth_turtle.txt
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import torch

from azimuth_sweep import LIGHTS, read_estimates  # this folder's
LUMINANCE = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)


def aniso_answer(features: torch.Tensor, cov: torch.Tensor, rough4: torch.Tensor, wi: torch.Tensor,
                 wo: torch.Tensor) -> torch.Tensor:
    """The base's answer (terminator none) with GGX of the alpha matrix A = rough4 I + 2 cov, in slope space about
    the texel's mean slopes. features: (N, BASE_CHANNELS); cov: (N, 2, 2); rough4: (N,); wi, wo: (N, 2)."""
    from neumip.training.model.base import _dot, base_normal, half_direction, lift, visibility

    wi3, wo3 = lift(wi), lift(wo)
    n = base_normal(features)
    h = half_direction(wi3, wo3)
    eye = torch.eye(2, dtype=cov.dtype).expand_as(cov)
    a = rough4[:, None, None] * eye + 2.0 * cov
    a = a + 1e-8 * eye
    slope = -h[:, :2] / torch.clamp(h[:, 2:3], min=1e-6) - features[:, 6:8]  # facet slope minus the mean slope
    inv = torch.linalg.inv(a)
    quad = torch.einsum("ni,nij,nj->n", slope, inv, slope)
    p22 = 1.0 / (math.pi * torch.sqrt(torch.linalg.det(a)) * (1.0 + quad) ** 2)
    distribution = (p22 / torch.clamp(h[:, 2], min=1e-6) ** 4)[:, None]

    def g1(w3: torch.Tensor) -> torch.Tensor:
        c = torch.clamp(_dot(n, w3), min=0.0)
        t = w3[:, :2] / torch.clamp(torch.linalg.norm(w3[:, :2], dim=1, keepdim=True), min=1e-6)
        alpha2 = torch.einsum("ni,nij,nj->n", t, a, t)[:, None]
        return 2.0 * c / (c + torch.sqrt(alpha2 * (1.0 - c * c) + c * c))

    cos_i = torch.clamp(_dot(n, wi3), min=0.0)
    cos_o = torch.clamp(_dot(n, wo3), min=0.0)
    f0 = features[:, 3:6]
    fresnel = f0 + (1.0 - f0) * (1.0 - torch.clamp(_dot(h, wi3), 0.0, 1.0)) ** 5
    specular = distribution * g1(wi3) * g1(wo3) * fresnel / (4.0 * torch.clamp(cos_o, min=1e-3))
    diffuse = features[:, 0:3] * (cos_i / math.pi)
    wi_z = wi3[:, 2:3]
    return (diffuse + specular) * visibility(features[:, 9:], wi, wi_z) / torch.clamp(wi_z, min=1e-3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material")
    parser.add_argument("--level", type=int, default=6, help="the base level: footprint 2^LEVEL finest texels")
    parser.add_argument("--step", type=float, default=15.0)
    parser.add_argument("--sweep", type=Path, help="an azimuth_sweep.py printout of the same material and level")
    args = parser.parse_args()

    from neumip.core.config import MaterialConfig
    from neumip.groundtruth.description import find_description, resolve
    from neumip.training.model.base import base_answer, base_maps, base_resolution
    from neumip.training.model.maps import finest_statistics, resize

    geo = resolve(find_description(args.material))
    res = base_resolution(geo)
    levels = base_maps(geo, res)
    size = MaterialConfig(resolution=res).level_sizes()[args.level]
    stats = finest_statistics(geo)[..., 1:6]
    m = resize(stats, size).astype(np.float64).reshape(-1, 5)
    sx, sy = m[:, 0], m[:, 1]
    cov = np.stack([np.stack([m[:, 2] - sx * sx, m[:, 4] - sx * sy], 1),
                    np.stack([m[:, 4] - sx * sy, m[:, 3] - sy * sy], 1)], 1)
    rough4 = resize(np.asarray(geo.roughness, np.float64) ** 4, size).reshape(-1)
    fine = torch.from_numpy(levels[0].reshape(-1, levels[0].shape[2]).astype(np.float64))
    coarse = torch.from_numpy(levels[args.level].reshape(-1, levels[0].shape[2]).astype(np.float64))
    cov_t, rough_t = torch.from_numpy(cov), torch.from_numpy(rough4)
    eigen = np.linalg.eigvalsh(cov)
    print(f"{args.material}: base {res}^2, level {args.level} ({size}^2 texels); the slopes' covariance's eigenvalues "
          f"there: median {np.median(eigen[:, 0]):.4f} and {np.median(eigen[:, 1]):.4f}, roughness^4 median "
          f"{np.median(rough4):.4f}")
    truth = read_estimates(args.sweep) if args.sweep else {}
    columns = ["estimator", "model"] * bool(truth) + ["fine", "iso", "aniso", "fine_unlit", "iso_vis", "iso_vis_mask"]
    from neumip.training.model.base import lift, visibility

    def filtered(features: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """The finest texels' visibility of direction w (one (1, 2) row), averaged into the level's texels."""
        vis = visibility(features[:, 9:], w.expand(len(features), 2), lift(w)[:, 2:3].expand(len(features), 1))
        f = res // size
        return vis.reshape(size, f, size, f).mean((1, 3)).reshape(-1, 1)
    print("each column over its mean across phi; " + ", ".join(columns))
    for light, (zen, az) in LIGHTS.items():
        rows = []
        for phi in np.arange(0.0, 90.0 + 1e-6, args.step):
            def direction(zenith, azimuth, count):
                z, a = math.radians(zenith), math.radians(azimuth + phi)
                return torch.tensor([[math.sin(z) * math.sin(a), -math.sin(z) * math.cos(a)]],
                                    dtype=torch.float64).expand(count, 2)

            def mean(rgb: torch.Tensor) -> float:
                return float((rgb @ LUMINANCE).mean())

            wi_f, wo_f = direction(zen, az, len(fine)), direction(55, 0, len(fine))
            wi_c, wo_c = direction(zen, az, len(coarse)), direction(55, 0, len(coarse))
            row = [mean(base_answer(fine, wi_f, wo_f, "none")), mean(base_answer(coarse, wi_c, wo_c, "none")),
                   mean(aniso_answer(coarse, cov_t, rough_t, wi_c, wo_c)),
                   mean(base_answer(fine, wi_f, wo_f, "none", torch.ones(len(fine), 1, dtype=torch.float64)))]
            lit, seen = filtered(fine, wi_c[:1]), filtered(fine, wo_c[:1])
            row += [mean(base_answer(coarse, wi_c, wo_c, "none", lit)), mean(base_answer(coarse, wi_c, wo_c, "none", lit) * seen)]
            if truth:
                est, ratio = truth[light, float(phi)]
                row = [est, est * ratio] + row
            rows.append((phi, row))
        table = np.array([r for _, r in rows])
        shape = table / table.mean(0)
        for (phi, row), s in zip(rows, shape):
            print(f"  {light:5s} phi {phi:5.1f}: " + "  ".join(f"{c} {v:.3f}" for c, v in zip(columns, s))
                  + "   (" + ", ".join(f"{c} {v:.4f}" for c, v in zip(columns, row)) + ")")
        if truth:
            for j, c in enumerate(columns[1:], 1):
                print(f"  {light:5s} {c}: mean |log(shape / estimator's shape)| "
                      f"{np.mean(np.abs(np.log(shape[:, j] / shape[:, 0]))):.4f}")


if __name__ == "__main__":
    main()
