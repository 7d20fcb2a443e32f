"""The classical base alone against the ground truth, by footprint and by the light's zenith angle.

The base (`training/model/base.py`) is what a model with `--base` starts from: its decoder then learns
base * exp(c) + a. Where the base's prefiltered answer drifts from the data's with the footprint, the decoder
must learn that drift from 64^2 latents and 16-spp targets. This prints, per bin of the light's zenith angle
and of the footprint sigma (in map texels), the mean luminance of the data's targets and of the base's
answers (an untrained material with the base and the relief, no neural offset: its decoder's last layer is
zero), with the base's horizons as `base.base_maps` builds them (a coarse texel's horizon the mean of its finest
texels') and as the horizons of each level's own area-averaged heights (`level_horizon_maps`: the base of
experiments/maps/maps.py's HL variants, measured and not shipped).

    .venv/bin/python experiments/grazing/base_footprints.py data/rock_n1048576_s16 rock

Results: experiments/grazing/grazing.txt.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from neumip.core import contract as C  # noqa: E402
from neumip.core import weights as W  # noqa: E402
from neumip.core.config import (BASE_AZIMUTH_FLOOR, BASE_AZIMUTH_KERNEL, BASE_AZIMUTHS, BASE_HORIZONS,  # noqa: E402
                                BASE_SHADOW_SOFTNESS, MaterialConfig)
from neumip.training.model import base as B  # noqa: E402
from neumip.training.model.base import base_maps, base_resolution  # noqa: E402
from neumip.groundtruth.dataset import open_dataset  # noqa: E402
from neumip.training.model.maps import horizon_angles, resize  # noqa: E402
from neumip.training.model.material import NeuMIPMaterial  # noqa: E402
from neumip.groundtruth.description import find_description, resolve  # noqa: E402
from neumip.training.model.relief import relief_heights, relief_resolution  # noqa: E402

ZENITHS = ((0, 45), (60, 75), (80, 88))
"""Bins of the light's zenith angle, degrees."""
FOOTPRINTS = ((0, 0.01), (0.5, 1.5), (1.5, 3), (3, 6), (6, 12), (12, 48), (48, 256))
"""Bins of the footprint sigma, in texels of the material's maps."""
LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def level_horizon_maps(geo, resolution: int) -> list[np.ndarray]:
    """`base.base_maps` with each level's horizons those of the level's own area-averaged heights (a bump narrower
    than the texel casts none there), not the mean of the finest level's horizons."""
    levels = base_maps(geo, resolution)
    height = geo.height.astype(np.float64)
    for level in levels:
        level[..., 9:] = np.sin(horizon_angles(resize(height, level.shape[0]), BASE_HORIZONS) * (np.pi / 2))
    return levels


def horizon_moment_maps(geo, resolution: int) -> list[np.ndarray]:
    """`base.base_maps` with BASE_HORIZONS more channels: each level's mean of its finest texels' squared horizon
    sines, so that `spread_visibility` can read the horizons' spread within a texel."""
    levels = base_maps(geo, resolution)
    squares = np.sin(horizon_angles(geo.height.astype(np.float64), BASE_HORIZONS) * (np.pi / 2)) ** 2
    return [np.concatenate([level, resize(squares, level.shape[0])], axis=2) for level in levels]


def spread_visibility(horizons: torch.Tensor, wi: torch.Tensor, wi_z: torch.Tensor) -> torch.Tensor:
    """`base.visibility`, and with 2 BASE_HORIZONS columns (`horizon_moment_maps`) the share of the texel's finest
    texels that see the light if their horizon sines spread uniformly about the mean: the ramp widens to
    sqrt(BASE_SHADOW_SOFTNESS^2 + 12 variance)."""
    if horizons.shape[1] == BASE_HORIZONS:
        return _visibility(horizons, wi, wi_z)
    mean, square = horizons[:, :BASE_HORIZONS], horizons[:, BASE_HORIZONS:]
    r = torch.sqrt(torch.clamp((wi * wi).sum(1, keepdim=True), min=BASE_AZIMUTH_FLOOR ** 2))
    azimuths = torch.tensor(BASE_AZIMUTHS, dtype=wi.dtype, device=wi.device).T
    kernel = torch.clamp(wi @ azimuths / r - BASE_AZIMUTH_KERNEL, min=0.0)
    weights = kernel / torch.clamp(kernel.sum(1, keepdim=True), min=BASE_AZIMUTH_FLOOR)
    horizon = (weights * mean).sum(1, keepdim=True)
    variance = (weights * torch.clamp(square - mean * mean, min=0.0)).sum(1, keepdim=True)
    width = torch.sqrt(BASE_SHADOW_SOFTNESS ** 2 + 12.0 * variance)
    return torch.clamp((wi_z - horizon) / width + 0.5, min=0.0, max=1.0)


_visibility, B.visibility = B.visibility, spread_visibility  # (base_answer looks it up in its module)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", help="a data set folder (neumip generate)")
    p.add_argument("material", help="its material: a library name or a .toml")
    args = p.parse_args()
    torch.set_num_threads(1)
    geo = resolve(find_description(args.material))
    res = base_resolution(geo)
    config = MaterialConfig(resolution=64, offset=False, base=res, relief=relief_resolution(geo), terminator="none",
                            local_frame=True)
    material = NeuMIPMaterial(config).eval()
    material.set_maps(W.RELIEF, relief_heights(geo, config.relief))
    pyramids = {"base": base_maps(geo, res), "level horizons": level_horizon_maps(geo, res),
                "horizon spread": horizon_moment_maps(geo, res)}
    data = open_dataset(args.data)
    queries, targets = np.asarray(data.queries), np.asarray(data.rgb) @ LUMINANCE
    wi_z = np.sqrt(np.clip(1 - queries[:, C.WI_X] ** 2 - queries[:, C.WI_Y] ** 2, 0, 1))
    zenith, sigma = np.degrees(np.arccos(wi_z)), queries[:, C.SIGMA] * res
    print(f"{args.material}: {len(queries)} queries of {args.data}; mean luminance of the targets and of the base's "
          f"answers ({res}^2 maps)")
    print(f"{'light zenith':>13} {'sigma texels':>13} {'queries':>8} {'target':>8}" +
          "".join(f"{name:>15}" for name in pyramids))
    for lo, hi in ZENITHS:
        for s0, s1 in FOOTPRINTS:
            rows = (zenith > lo) & (zenith < hi) & (sigma >= s0) & (sigma < s1)
            if not rows.any():
                continue
            batch = torch.as_tensor(queries[rows])
            answers = []
            for levels in pyramids.values():
                material.base_maps = torch.as_tensor(np.concatenate([lvl.reshape(-1, lvl.shape[2]) for lvl in levels]))
                with torch.no_grad():
                    answers.append(float((material(batch).numpy() @ LUMINANCE).mean()))
            print(f"{f'{lo}-{hi}':>13} {f'{s0}-{s1}':>13} {rows.sum():8d} {targets[rows].mean():8.4f}" +
                  "".join(f"{a:15.4f}" for a in answers))


if __name__ == "__main__":
    main()
