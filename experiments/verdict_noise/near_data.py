"""Does the model fit its own training data at a far view's directions? The data set's queries whose light and view
directions lie within 10 or 20 degrees of a report view's (at its image centre), by footprint, and the model's mean
answer on them over the data's mean target (luminance).

    .venv/bin/python experiments/verdict_noise/near_data.py DATA MODELS MATERIAL VIEW...
"""

from __future__ import annotations

import math
import sys

import numpy as np

from direction_check import LUM, unit_directions, view_queries  # this folder's
from neumip.core import contract as C
from neumip.engines.kernel import KernelMaterials
from neumip.groundtruth.dataset import open_dataset
from neumip.report.views import VIEWS

FOOTPRINTS = ((0, 2), (4, 16), (16, 64))
"""Footprint ranges (map texels) of the data's queries compared."""


def main() -> int:
    data, models, material, views = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
    d = open_dataset(data)
    q, rgb = np.asarray(d.queries), np.asarray(d.rgb)
    evaluator = KernelMaterials(models)
    resolution = int(d.meta["generator"]["resolution"])
    texels = q[:, C.SIGMA] * resolution
    wi, wo = unit_directions(q[:, C.WI_X:C.WI_Y + 1]), unit_directions(q[:, C.WO_X:C.WO_Y + 1])
    by_name = {v.name: v for v in VIEWS}
    for name in views:
        _, vwi, vwo = view_queries(by_name[name], resolution, 64)
        for degrees in (10, 20):
            near = (wi @ vwi[0] > math.cos(math.radians(degrees))) & (wo @ vwo[0] > math.cos(math.radians(degrees)))
            for lo, hi in FOOTPRINTS:
                rows = np.flatnonzero(near & (texels >= lo) & (texels < hi))
                answers = np.asarray(evaluator.evaluate(material, q[rows])).astype(np.float64)
                target = rgb[rows].astype(np.float64).mean(0) @ LUM
                print(f"{name} within {degrees} deg, {lo}-{hi} texels: n {len(rows)}, data mean lum {target:.4f}, "
                      f"model / data {answers.mean(0) @ LUM / target:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
