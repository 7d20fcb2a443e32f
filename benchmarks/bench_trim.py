"""Benchmark: what trimming a scene's models to its budget saves, and what it changes in the render.

For the demo scene at each ``--sizes`` resolution: `neumip budget` (4 spp traced, footprints of a
render at ``--spp``) finds each material's
finest level that matters, the shipped models are trimmed to it (`neumip trim`: every pyramid, the base
maps' and the relief's at the same footprint) into a temporary
folder, and the scene is rendered at ``--spp`` through the untrimmed and the trimmed models with one
seed, and through the untrimmed models with a second seed. Printed: bytes before and after per
material (the budget's estimate beside, and the neural offset's bytes, which trimming keeps whole), and the
mean and largest pixel difference trimmed vs untrimmed (same seed) beside the same figures for the two
seeds (the Monte-Carlo noise of the render).

    .venv/bin/python benchmarks/bench_trim.py --sizes 32,16 --spp 4   # far and few samples: levels 1, 2
    .venv/bin/python benchmarks/bench_trim.py                         # 96^2 and 64^2, 64 spp: level 0
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from neumip.engines.local import LocalMaterials
from neumip.client.mitsuba.budget import scene_budget
from neumip.client.mitsuba.render import RenderConfig, load_scene, render_scene
from neumip.training.export.trim import trim_file


def render(scene_path: str, params: dict, folder: Path, spp: int, seed: int) -> np.ndarray:
    scene = load_scene(scene_path, **params)
    return render_scene(scene, LocalMaterials(folder), RenderConfig(spp=spp, seed=seed)).image[..., :3]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="scenes/demo.xml")
    parser.add_argument("--models", type=Path, default=Path("models"))
    parser.add_argument("--sizes", default="96,64", help="image sizes (square), comma-separated")
    parser.add_argument("--spp", type=int, default=64)
    args = parser.parse_args()
    for size in (int(s) for s in args.sizes.split(",")):
        params = {"resx": str(size), "resy": str(size)}
        budget = scene_budget(load_scene(args.scene, **params), args.models, spp=4, render_spp=args.spp)
        with tempfile.TemporaryDirectory() as tmp:
            before = after = 0
            print(f"{args.scene} at {size}x{size}:")
            for m in budget.materials:
                src, dst = args.models / f"{m.material}.onnx", Path(tmp) / f"{m.material}.onnx"
                trim_file(src, dst, m.finest_level)
                before, after = before + src.stat().st_size, after + dst.stat().st_size
                levels = ", ".join(f"{name} {level}" for name, level in (m.pyramid_levels or {}).items())
                print(f"  {m.material}: finest levels {levels}: {src.stat().st_size:,} -> {dst.stat().st_size:,} "
                      f"bytes (budget: {m.trimmed_bytes:,}; the neural offset keeps {m.offset_bytes:,})")
            print(f"  all: {before:,} -> {after:,} bytes ({100 * (1 - after / before):.1f} % saved)")
            full = render(args.scene, params, args.models, args.spp, 0)
            trimmed = render(args.scene, params, Path(tmp), args.spp, 0)
            other = render(args.scene, params, args.models, args.spp, 1)
        for name, image in (("trimmed vs untrimmed (seed 0)", trimmed), ("noise: seed 1 vs seed 0", other)):
            diff = np.abs(image - full)
            print(f"  {name}: mean {diff.mean():.2e}, max {diff.max():.2e}")


if __name__ == "__main__":
    main()
