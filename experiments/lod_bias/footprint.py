"""What a model answers at a sharp footprint, and what that does to the report's views (`MaterialConfig.lod_bias`).

A close-up render's samples each read an eighth of the pixel's footprint (`contract.sample_footprint`): at one map
texel per pixel a sixteenth of a texel. With the paper's level of detail, clamp(log2(sigma R), 0, L), every footprint
of a texel's std or less reads the finest level, which the data train mostly on footprints of a texel and more
(`QuerySampling`: 60 % of the queries texel / sqrt(U), 10 % zero), so the sharp samples read the appearance
filtered by a Gaussian of about a texel's std.

``query MATERIAL VIEW MODEL...``: a 24 x 24-texel patch at 4 x 4 positions a texel, one report view's light and view
direction (the image centre's), path-traced at several footprints (the data's estimator, ``--spp`` samples a
query); each model queried at several footprints, its MSE (x1e-3) against the targets of each footprint. A model
whose finest level is blurred answers a sixteenth of a texel as it answers a whole texel.

``views MATERIAL CACHE VIEWS METHOD FOLDER...``: the report's views rendered as `neumip report` renders them (R and
the method cached in ``CACHE``, as the report's), the method's model taken from each folder in turn (a folder holds
``NAME.onnx`` and the method's file, e.g. ``NAME_maps.onnx`` for Nmaps): the two seeds' mean's MSE against R
(x1e-3), its mean and 99th-percentile luminance over R's, and the last folder's MSE over the first's; ``--where``
adds where each image's error sits (R's shadowed pixels and the rest; its MSE against R blurred by 1 px).

    .venv/bin/python experiments/lod_bias/footprint.py query rock level0_side models/rock.onnx models/rock_maps.onnx
    .venv/bin/python experiments/lod_bias/footprint.py views rock runs/report-final/cache/renders level0_side,level2_side \\
        Nmaps models /tmp/lod/rock
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
FOOTPRINTS = (0.0, 0.125, 0.5, 1.0, 2.0)
"""Footprints (std, map texels) of the targets and of the models' queries."""


def patch_queries(desc, view, sigma_texels: float, texels: int = 24, per_texel: int = 4) -> np.ndarray:
    """(texels per_texel)^2 queries on a patch at ``per_texel``^2 positions a map texel, at one view's directions."""
    from neumip.core import contract as C
    from neumip.report.views import light_direction

    g = (np.arange(texels * per_texel) + 0.5) / per_texel / desc.resolution + 0.3
    u, v = np.meshgrid(g, g)
    q = np.zeros((u.size, C.QUERY_DIM), np.float32)
    q[:, C.U], q[:, C.V] = u.ravel(), v.ravel()
    q[:, C.SIGMA] = sigma_texels / desc.resolution
    q[:, [C.WI_X, C.WI_Y]] = light_direction(view)[:2]
    q[:, [C.WO_X, C.WO_Y]] = (0.0, -math.sin(math.radians(view.theta)))  # towards the camera, at the image centre
    return q


def query(args) -> None:
    import onnxruntime as ort

    from neumip.core import contract as C
    from neumip.groundtruth.description import find_description, resolve
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.tracer import QueryTracer
    from neumip.report.views import VIEWS

    view = {v.name: v for v in VIEWS}[args.view]
    desc = find_description(args.material)
    settings = GenerateSettings()
    tracer = QueryTracer(resolve(desc), settings.tracer, settings.tiling)
    targets = {s: tracer.estimate(patch_queries(desc, view, s), args.spp, args.seed).astype(np.float64)
               for s in FOOTPRINTS}
    print(f"== {args.material} {args.view}: 96 x 96 positions on 24 x 24 texels, {args.spp} spp a target; the targets "
          f"at each footprint (texels) against the unfiltered ones, MSE x1e-3: "
          + ", ".join(f"{s:g}: {((t - targets[0.0]) ** 2).mean() * 1e3:.4f}" for s, t in targets.items()))
    print(f"   {'model':<28} {'queried at':>10}  " + "  ".join(f"{'vs ' + format(s, 'g'):>8}" for s in FOOTPRINTS))
    for path in args.models:
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        for s in (0.0625, 1.0):
            answer = session.run(None, {C.ONNX_INPUT: patch_queries(desc, view, s)})[0].astype(np.float64)
            print(f"   {Path(path).name[-28:]:<28} {s:>10g}  "
                  + "  ".join(f"{((answer - t) ** 2).mean() * 1e3:8.4f}" for t in targets.values()))


