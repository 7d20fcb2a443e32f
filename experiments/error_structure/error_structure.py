"""Where a report view's remaining error sits: brightness, pixel-scale detail, a few pixels, or the texel grid.

The report splits each method's image MSE into noise and bias (`report/metrics.bias_noise`). Where a
bias stays put whatever the model (as foam's 0.14e-3 did at 4-64 texels per pixel, before `render.pass_seed`: it was
noise the seed pairs missed, `experiments/error_structure/floor.txt`), two ways to look at it:

``images MATERIAL VIEWS METHODS``: renders the report's views as `neumip report` does (R at the report's spp, two
seeds; each method at 64 spp, two seeds; cached in ``--cache``) and prints, per method, the MSE of the two seeds'
mean and its bias, the MSE left after the best per-channel gain (a brightness error), the MSE of the error blurred
by 4 and 16 pixels (its low-frequency part), and the share of the squared error in the worst 1 % of pixels
(fireflies); and for R, that share of its two seeds' difference.

``--footprint-spp K`` renders the neural methods with each sample's footprint that of a K-spp render
(`RenderConfig.footprint_spp`; the report's is its own spp, 64: an eighth of the pixel's), not cached: a wider
footprint prefilters more of the pixel in the lookup (less of the texture's noise, where that is the render's
noise), and the samples' spread blurs it once more.

``--light sun`` or ``--light sky`` renders every method under the report's directional light alone or its dim
constant environment alone (the report's scenes with the other emitter left out; cached in a subfolder of
``--cache`` of that name): which light a method's error comes with. ``--light uniform`` keeps both but lets a
light sample choose either with probability 1/2 (Mitsuba's default; the report's scenes choose in proportion to
the irradiance each gives).

``phase DATA MODELS``: each model's MSE on a held-out data set (``neumip generate ... --seed 7``) by where the
query falls in the texel grid of the level it reads (queries within 0.15 of a whole level; distance from the
nearest texel centre in texels, the larger of the two axes). A bilinear pyramid that cannot reconstruct its level's
detail errs more half-way between texel centres. Use models without the parallax stages (``NAME_nooffset``): the
relief moves the lookup away from the query's uv.

    .venv/bin/python experiments/error_structure/error_structure.py images foam level0_high,level2_high,level4_high C,N,Nmaps,Nmaps0
    .venv/bin/python experiments/error_structure/error_structure.py images foam level2_high Nmaps --footprint-spp 4
    neumip generate foam -o runs/floor/foam_q --queries 262144 --resolution 256 --spp 16 --seed 7
    .venv/bin/python experiments/error_structure/error_structure.py phase runs/floor/foam_q models/foam_maps_nooffset.onnx

``directions MATERIAL VIEW MODELS``: the models' answers against the training data's own estimator (`QueryTracer`,
``--spp`` samples a query) on queries at one report view's directions alone (its light, and the view direction
at the image centre), at random positions and a footprint of ``--texels`` map texels: is a model off there in
query space too, or only in the render?

    .venv/bin/python experiments/error_structure/error_structure.py directions docs/materials/planks.toml level2_high \
        docs/materials/planks_models/planks_maps.onnx
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def top_share(squared: np.ndarray, share: float = 0.01) -> float:
    """Share of the sum of per-pixel squared errors (H, W, 3) held by the worst `share` of pixels."""
    per_pixel = np.sort(squared.sum(-1).ravel())
    return float(per_pixel[-max(1, int(len(per_pixel) * share)):].sum() / max(per_pixel.sum(), 1e-30))


def box_blur(image: np.ndarray, size: int) -> np.ndarray:
    """(H, W, C) -> its mean over a size x size box around each pixel (edges repeated)."""
    lo = size // 2
    padded = np.pad(image, ((lo, size - 1 - lo), (lo, size - 1 - lo), (0, 0)), mode="edge").astype(np.float64)
    for axis in (0, 1):
        total = np.cumsum(np.insert(padded, 0, 0.0, axis=axis), axis=axis)
        n = padded.shape[axis] - size + 1
        padded = (np.take(total, range(size, size + n), axis=axis) - np.take(total, range(n), axis=axis)) / size
    return padded


def images(args) -> None:
    from neumip.engines.kernel import KernelMaterials
    from neumip.client.mitsuba.render import RenderConfig, render_scene
    from neumip.groundtruth.description import resolve
    from neumip.report import metrics as Q
    from neumip.report.methods import NEURAL
    from neumip.report.cache import RenderCache
    from neumip.report.config import ReportConfig
    from neumip.report.pipeline import REFERENCE_SEEDS
    from neumip.report.renderer import MaterialRenderer
    from neumip.report.run import find_materials
    from neumip.report.views import VIEWS

    desc = find_materials([args.material], args.models)[Path(args.material).stem]
    cfg = ReportConfig()
    cache = args.cache
    if args.light != "both":  # the report's scenes with one emitter: a cache of their own (keys do not name lights)
        from neumip.report import methods

        both = methods.emitter_dicts
        if args.light == "uniform":  # both, each chosen with probability 1/2 (Mitsuba's default)
            methods.emitter_dicts = lambda view: {name: {k: v for k, v in e.items() if k != "sampling_weight"}
                                                  for name, e in both(view).items()}
        else:
            methods.emitter_dicts = lambda view: {name: e for name, e in both(view).items() if name == args.light}
        cache = args.cache / f"light-{args.light}"
    renderer = MaterialRenderer(Path(args.material).stem, desc, resolve(desc), args.models, KernelMaterials(args.models),
                                cfg, RenderCache(cache))
    views = {v.name: v for v in VIEWS}
    for name in args.views.split(","):
        view = views[name]
        r0, r1 = (renderer.render(view, "R", cfg.reference_spp, s)[0] for s in REFERENCE_SEEDS)
        ref = (r0 + r1) / 2
        ref_noise = Q.noise_mse(r0, r1) / 2
        footprint = f", neural footprints of {args.footprint_spp} spp" if args.footprint_spp else ""
        footprint += {"both": "", "uniform": ", either light chosen with probability 1/2"}.get(args.light, f", {args.light} alone")
        print(f"== {args.material} {name}{footprint}: film {ref.shape[1]} x {ref.shape[0]}, R mean {ref.mean():.4f}, "
              f"R noise {ref_noise * 1e3:.4f}e-3; R's two seeds: worst 1 % of pixels hold "
              f"{top_share((r0 - r1) ** 2):.2f} of their squared difference")
        print(f"   {'method':<7} {'MSE x1e-3':>9} {'bias':>7} {'mean/R':>7} {'after gain':>10} "
              f"{'blurred 4 px':>12} {'16 px':>7} {'worst 1 %':>9}")
        for method in args.methods.split(","):
            if args.footprint_spp and method in NEURAL:
                a, b = (render_scene(renderer.scene(view, method), renderer.evaluator, RenderConfig(
                    spp=cfg.spp, seed=s, max_lanes=cfg.max_lanes, footprint_spp=args.footprint_spp)).image[..., :3]
                    for s in (0, 1))
            else:
                a, b = (renderer.render(view, method, cfg.spp, s)[0] for s in (0, 1))
            mean = (a + b) / 2
            error = mean - ref
            mse = float((error ** 2).mean())
            bias = mse - Q.noise_mse(a, b) / 2 - ref_noise  # signed (Q.bias_noise clamps at 0); the mean of two seeds has half one render's noise
            gain = (mean * ref).sum((0, 1)) / np.maximum((mean * mean).sum((0, 1)), 1e-30)
            after_gain = float(((mean * gain - ref) ** 2).mean())
            blurred = [float((box_blur(error, k) ** 2).mean()) for k in (4, 16)]
            print(f"   {method:<7} {mse * 1e3:9.4f} {bias * 1e3:7.4f} {mean.mean() / ref.mean():7.4f} "
                  f"{after_gain * 1e3:10.4f} {blurred[0] * 1e3:12.4f} {blurred[1] * 1e3:7.4f} "
                  f"{top_share(error ** 2):9.2f}")
        renderer.release()


def phase(args) -> None:
    import onnx
    import onnxruntime as ort

    from neumip.core import contract as C
    from neumip.groundtruth.dataset import open_dataset

    data = open_dataset(args.data)
    queries, target = np.asarray(data.queries), np.asarray(data.rgb, np.float64)
    bins = ((0.0, 0.125), (0.125, 0.25), (0.25, 0.375), (0.375, 0.5))
    for path in args.models:
        model = onnx.load(str(path))
        config = json.loads({p.key: p.value for p in model.metadata_props}[C.META_CONFIG])
        resolution = int(config["resolution"])
        answer = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
            None, {C.ONNX_INPUT: queries})[0].astype(np.float64)
        error = ((answer - target) ** 2).mean(1)
        lod = C.level_of_detail(queries[:, C.SIGMA], resolution)
        print(f"== {path} ({resolution}^2): MSE x1e-3 {error.mean() * 1e3:.4f} on {len(queries)} queries; by distance "
              f"from the nearest texel centre (texels): " + ", ".join(f"[{lo}, {hi})" for lo, hi in bins))
        for level in range(int(np.log2(resolution)) - 1):
            near = np.abs(lod - level) < 0.15
            size = resolution >> level
            x, y = ((queries[:, c] * size - 0.5) % 1.0 for c in (C.U, C.V))  # 0: on a texel centre
            distance = np.maximum(np.minimum(x, 1 - x), np.minimum(y, 1 - y))
            cells = []
            for lo, hi in bins:
                sel = near & (distance >= lo) & (distance < hi)
                cells.append(f"{error[sel].mean() * 1e3:8.4f} ({sel.sum():5d})" if sel.sum() >= 50 else f"{'-':>16}")
            print(f"   level {level} ({size}^2)  " + "  ".join(cells))


def directions(args) -> None:
    import math

    import onnxruntime as ort

    from neumip.core import contract as C
    from neumip.groundtruth.description import find_description, resolve
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.tracer import QueryTracer
    from neumip.report.views import VIEWS, light_direction

    view = {v.name: v for v in VIEWS}[args.view]
    desc = find_description(args.material)
    wi = light_direction(view)
    t = math.radians(view.theta)
    rng = np.random.default_rng(args.seed)
    queries = np.zeros((args.queries, C.QUERY_DIM), np.float32)
    queries[:, [C.U, C.V]] = rng.random((args.queries, 2))
    queries[:, C.SIGMA] = args.texels / desc.resolution
    queries[:, [C.WI_X, C.WI_Y]] = wi[:2]
    queries[:, [C.WO_X, C.WO_Y]] = (0.0, -math.sin(t))  # towards the camera, at the image centre
    settings = GenerateSettings()
    target = QueryTracer(resolve(desc), settings.tracer, settings.tiling).estimate(queries, args.spp, args.seed)
    target = target.astype(np.float64)
    print(f"== {args.material} {args.view}: {args.queries} queries at wi {np.round(wi, 3)}, view zenith {view.theta:g} "
          f"degrees, {args.texels:g} texels; target mean {np.round(target.mean(0), 4)} ({args.spp} spp)")
    for path in args.models:
        answer = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
            None, {C.ONNX_INPUT: queries})[0].astype(np.float64)
        print(f"   {path}: mean target / answer {np.round(target.mean(0) / np.maximum(answer.mean(0), 1e-30), 3)}, "
              f"MSE x1e-3 {((answer - target) ** 2).mean() * 1e3:.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("images", help="a report view's error in image space")
    p.add_argument("material", help="a shipped material or a description file (.toml)")
    p.add_argument("views", help="comma-separated report views (level4_high, low_light, ...)")
    p.add_argument("methods", help="comma-separated report methods (C, N, Nmaps, ...)")
    p.add_argument("--models", type=Path, default=Path("models"))
    p.add_argument("--cache", type=Path, default=Path("runs/floor/renders"))
    p.add_argument("--light", choices=("both", "sun", "sky", "uniform"), default="both",
                   help="render under the report's directional light (sun) or its environment (sky) alone, or under "
                        "both with each light sample choosing either with probability 1/2 (uniform: Mitsuba's default)")
    p.add_argument("--footprint-spp", type=int, metavar="K", help="neural methods: each sample's footprint that of "
                   "a K-spp render (default: the report's, its own spp)")
    p = sub.add_parser("phase", help="models' error on data by position in the texel grid")
    p.add_argument("data", help="a `neumip generate` data set (held out: another seed than the training data's)")
    p.add_argument("models", type=Path, nargs="+")
    p = sub.add_parser("directions", help="models against the data's estimator at one report view's directions")
    p.add_argument("material", help="a shipped material or a description file (.toml)")
    p.add_argument("view", help="a report view (level2_high, ...)")
    p.add_argument("models", type=Path, nargs="+")
    p.add_argument("--queries", type=int, default=16384)
    p.add_argument("--spp", type=int, default=256, help="path samples a query")
    p.add_argument("--texels", type=float, default=0.5, help="footprint (std) in map texels (the report's 64-spp "
                   "samples at 4 texels a pixel read about half a texel)")
    p.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    {"images": images, "phase": phase, "directions": directions}[args.command](args)


if __name__ == "__main__":
    main()
