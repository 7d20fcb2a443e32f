"""The data's mean over the answers' mean (luminance) near the report's three lights, by level, for each model: queries
of a data set whose view is within 0.12 in wo_z of the report's 55 degrees and whose light is within 0.12 in wi_z and
25 degrees in azimuth of each light (high: zenith 20, azimuth 45 from the view; side: 60, 90; front: 50, 135), a
seeded sample of 6 M queries. What the training data say about the report's far views.

    .venv/bin/python experiments/energy/near_views.py DATA MODEL...
"""

from __future__ import annotations

import sys

import numpy as np

LIGHTS = {"high": (20, 45), "side": (60, 90), "front": (50, 135)}
"""The report's lights: zenith and azimuth from the view, degrees."""


def main() -> None:
    from neumip.core import contract as C
    from neumip.core.config import MaterialConfig
    from neumip.engines.local import load_material
    from neumip.groundtruth.dataset import open_dataset

    data, models = open_dataset(sys.argv[1]), [load_material(p) for p in sys.argv[2:]]
    rows = np.sort(np.random.default_rng(2).choice(len(data), min(6_000_000, len(data)), replace=False))
    q, t = np.asarray(data.queries[rows]), np.asarray(data.rgb[rows], np.float64)
    config = MaterialConfig.from_dict(models[0].config) if isinstance(models[0].config, dict) else models[0].config
    level = np.clip(np.floor(np.log2(np.maximum(q[:, C.SIGMA], 1e-12) * config.resolution) + config.lod_bias),
                    0, config.levels).astype(int)
    lift = lambda x, y: np.sqrt(np.maximum(0, 1 - x * x - y * y))  # noqa: E731
    wi_z, wo_z = lift(q[:, C.WI_X], q[:, C.WI_Y]), lift(q[:, C.WO_X], q[:, C.WO_Y])
    azimuth = np.degrees(np.abs(np.angle(np.exp(1j * (np.arctan2(q[:, C.WI_Y], q[:, C.WI_X])
                                                      - np.arctan2(q[:, C.WO_Y], q[:, C.WO_X]))))))
    luminance = np.array([0.2126, 0.7152, 0.0722])
    view = np.abs(wo_z - np.cos(np.radians(55))) < 0.12
    answers = [m.run(q[view]).astype(np.float64) @ luminance for m in models]
    target = t[view] @ luminance
    print(f"{sys.argv[1]}: data / answer near the report's lights (view 55 degrees); models: " + ", ".join(sys.argv[2:]))
    for name, (zenith, az) in LIGHTS.items():
        near = (np.abs(wi_z[view] - np.cos(np.radians(zenith))) < 0.12) & (np.abs(azimuth[view] - az) < 25)
        for lo, hi in ((0, 1), (2, 3), (4, 5), (6, 8)):
            r = near & (level[view] >= lo) & (level[view] <= hi)
            print(f"{name:5s} levels {lo}-{hi}: {r.sum():6d} queries  "
                  + " ".join(f"{target[r].sum() / a[r].sum():.3f}" for a in answers))


if __name__ == "__main__":
    main()