def views(args) -> None:
    from neumip.engines.kernel import KernelMaterials
    from neumip.groundtruth.description import resolve
    from neumip.report.cache import RenderCache
    from neumip.report.config import ReportConfig
    from neumip.report.pipeline import REFERENCE_SEEDS
    from neumip.report.renderer import MaterialRenderer
    from neumip.report.run import find_materials
    from neumip.report.views import VIEWS

    cfg = ReportConfig()
    by_name = {v.name: v for v in VIEWS}
    rows: dict[str, list] = {}
    for folder in args.folders:
        desc = find_materials([args.material], folder)[Path(args.material).stem]
        renderer = MaterialRenderer(Path(args.material).stem, desc, resolve(desc), folder, KernelMaterials(folder),
                                    cfg, RenderCache(args.cache))
        for name in args.views.split(","):
            view = by_name[name]
            ref = sum(renderer.render(view, "R", cfg.reference_spp, s)[0] for s in REFERENCE_SEEDS) / 2
            mean = sum(renderer.render(view, args.method, cfg.spp, s)[0] for s in (0, 1)) / 2
            lr, lm = ref @ LUMINANCE, mean @ LUMINANCE
            rows.setdefault(name, []).append((((mean - ref) ** 2).mean() * 1e3, lm.mean() / lr.mean(),
                                              np.quantile(lm, 0.99) / np.quantile(lr, 0.99)))
            if args.where:
                print(f"   {name} {str(folder)[-30:]}: {where(mean, ref)}")
        renderer.release()
    print(f"== {args.material}, {args.method}: the two seeds' mean against R; MSE x1e-3, mean and p99 luminance over R's")
    print(f"   {'view':<13} " + "  ".join(f"{str(f)[-30:]:>30}" for f in args.folders) + "  last / first")
    for name, cells in rows.items():
        print(f"   {name:<13} " + "  ".join(f"{e:9.4f} mean {m:5.3f} p99 {p:5.3f}" for e, m, p in cells)
              + f"  {cells[-1][0] / cells[0][0]:12.2f}")


def where(mean: np.ndarray, ref: np.ndarray) -> str:
    """Where an image's error against R sits: R's shadowed pixels (luminance under 0.4 of its median) and the rest,
    and the MSE against R blurred by a Gaussian of 1 px (lower than against R: the image is blurred)."""
    from scipy.ndimage import gaussian_filter

    err = ((mean - ref) ** 2).mean(axis=2)
    lm, lr = mean @ LUMINANCE, ref @ LUMINANCE
    dark = lr < 0.4 * np.median(lr)
    blurred = np.stack([gaussian_filter(ref[..., c], 1.0, mode="nearest") for c in range(3)], axis=2)
    return (f"R's shadowed pixels {dark.mean():.2f} of the image, {err[dark].sum() / err.sum():.2f} of the error, "
            f"mean over R's there {lm[dark].mean() / lr[dark].mean():.3f} (elsewhere {lm[~dark].mean() / lr[~dark].mean():.3f}); "
            f"MSE against R blurred by 1 px {((mean - blurred) ** 2).mean() * 1e3:.4f}e-3")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(required=True)
    q = sub.add_parser("query", help="a patch's answers against path-traced targets at several footprints")
    q.add_argument("material", help="a shipped material or a description file (.toml)")
    q.add_argument("view", help="a report view (level0_side, ...): its light and view direction")
    q.add_argument("models", type=Path, nargs="+")
    q.add_argument("--spp", type=int, default=128, help="path samples a target")
    q.add_argument("--seed", type=int, default=1)
    q.set_defaults(func=query)
    v = sub.add_parser("views", help="the report's views with each folder's model, against R")
    v.add_argument("material", help="a shipped material or a description file (.toml)")
    v.add_argument("cache", type=Path, help="the report's render cache (its renders/ folder)")
    v.add_argument("views", help="comma-separated report views")
    v.add_argument("method", help="a report method (Nmaps, N, ...)")
    v.add_argument("folders", type=Path, nargs="+", help="model folders, the first the baseline")
    v.add_argument("--where", action="store_true", help="also where each image's error sits (shadows, blur)")
    v.set_defaults(func=views)
    args = p.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
