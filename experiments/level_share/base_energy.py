"""How much of its finer texels' energy the classical base's prefiltered coarse level keeps: per level, the mean of
the finest level's base answers over each coarse texel, over the coarse texel's own answer (luminance, summed over
texels and random direction pairs uniform in solid angle up to 85 degrees, the report's range; `terminator` none, as
the shipped models). > 1: the prefiltered level is darker than the texels it stands for; [p99]: the same for the
99th percentiles (the highlights).

    .venv/bin/python experiments/level_share/base_energy.py turtle rock yarn foam docs/materials/planks.toml
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch


def main() -> None:
    from neumip.groundtruth.description import find_description, resolve
    from neumip.training.model.base import base_answer, base_maps, base_resolution

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("materials", nargs="+")
    p.add_argument("--pairs", type=int, default=4, help="direction pairs per finest texel")
    args = p.parse_args()
    rng = np.random.default_rng(0)
    luminance = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)
    for name in args.materials:
        geo = resolve(find_description(name))
        res = base_resolution(geo)
        levels = [torch.from_numpy(np.asarray(lv, np.float64)) for lv in base_maps(geo, res)]
        n = res * res * args.pairs
        cos = 1.0 - (1.0 - math.cos(math.radians(85))) * rng.random((2, n))
        phi = 2 * math.pi * rng.random((2, n))
        r = np.sqrt(1.0 - cos * cos)
        wi = torch.from_numpy(np.stack([r[0] * np.cos(phi[0]), r[0] * np.sin(phi[0])], 1))
        wo = torch.from_numpy(np.stack([r[1] * np.cos(phi[1]), r[1] * np.sin(phi[1])], 1))
        fine = levels[0].reshape(res * res, -1).repeat_interleave(args.pairs, 0)  # texel t's pairs at t P .. t P + P - 1
        fine_answer = (base_answer(fine, wi, wo, "none") @ luminance).reshape(res, res, args.pairs)
        cells = []
        for lv in range(1, len(levels)):
            size, f = levels[lv].shape[0], res // levels[lv].shape[0]
            # each finest texel's pairs answered by the coarse texel that covers it
            cover = levels[lv].repeat_interleave(f, 0).repeat_interleave(f, 1).reshape(res * res, -1)
            coarse_answer = (base_answer(cover.repeat_interleave(args.pairs, 0), wi, wo, "none") @ luminance)
            ratio = float(fine_answer.sum() / coarse_answer.sum())
            tail = float(np.percentile(fine_answer.numpy(), 99) / np.percentile(coarse_answer.numpy(), 99))
            cells.append(f"{lv} ({size}^2): {ratio:.3f} [{tail:.2f}]")
        print(f"{geo.name if hasattr(geo, 'name') else name} ({res}^2): " + ", ".join(cells))


if __name__ == "__main__":
    main()
