"""Each model's MSE (x1e-3, linear RGB) per level of detail on a reference data set (many samples a query, another
seed than the training data's), all lights and, in brackets, lights above 11.5 degrees (wi_z >= 0.2: most of a
glossy material's reference error is in a few grazing glints).

    neumip generate NAME -o REF --queries 16384 --spp 256 --seed 1 --directions solid_angle --max-zenith 85 \\
        --level-fraction 1.0 --heavy-fraction 0 --sub-texel-levels 1
    .venv/bin/python experiments/energy/reference_mse.py REF MODEL...
"""

from __future__ import annotations

import sys

import numpy as np


def main() -> None:
    from neumip.core import contract as C
    from neumip.core.config import MaterialConfig
    from neumip.engines.local import load_material
    from neumip.groundtruth.dataset import open_dataset

    reference, paths = sys.argv[1], sys.argv[2:]
    data = open_dataset(reference)
    q, target = np.asarray(data.queries), np.asarray(data.rgb, np.float64)
    models = [load_material(path) for path in paths]
    config = MaterialConfig.from_dict(models[0].config) if isinstance(models[0].config, dict) else models[0].config
    level = np.clip(np.floor(np.log2(np.maximum(q[:, C.SIGMA], 1e-12) * config.resolution) + config.lod_bias),
                    0, config.levels).astype(int)
    lit = np.sqrt(np.maximum(0, 1 - q[:, C.WI_X] ** 2 - q[:, C.WI_Y] ** 2)) >= 0.2
    errors = [((m.run(q) - target) ** 2).mean(1) for m in models]
    print(f"{reference}: MSE x1e-3 per level, all [lights above 11.5 degrees]; models: " + ", ".join(paths))
    for lv in range(config.levels + 1):
        r = level == lv
        if r.sum() >= 50:
            print(f"{lv:5d}  " + "   ".join(f"{e[r].mean() * 1e3:8.3f} [{e[r & lit].mean() * 1e3:7.3f}]" for e in errors))
    print("  all  " + "   ".join(f"{e.mean() * 1e3:8.3f} [{e[lit].mean() * 1e3:7.3f}]" for e in errors))


if __name__ == "__main__":
    main()
