"""How sure is the report's bias estimate? Its views re-scored from a report's cached renders, each bias (the error
floor that more samples do not remove) with its uncertainty, and the neural method's bias against C's and Cmip's.

    .venv/bin/python experiments/verdict_noise/bias_spread.py rock yarn turtle foam --cache runs/rep/cache
    .venv/bin/python experiments/verdict_noise/bias_spread.py docs/materials/planks.toml \
        --models docs/materials/planks_models --cache runs/rep/cache

The report (`report/pipeline.py`) estimates a method's bias as ``MSE(a, R) - MSE(a, b) / 2 - R's noise`` from two
renders a, b of different seeds at 64 spp and the reference R (the mean of two renders). Here the same per-pixel
terms are resampled in blocks of 8 x 8 pixels (a block bootstrap, 2,000 draws; the blocks keep the images' local
correlation): per view and method the bias and its standard error, and for N against C and Cmip the difference of
their biases (N - X; negative: N's floor is lower) with its standard error and z (the difference over its error).
The report's verdict compares the two biases as estimated; |z| < 2 is a difference the two seeds cannot tell from
none. Nothing is rendered: a view missing from the cache is skipped.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from neumip.engines.kernel import KernelMaterials
from neumip.groundtruth.description import find_description, resolve
from neumip.report.cache import RenderCache
from neumip.report.config import ReportConfig
from neumip.report.pipeline import REFERENCE_SEEDS
from neumip.report.renderer import MaterialRenderer
from neumip.report.views import VIEWS

BLOCK = 8
DRAWS = 2000


def block_means(per_pixel: np.ndarray) -> np.ndarray:
    """(H, W) -> the means of its BLOCK x BLOCK blocks, flat (a ragged edge dropped)."""
    h, w = (per_pixel.shape[0] // BLOCK) * BLOCK, (per_pixel.shape[1] // BLOCK) * BLOCK
    return per_pixel[:h, :w].reshape(h // BLOCK, BLOCK, w // BLOCK, BLOCK).mean(axis=(1, 3)).ravel()


def bias_blocks(a: np.ndarray, b: np.ndarray, r0: np.ndarray, r1: np.ndarray) -> np.ndarray:
    """Per block, the report's bias estimate's terms (channels averaged): (a - R)^2 - (a - b)^2 / 2 - (r0 - r1)^2 / 4."""
    reference = (r0 + r1) / 2
    term = ((a - reference) ** 2 - (a - b) ** 2 / 2 - (r0 - r1) ** 2 / 4).astype(np.float64).mean(axis=2)
    return block_means(term)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("materials", nargs="+")
    parser.add_argument("--models", type=Path, default=Path("models"))
    parser.add_argument("--cache", type=Path, required=True, help="a report's --cache folder")
    parser.add_argument("--views", default="", help="comma-separated view names (default: every view at 16-256 texels)")
    parser.add_argument("--method", default="N")
    args = parser.parse_args()
    config = ReportConfig()
    views = [v for v in VIEWS if (v.name in args.views.split(",") if args.views else v.footprint_texels >= 16)]
    rng = np.random.default_rng(0)
    evaluator = KernelMaterials(args.models)
    print(f"# bias x1e-3 (+- standard error), block bootstrap of {BLOCK} x {BLOCK} px, {DRAWS} draws; "
          f"{args.method} - X: the difference of the biases; z: it over its standard error")
    for name in args.materials:
        desc = find_description(name)
        r = MaterialRenderer(desc.name, desc, resolve(desc), args.models, evaluator, config,
                             RenderCache(args.cache / "renders"))
        for view in views:
            def image(method, spp, seed):
                cached = r.cache.get(r.key(view, method, spp, seed))
                return None if cached is None else cached.image[..., :3]

            r0, r1 = (image("R", config.reference_spp, s) for s in REFERENCE_SEEDS)
            if r0 is None or r1 is None:
                continue
            blocks = {}
            for method in (args.method, "C", "Cmip"):
                a, b = image(method, config.spp, 0), image(method, config.spp, 1)
                if a is not None and b is not None:
                    blocks[method] = bias_blocks(a, b, r0, r1)
            if args.method not in blocks:
                continue
            draws = rng.integers(0, len(blocks[args.method]), (DRAWS, len(blocks[args.method])))
            cells = []
            for method, x in blocks.items():
                cells.append(f"{method} {x.mean() * 1e3:.4f} +- {x[draws].mean(axis=1).std() * 1e3:.4f}")
            for other in ("C", "Cmip"):
                if other in blocks:
                    d = blocks[args.method] - blocks[other]
                    se = d[draws].mean(axis=1).std()
                    cells.append(f"{args.method} - {other} {d.mean() * 1e3:+.4f} +- {se * 1e3:.4f} "
                                 f"(z {d.mean() / se:+.1f})")
            print(f"{desc.name:7s} {view.name:13s} {view.footprint_texels:4.0f} texels | " + " | ".join(cells), flush=True)
        r.release()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
