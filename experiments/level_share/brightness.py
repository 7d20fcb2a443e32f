"""Where a model's answers are too dark: mean target over mean answer (luminance) per level of detail, on a reference
data set (a `neumip generate` set traced with many samples), for each model given.

    neumip generate turtle -o runs/uref/turtle --queries 16384 --spp 256 --seed 1 --resolution 256 \
        --directions solid_angle --max-zenith 85 --level-fraction 1.0 --heavy-fraction 0 --sub-texel-levels 1
    .venv/bin/python experiments/level_share/brightness.py runs/uref/turtle models/turtle_maps.onnx models/turtle.onnx

`--base-alone`: also each model with its decoder's last layer zeroed (a model with a classical base then answers
the base alone: what the decoder corrects). A level is floor(log2(sigma R) + lod_bias) of the first model's config
(R its resolution), clamped to [0, L];
> 1: the model answers darker than the ground truth there. Also the 99th percentile of the luminance, target over
answer (the highlights' energy).
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    from neumip.core import contract as C
    from neumip.core.config import MaterialConfig
    from neumip.engines.local import load_material
    from neumip.groundtruth.dataset import open_dataset

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reference")
    p.add_argument("models", nargs="+")
    p.add_argument("--base-alone", action="store_true", help="also each model's classical base alone")
    args = p.parse_args()
    data = open_dataset(args.reference)
    queries, target = np.asarray(data.queries), np.asarray(data.rgb, np.float64)
    luminance = np.array([0.2126, 0.7152, 0.0722])
    materials = [load_material(path) for path in args.models]
    config = MaterialConfig.from_dict(materials[0].config) if isinstance(materials[0].config, dict) else materials[0].config
    if args.base_alone:
        import tempfile

        folder = tempfile.mkdtemp()
        for path in list(args.models):
            args.models.append(f"{folder}/{path.split('/')[-1][:-5]}_base_alone.onnx")
            materials.append(load_material(_base_alone(path, args.models[-1])))
    level = np.clip(np.floor(np.log2(np.maximum(queries[:, C.SIGMA], 1e-12) * config.resolution) + config.lod_bias),
                    0, config.levels).astype(int)
    answers = [m.run(queries).astype(np.float64) @ luminance for m in materials]
    t = target @ luminance
    print(f"{args.reference}: mean target / mean answer (luminance) per level; [p99 target / p99 answer]")
    print("level  queries  " + "  ".join(f"{path.split('/')[-1]:>24s}" for path in args.models))
    for lv in range(config.levels + 1):
        rows = level == lv
        if rows.sum() < 100:
            continue
        cells = [f"{t[rows].mean() / a[rows].mean():7.3f} [{np.percentile(t[rows], 99) / np.percentile(a[rows], 99):6.3f}]"
                 for a in answers]
        print(f"{lv:5d}  {rows.sum():7d}  " + "  ".join(f"{c:>24s}" for c in cells))


def _base_alone(path: str, out: str) -> str:
    """The model at `path` with its decoder's last layer zeroed, written to `out`."""
    import onnx

    from neumip.core import contract as C
    from neumip.core import weights as W
    from neumip.training.export.graph import build_onnx, save_onnx
    from neumip.training.export.read import read_model

    config, weights, meta, finest = read_model(onnx.load(path))
    last = config.layers - 1
    for name in (W.weight(W.DECODER, last), W.bias(W.DECODER, last)):
        weights[name] = np.zeros_like(weights[name])
    owned = {C.META_CONTRACT, C.META_CONFIG, C.META_DESCRIPTION}
    save_onnx(build_onnx(config, weights, "base alone", {k: v for k, v in meta.items() if k not in owned}, finest), out)
    return out


if __name__ == "__main__":
    main()
