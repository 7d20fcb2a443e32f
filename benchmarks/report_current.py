"""Are a committed report's neural images still this code's? Re-render some of its cached views now and print
the largest pixel difference from the cached render of the same key (model, view, spp, seed).

A change to `neumip_path` that should only move cost (not the images) leaves the report's figures valid
where the differences are float rounding (about 1e-7); a larger one means the report must be regenerated with
the renderer's cache version bumped (`report/renderer.NEURAL_VERSION`).

    .venv/bin/python benchmarks/report_current.py rock turtle --cache runs/report-final/cache
    .venv/bin/python benchmarks/report_current.py docs/materials/planks.toml \
        --models docs/materials/planks_models --cache runs/report-planks
    .venv/bin/python benchmarks/report_current.py rock turtle --against OLD_MODELS   # no cache needed

``--against DIR``: where the models were re-exported and the report's cache is gone, render each view with the
models of DIR (the files the report was made with) and with ``--models``, both now, and print their largest
difference beside that of two renders of ``--models`` alike (the renderer's own run-to-run rounding).
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


def against(desc, args, evaluator, config, views) -> float:
    """`--against`: the largest difference between each view rendered with the two folders' models."""
    import tempfile

    worst = 0.0
    with tempfile.TemporaryDirectory() as tmp:  # an empty cache: every render is made now
        renderers = [MaterialRenderer(desc.name, desc, resolve(desc), folder, engine, config,
                                      RenderCache(Path(tmp) / str(i)))
                     for i, (folder, engine) in enumerate(((args.models, evaluator),
                                                           (args.against, KernelMaterials(args.against))))]
        now, old = renderers
        for view_name in args.views.split(","):
            view = views[view_name]
            for method in args.methods.split(","):
                if method not in now.methods:
                    continue
                image = now._render(now.scene(view, method), config.spp, 0)
                again = now._render(now.scene(view, method), config.spp, 0)
                before = old._render(old.scene(view, method), config.spp, 0)
                diff = float(np.abs(image - before).max())
                worst = max(worst, diff)
                print(f"{desc.name:8s} {view_name:14s} {method:6s} max |now - against| {diff:.2e}, |now - now| "
                      f"{float(np.abs(image - again).max()):.2e} (image mean {float(image.mean()):.4f})", flush=True)
        for r in renderers:
            r.release()
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("materials", nargs="+", help="library names or description files")
    ap.add_argument("--models", type=Path, default=Path("models"))
    ap.add_argument("--cache", type=Path, help="the report's --cache folder")
    ap.add_argument("--against", type=Path, help="instead of the cache: the models the report was made with")
    ap.add_argument("--views", default="level0_side,level2_front,level6_high,low_light")
    ap.add_argument("--methods", default="N,Nmaps")
    args = ap.parse_args()
    if (args.cache is None) == (args.against is None):
        ap.error("give --cache or --against")
    config = ReportConfig()
    views = {v.name: v for v in VIEWS}
    evaluator = KernelMaterials(args.models)
    worst = 0.0
    for name in args.materials:
        desc = find_description(name)
        if args.against:
            worst = max(worst, against(desc, args, evaluator, config, views))
            continue
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
