"""Are a committed report's neural images still this code's? Re-render some of its cached views now and print
the largest pixel difference from the cached render of the same key (model, view, spp, seed).

A change to `neumip_path` that should only move cost (not the images) leaves the report's figures valid
where the differences are float rounding (about 1e-7); a larger one means the report must be regenerated with
the renderer's cache version bumped (`report/renderer.NEURAL_VERSION`).

    .venv/bin/python benchmarks/report_current.py rock turtle --cache runs/report-final/cache
    .venv/bin/python benchmarks/report_current.py docs/materials/planks.toml \
        --models docs/materials/planks_models --cache runs/report-planks
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from neumip.engines.kernel import KernelMaterials
from neumip.groundtruth.description import find_description, resolve
from neumip.report.cache import RenderCache
from neumip.report.config import ReportConfig
from neumip.report.renderer import MaterialRenderer
from neumip.report.views import VIEWS


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("materials", nargs="+", help="library names or description files")
    ap.add_argument("--models", type=Path, default=Path("models"))
    ap.add_argument("--cache", type=Path, required=True, help="the report's --cache folder")
    ap.add_argument("--views", default="level0_side,level2_front,level6_high,low_light")
    ap.add_argument("--methods", default="N,Nmaps")
    args = ap.parse_args()
    config = ReportConfig()
    views = {v.name: v for v in VIEWS}
    evaluator = KernelMaterials(args.models)
    worst = 0.0
    for name in args.materials:
        desc = find_description(name)
        r = MaterialRenderer(desc.name, desc, resolve(desc), args.models, evaluator, config,
                             RenderCache(args.cache / "renders"))
        for view_name in args.views.split(","):
            view = views[view_name]
            for method in args.methods.split(","):
                if method not in r.methods:
                    continue
                cached = r.cache.get(r.key(view, method, config.spp, 0))
                if cached is None:
                    print(f"{desc.name:8s} {view_name:14s} {method:6s} not in the cache")
                    continue
                image = r._render(r.scene(view, method), config.spp, 0)
                diff = float(np.abs(image - cached.image).max())
                worst = max(worst, diff)
                print(f"{desc.name:8s} {view_name:14s} {method:6s} max |now - cached| {diff:.2e} "
                      f"(image mean {float(cached.image.mean()):.4f})", flush=True)
            r.release()
    print(f"largest difference: {worst:.2e}")


if __name__ == "__main__":
    main()
