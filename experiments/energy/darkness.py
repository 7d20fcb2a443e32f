"""Where a model answers darker than its data: the data's mean over the answers' mean (luminance) per level of detail
and bin of the light's elevation (wi_z) or of the half vector's (h_z), on a seeded sample of a data set, for each
model given (the energy table's evidence: `MaterialConfig.energy_bins`).

    .venv/bin/python experiments/energy/darkness.py DATA MODEL... [--queries 2000000] [--by wi_z|h_z|both]

DATA: the data set the models were trained on (`neumip generate NAME -o DATA --sub-texel-levels 1` is what `neumip
fit NAME` generates). A level is floor(log2(sigma R) + lod_bias) of the first model's config; > 1: darker.
"""

from __future__ import annotations

import argparse

import numpy as np

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
WI_BINS = (0.0, 0.2, 0.5, 0.8, 1.01)
H_BINS = (0.0, 0.7, 0.85, 0.95, 0.99, 1.01)


def main() -> None:
    from neumip.core import contract as C
    from neumip.core.config import MaterialConfig
    from neumip.engines.local import load_material
    from neumip.groundtruth.dataset import open_dataset

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data")
    p.add_argument("models", nargs="+")
    p.add_argument("--queries", type=int, default=2_000_000, help="the sample's size (seeded)")
    p.add_argument("--by", choices=("wi_z", "h_z", "both"), default="both")
    args = p.parse_args()
    data = open_dataset(args.data)
    rows = np.arange(len(data))
    if len(rows) > args.queries:
        rows = np.sort(np.random.default_rng(0).choice(rows, args.queries, replace=False))
    q, target = np.asarray(data.queries[rows]), np.asarray(data.rgb[rows], np.float64) @ LUMINANCE
    models = [load_material(path) for path in args.models]
    config = MaterialConfig.from_dict(models[0].config) if isinstance(models[0].config, dict) else models[0].config
    answers = [m.run(q).astype(np.float64) @ LUMINANCE for m in models]
    level = np.clip(np.floor(np.log2(np.maximum(q[:, C.SIGMA], 1e-12) * config.resolution) + config.lod_bias),
                    0, config.levels).astype(int)
    lift = lambda x, y: np.sqrt(np.maximum(0, 1 - x * x - y * y))  # noqa: E731
    wi_z, wo_z = lift(q[:, C.WI_X], q[:, C.WI_Y]), lift(q[:, C.WO_X], q[:, C.WO_Y])
    h = np.stack([q[:, C.WI_X] + q[:, C.WO_X], q[:, C.WI_Y] + q[:, C.WO_Y], wi_z + wo_z], 1)
    h_z = h[:, 2] / np.linalg.norm(h, axis=1)
    axes = {"wi_z": (wi_z, WI_BINS, np.ones(len(q), bool)), "h_z": (h_z, H_BINS, wi_z >= 0.2)}
    for name in (("wi_z", "h_z") if args.by == "both" else (args.by,)):
        values, bins, keep = axes[name]
        note = " (lights above 11.5 degrees)" if name == "h_z" else ""
        print(f"{args.data}, {len(q):,} queries: data / answer per level and {name} bin{note}; models: "
              + ", ".join(args.models))
        print("level  " + "  ".join(f"{name} [{lo}, {hi})".rjust(13 * len(models) - 1) for lo, hi in zip(bins, bins[1:])))
        for lv in range(config.levels + 1):
            cells = []
            for lo, hi in zip(bins, bins[1:]):
                r = (level == lv) & keep & (values >= lo) & (values < hi)
                cells.append(" ".join(f"{target[r].sum() / a[r].sum():6.3f}({r.sum():5d})" if r.sum() >= 200
                                      else f"{'-':>12s}" for a in answers))
            if any(c.strip("- ") for c in cells):
                print(f"{lv:5d}  " + "  ".join(cells))


if __name__ == "__main__":
    main()
