"""What the neural render's two sampling stages buy: the noise and the seconds of the neural render in the
report's views at equal spp, with each stage on or off.

- ``paper``: the paper's sampling: the cosine, and one emitter chosen per shading point (``lobe_weight`` 0
  on the BSDF, ``all_emitters`` off on the integrator);
- ``lobe``: the sampling lobe the model file declares (`client/mitsuba/bsdf.py`), one emitter chosen;
- ``lobe+all``: the lobe, and next-event estimation towards every emitter (`client/mitsuba/integrator.py`,
  `PathConfig.all_emitters`): what `neumip render` and the report do.

Each view is rendered as the report renders it (`training.report.methods`: its film, its sun and dim sky)
with two seeds per setting, in interleaved rounds; the noise is the MSE of the two seeds' difference / 2
(one render's variance), as the report measures it. Ratios are against ``paper``; the seconds are the
median render's. R's noise (the real geometry, stock `path`) is printed beside them with ``--reference``.
The stages move noise only: the image means must agree (``mean``).

    .venv/bin/python experiments/sampling/sampling.py docs/materials/planks.toml docs/materials/planks_models
    .venv/bin/python experiments/sampling/sampling.py turtle models --methods Nmaps --views level0_side,low_light
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from neumip.engines.kernel import KernelMaterials
from neumip.client.mitsuba import render as R
from neumip.groundtruth.description import find_description, resolve
from neumip.report import methods as M
from neumip.report.config import ReportConfig
from neumip.report.views import VIEWS, film_for_tiles

SETTINGS = {"paper": ({"lobe_weight": 0.0}, {"all_emitters": False}), "lobe": ({}, {"all_emitters": False}),
            "lobe+all": ({}, {})}
"""Setting -> (properties of the `neumip` BSDF, of the `neumip_path` integrator)."""


def scene_dict(mi, spec: M.SceneSpec, geo, name: str, method: str, setting: str) -> dict:
    if method == "R":
        return M.reference_scene(mi, spec, geo)
    d = M.neural_scene(mi, spec, M.NEURAL_MODELS[method].format(name=name))
    bsdf, integrator = SETTINGS[setting]
    d["plane"]["bsdf"].update(bsdf)
    d["integrator"].update(integrator)
    return d


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("material", help="library name or description .toml")
    ap.add_argument("models", type=Path, help="folder of the material's models (NAME.onnx, NAME_maps.onnx)")
    ap.add_argument("--methods", default="Nmaps,N", help="neural methods (report names)")
    ap.add_argument("--views", default="level0_side,level0_high,level0_front,level2_side,level4_side,low_light")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=2, help="interleaved rounds (seed pairs) per setting")
    ap.add_argument("--reference", action="store_true", help="also R's noise (the real geometry, stock path)")
    args = ap.parse_args()

    mi = R.mi
    desc = find_description(args.material)
    geo = resolve(desc)
    evaluator = KernelMaterials(args.models)
    config = ReportConfig()
    views = {v.name: v for v in VIEWS}
    methods = [m for m in args.methods.split(",") if m]
    for m in methods:
        lobe = evaluator.sampling(M.NEURAL_MODELS[m].format(name=desc.name))
        print(f"# {desc.name} {m}: declared lobe {lobe}")
    print(f"# {args.spp} spp, {args.rounds} seed pairs per setting; noise = MSE(seed a - seed b) / 2")
    header = f"{'view':14s} {'method':6s} {'noise paper':>11s}"
    for s in list(SETTINGS)[1:]:
        header += f" {'noise ' + s:>14s} {'x':>6s} {'mean':>6s} {'time':>6s}"
    print(header + (f" {'R noise':>10s} {'x R':>6s}" if args.reference else ""))
    for view_name in args.views.split(","):
        view = views[view_name]
        film = config.film
        if geo.height.shape[0] > 1:
            film = film_for_tiles(view, film, desc.resolution, config.max_reference_tiles)
        spec = M.SceneSpec(view, film, desc.resolution)
        ref_noise = None
        if args.reference:
            scene = mi.load_dict(scene_dict(mi, spec, geo, desc.name, "R", ""))
            a, b = (R.render_scene(scene, evaluator, R.RenderConfig(spp=args.spp, seed=s)).image[..., :3]
                    for s in (101, 102))
            ref_noise = float(np.mean((a - b) ** 2) / 2)
        for method in methods:
            scenes = {s: mi.load_dict(scene_dict(mi, spec, geo, desc.name, method, s)) for s in SETTINGS}
            noise = {s: [] for s in SETTINGS}
            means = {s: [] for s in SETTINGS}
            seconds = {s: [] for s in SETTINGS}
            for s in SETTINGS:  # warm-up: the first render of a scene compiles its kernels
                R.render_scene(scenes[s], evaluator, R.RenderConfig(spp=1, seed=999))
            order = list(SETTINGS)
            for r in range(args.rounds):
                for s in order if r % 2 == 0 else order[::-1]:
                    images = []
                    for seed in (2 * r + 1, 2 * r + 2):
                        start = time.perf_counter()
                        images.append(R.render_scene(scenes[s], evaluator,
                                                     R.RenderConfig(spp=args.spp, seed=seed)).image[..., :3])
                        seconds[s].append(time.perf_counter() - start)
                    noise[s].append(float(np.mean((images[0] - images[1]) ** 2) / 2))
                    means[s].append(float(np.mean(images)))
            base = np.mean(noise["paper"])
            line = f"{view_name:14s} {method:6s} {base:11.3e}"
            for s in order[1:]:
                line += (f" {np.mean(noise[s]):14.3e} {np.mean(noise[s]) / base:6.3f}"
                         f" {np.mean(means[s]) / np.mean(means['paper']):6.4f}"
                         f" {np.median(seconds[s]) / np.median(seconds['paper']):6.3f}")
            if ref_noise is not None:
                line += f" {ref_noise:10.3e} {np.mean(noise[order[-1]]) / ref_noise:6.3f}"
            print(line, flush=True)


if __name__ == "__main__":
    main()
