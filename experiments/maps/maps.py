"""Map-informed materials (issue 25): the paper's model N against the map-informed one M, the
classical material C and the real geometry R, in images, up close, under several lights.

`train` fits each variant to one data set in-process (equal data and equal steps for every variant)
and exports ``RUNS/VARIANT/MATERIAL.onnx``; the run's wall time and held-out MSE go to
``RUNS/VARIANT/MATERIAL.json``.

`score` renders R (stock `path` on the displaced geometry, the mean of two seeds), C (the principled
BSDF with the full-resolution maps and a normal map, stock `path`) and every variant (`neumip_path`)
with the report's building blocks (`report/`: views, scenes, renderer, metrics), in oblique
views (55 degrees) whose pixel footprint covers 1 and 4 texels of a ``--camera-res`` texel grid,
each under the lights of `LIGHTS`. Renders are cached (``--cache``). One JSON line per
(variant, view) is appended to --out; ``--table`` prints them.

    .venv/bin/python experiments/maps/maps.py train --data data/rock --material rock --runs runs/maps N M
    .venv/bin/python experiments/maps/maps.py score --material rock --runs runs/maps N M --out runs/maps/scores.jsonl
    .venv/bin/python experiments/maps/maps.py --table runs/maps/scores.jsonl
    .venv/bin/python experiments/maps/maps.py --spread runs/maps/scores.jsonl Nbr,Nbr_seed1,Nbr_seed2   # against seeds
    .venv/bin/python experiments/maps/maps.py --ensemble Nbr,Nbr_seed1,Nbr_seed2 runs/maps/scores_rock_64_*.npz
    .venv/bin/python experiments/maps/maps.py --strip closeups.png C,N,M runs/maps/scores_rock_64_level0_side.npz ...
    .venv/bin/python experiments/maps/maps.py speed N M --data data/rock --material rock   # seconds per step

experiments/maps/maps.txt has every command and figure of the last run.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402

from neumip.core.config import MaterialConfig  # noqa: E402
from neumip.training.model.maps import RESIDUAL_EVERY_LEVEL, MapConfig  # noqa: E402
from neumip.training.loop.config import PRESETS  # noqa: E402

SHIP = replace(PRESETS["ship"], validate_every=0)
QUICK = replace(PRESETS["quick"], validate_every=0)
QUALITY = replace(PRESETS["quality"], validate_every=0)
RECIPE = {"resolution": 64, "hidden": 25}
"""The shipped models' architecture (models/make_models.sh)."""

VARIANTS: dict[str, tuple[dict, MapConfig | None, object]] = {
    # name: (MaterialConfig overrides, map encoder or None for the paper's model, TrainConfig)
    "N": ({}, None, SHIP),
    "M": ({}, MapConfig(), SHIP),
    "N_seed1": ({}, None, replace(SHIP, seed=1)),  # the run-to-run spread of each model
    "M_seed1": ({}, MapConfig(), replace(SHIP, seed=1)),
    "M_seed2": ({}, MapConfig(), replace(SHIP, seed=2)),
    "M_seed3": ({}, MapConfig(), replace(SHIP, seed=3)),
    "M_hz": ({}, MapConfig(horizons=8), SHIP),
    "Nh": ({"half_vector": True}, None, SHIP),  # the decoder also reads h and cos(theta_d)
    "Mh_hz": ({"half_vector": True}, MapConfig(horizons=8), SHIP),
    "N_k4": ({}, None, replace(SHIP, candidates=4)),  # best of 4 starts after 300 steps
    "M_k4": ({}, MapConfig(), replace(SHIP, candidates=4)),
    "M_hz_k4": ({}, MapConfig(horizons=8), replace(SHIP, candidates=4)),
    "M_1x1": ({}, MapConfig(neighbourhood=1), SHIP),
    "M_residual": ({}, MapConfig(residual=RESIDUAL_EVERY_LEVEL), SHIP),
    "M_noblur": ({}, MapConfig(), replace(SHIP, blur_start=0.0)),
    # the classical base (MaterialConfig.base at the maps' resolution): base(maps) * exp(c) + a
    "Nb": ({"base": "maps"}, None, SHIP),
    "Mb_hz": ({"base": "maps"}, MapConfig(horizons=8), SHIP),
    # the relief stage (MaterialConfig.relief at the height map's resolution, 8 steps), before the offset or alone
    "Nr": ({"relief": "maps"}, None, SHIP),
    "Nr0": ({"relief": "maps", "offset": False}, None, SHIP),
    "Nbr": ({"base": "maps", "relief": "maps"}, None, SHIP),
    # the shipped recipe's spread from seed to seed
    **{f"Nbr_seed{k}": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, seed=k)) for k in range(1, 8)},
    # the shipped recipe's latent pyramid at the maps' resolution, and both with 4.2x the steps (`quality`):
    # what a GPU (--device cuda) can afford that the 2-core machine's 30-minute budget cannot
    "Nbr256": ({"base": "maps", "relief": "maps", "resolution": 256}, None, SHIP),
    "Nbr_quality": ({"base": "maps", "relief": "maps"}, None, QUALITY),
    "Nbr256_quality": ({"base": "maps", "relief": "maps", "resolution": 256}, None, QUALITY),
    "N_rel": ({}, None, replace(SHIP, loss="relative")),  # relative MSE, detached denominator (lever 4)
    # the shipped recipe (Nbr) with other losses: unbiased under noisy targets
    "Nbr_rel": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, loss="relative")),
    "Nbr_mse": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, loss="mse")),
    "Nbr_logw": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, loss="log_weighted")),
    # comb2, then its last sixth of the steps (400) with an unbiased one
    "Nbr_fin_rel": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, finish_loss="relative", finish_fraction=1 / 6)),
    "Nbr_fin_logw": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, finish_loss="log_weighted", finish_fraction=1 / 6)),
    "Nbr_fin_mse": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, finish_loss="mse", finish_fraction=1 / 6)),
    "Nbr_fin_logw_lr10": ({"base": "maps", "relief": "maps"}, None,
                          replace(SHIP, finish_loss="log_weighted", finish_fraction=1 / 6, finish_lr_scale=0.1)),
    "Nbr_fin_logw_lr30": ({"base": "maps", "relief": "maps"}, None,
                          replace(SHIP, finish_loss="log_weighted", finish_fraction=1 / 6, finish_lr_scale=0.3)),
    # the weights averaged over the last quarter of the steps (Polyak), from seeds 0-3
    "Nbr_avg": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, average_fraction=0.25)),
    **{f"Nbr_avg_seed{k}": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, average_fraction=0.25, seed=k))
       for k in (1, 2, 3)},
    # ... from where the blur schedule ends (step ~1 420 of 2 400)
    "Nbr_fin40_rel": ({"base": "maps", "relief": "maps"}, None, replace(SHIP, finish_loss="relative", finish_fraction=0.4)),
    # the decoder also reads wi and wo in the base normal's frame (MaterialConfig.local_frame; experiments/frame/frame.txt)
    "Nbr_frame": ({"base": "maps", "relief": "maps", "local_frame": True}, None, SHIP),
    **{f"Nbr_frame_seed{k}": ({"base": "maps", "relief": "maps", "local_frame": True}, None, replace(SHIP, seed=k))
       for k in range(1, 4)},
    # the base without the shadow terminator's S(g): its horizon visibility alone shadows it (experiments/terminator/terminator.txt)
    "Nbr_vis": ({"base": "maps", "relief": "maps", "terminator": "none"}, None, SHIP),
    **{f"Nbr_vis_seed{k}": ({"base": "maps", "relief": "maps", "terminator": "none"}, None, replace(SHIP, seed=k))
       for k in range(1, 4)},
    # S(g) on the specular lobe only: the diffuse term's lit faces as the geometry's, the glossy lobe still bounded
    "Nbr_spec": ({"base": "maps", "relief": "maps", "terminator": "specular"}, None, SHIP),
    **{f"Nbr_spec_seed{k}": ({"base": "maps", "relief": "maps", "terminator": "specular"}, None, replace(SHIP, seed=k))
       for k in range(1, 4)},
    **{f"Nbr_vis_frame{'' if k == 0 else f'_seed{k}'}": ({"base": "maps", "relief": "maps", "terminator": "none",
                                                           "local_frame": True}, None, replace(SHIP, seed=k))
       for k in range(4)},
    # the shipped recipe with losses unbiased under noisy targets (the low light's highlights: experiments/terminator/terminator.txt)
    **{f"Nbr_vis_frame_{loss}": ({"base": "maps", "relief": "maps", "terminator": "none", "local_frame": True}, None,
                                 replace(SHIP, loss=name)) for loss, name in (("rel", "relative"), ("logw", "log_weighted"))},
    "M_hz_rel": ({}, MapConfig(horizons=8), replace(SHIP, loss="relative")),
    # the shipped recipe on data whose directions reach 88 degrees (`train --data` names them; experiments/grazing/grazing.txt):
    # Z88 on the projected disk as now, SA88 uniform in solid angle
    **{f"{name}{'' if k == 0 else f'_seed{k}'}": ({"base": "maps", "relief": "maps", "terminator": "none",
                                                   "local_frame": True}, None, replace(SHIP, seed=k))
       for name in ("Z88", "SA88") for k in range(4)},
    # the shipped recipe with the decoder reading the base's visibility of the light (`--visibility-input`, experiments/grazing/grazing.txt)
    **{f"VIS{'' if k == 0 else f'_seed{k}'}": ({"base": "maps", "relief": "maps", "terminator": "none",
                                                "local_frame": True, "visibility_input": True}, None, replace(SHIP, seed=k))
       for k in range(4)},
    # the same on the 88-degree solid-angle data (`train --data`: more queries under the low light)
    "VISSA88": ({"base": "maps", "relief": "maps", "terminator": "none", "local_frame": True, "visibility_input": True},
                None, SHIP),
    # the same on the level-horizon base (below): a visibility that holds at every footprint
    **{f"VISHL{'' if k == 0 else f'_seed{k}'}": ({"base": "maps", "relief": "maps", "terminator": "none",
                                                  "local_frame": True, "visibility_input": True}, None,
                                                 replace(SHIP, seed=k)) for k in range(4)},
    # the shipped recipe on a base whose coarse levels shadow by their own heights' horizons
    # (base_footprints.level_horizon_maps, set by `train`; experiments/grazing/grazing.txt: not shipped)
    **{f"HL{'' if k == 0 else f'_seed{k}'}": ({"base": "maps", "relief": "maps", "terminator": "none",
                                               "local_frame": True}, None, replace(SHIP, seed=k)) for k in range(4)},
    # the shipped map-informed recipe (`fit --maps --horizons 8` on the shipped recipe), at 64^2 and at the maps'
    # 256^2, where the encoder leaves nothing per texel to fit from noisy queries (issue 25, lever 1), with
    # the free residual on every level (_res), or on the levels of at most 8 or 16 texels a side (_r8, _r16: where
    # the data hold hundreds of queries per texel; experiments/residual/residual.txt), and the `quality` schedule (GPU runs:
    # experiments/gpu/gpu.txt)
    **{f"Mship{res}{suffix}{seed_suffix}": ({"base": "maps", "relief": "maps", "terminator": "none", "local_frame": True,
                                             "resolution": int(res or 64)}, MapConfig(horizons=8, residual=residual),
                                            replace(schedule, seed=seed))
       for res in ("", "256") for suffix, residual, schedule in (("", 0, SHIP), ("_res", RESIDUAL_EVERY_LEVEL, SHIP),
                                                                 ("_r8", 8, SHIP), ("_r16", 16, SHIP),
                                                                 ("_quality", 0, QUALITY))
       for seed, seed_suffix in ((0, ""), (1, "_seed1"), (2, "_seed2"))},
    # the shipped map-informed recipe with MLPs 32 or 48 wide (25: the paper's), the directions' capacity at coarse
    # footprints and under a grazing light (experiments/grazing/grazing.txt, section 10)
    # (Mmaps_h48: at the material's own maps' resolution, as make_models.sh fits NAME_maps: planks' 128^2)
    **{f"{name}_h{hidden}{suffix}": ({"base": "maps", "relief": "maps", "terminator": "none", "local_frame": True,
                                      "resolution": res, "hidden": hidden}, MapConfig(horizons=8), replace(SHIP, seed=seed))
       for name, res in (("Mship256", 256), ("Mmaps", "maps")) for hidden in (32, 48)
       for seed, suffix in ((0, ""), (1, "_seed1"))},
    # the same 48 wide, pruned while it trains to a third of its weights, the 25-wide's fmas (experiments/prune/prune.py does it
    # after the run instead; experiments/grazing/grazing.txt, section 11)
    **{f"Mship256_h48_p67{suffix}": ({"base": "maps", "relief": "maps", "terminator": "none", "local_frame": True,
                                      "resolution": 256, "hidden": 48}, MapConfig(horizons=8), replace(SHIP, seed=seed))
       for seed, suffix in ((0, ""), (1, "_seed1"))},
    # the shipped map-informed recipe on twice ship's schedule (4 800 steps, the blur's half-life doubled): inside the
    # 30-minute training budget at 256^2, where Mship256_quality (10 000 steps) is not (experiments/steps/steps.txt)
    **{f"{name}_x2{suffix}": ({"base": "maps", "relief": "maps", "terminator": "none", "local_frame": True,
                               "resolution": res}, MapConfig(horizons=8),
                              replace(SHIP, steps=4800, blur_half_life=534.0, seed=seed))
       for name, res in (("Mship256", 256), ("Mmaps", "maps")) for seed, suffix in ((0, ""), (1, "_seed1"))},
    "N128": ({"resolution": 128}, None, SHIP),
    "M128": ({"resolution": 128}, MapConfig(), SHIP),
    "N256": ({"resolution": 256}, None, SHIP),
    "M256": ({"resolution": 256}, MapConfig(), SHIP),
    # 256^2 within this session's time: the `quick` schedule (half of ship's steps), a 1 x 1 encoder
    "N256q": ({"resolution": 256}, None, QUICK),
    "M256q": ({"resolution": 256}, MapConfig(neighbourhood=1), QUICK),
}

LIGHTS = {"high": (15.0, 90.0), "side": (60.0, 90.0), "front": (50.0, 0.0), "low": (85.0, 90.0)}
"""Light name: (zenith, azimuth from the camera's side) in degrees; side is the report's light, low its
low_light (5 degrees above the horizon: highlights)."""
LEVELS = (0, 2)
"""Footprints at the image centre: 2^level texels of the --camera-res grid (1 and 4 texels)."""
SPP, REFERENCE_SPP, SEED = 64, 256, 0


def views(levels=LEVELS):
    from neumip.report.views import View

    return [View(f"level{lv}_{light}", 55.0, lv, light_zenith=z, light_azimuth=a)
            for light, (z, a) in LIGHTS.items() for lv in levels]


PRUNED = {"Mship256_h48_p67": (0.67, 600, 1800)}
"""Variant (before any _seedN): (sparsity, first step, step it is reached): gradual magnitude pruning of the
decoder's and the offset network's weight matrices while the model trains (`prune.py`'s ramp, masks redrawn every
25 steps, the masked weights zeroed after every step from the first). The callback runs after `Trainer.run`'s
progress validation and checkpoint of a step, so those see the step's weights before masking; the masks live in
the callback, so a run resumed mid-pruning goes unmasked until its next 25-step mark; and with `average_fraction`
the average would be of unmasked weights. `train` starts every run afresh, and SHIP averages nothing."""


def sibling(topic: str) -> None:
    """Put another experiment's folder (``experiments/TOPIC``) on the import path, for its script's helpers."""
    import sys

    folder = str(Path(__file__).resolve().parents[1] / topic)
    if folder not in sys.path:
        sys.path.insert(0, folder)


def pruning_callback(trainer, sparsity: float, first: int, last: int):
    """A `Trainer.run` callback that prunes the trainer's MLPs on `PRUNED`'s schedule."""
    sibling("prune")
    from prune import apply_masks, magnitude_masks, ramp, weight_matrices

    masks = []

    def prune(_done: int, _loss: float) -> None:
        step = trainer.state.step
        if step < first:
            return
        matrices = [w for ws in weight_matrices(trainer.material, trainer.material.config).values() for w in ws]
        if step <= last and (step - first) % 25 == 0:
            masks[:] = magnitude_masks(matrices, sparsity * ramp(step - first, 25, last - first))
        apply_masks(matrices, masks)

    return prune


def train(variant: str, data: str, material: str, runs: Path, threads: int, validate_every: int = 0,
          device: str = "cpu", reference: str | None = None) -> None:
    """Fit `variant` on `device` -> RUNS/VARIANT/MATERIAL.onnx and .json; with `reference` (a data set
    folder, e.g. make_models.sh's runs/NAME/reference), the record has its `fit.reference_error` too."""
    import torch

    from neumip.training.model.base import base_resolution
    from neumip.training.export.graph import export_material
    from neumip.training.model.relief import relief_resolution
    from neumip.groundtruth.description import find_description, resolve
    from neumip.training.loop.train import Trainer

    torch.set_num_threads(threads)
    overrides, maps, config = VARIANTS[variant]
    config = replace(config, validate_every=validate_every, device=device)
    desc = find_description(material)
    out = runs / variant / f"{desc.name}.onnx"
    checkpoint = runs / variant / f"{desc.name}.pt"
    checkpoint.unlink(missing_ok=True)
    geo = resolve(desc)
    if overrides.get("base") == "maps":
        overrides = {**overrides, "base": base_resolution(geo)}
    if overrides.get("relief") == "maps":
        overrides = {**overrides, "relief": relief_resolution(geo)}
    if overrides.get("resolution") == "maps":
        overrides = {**overrides, "resolution": base_resolution(geo)}
    trainer = Trainer(data, checkpoint, MaterialConfig(**{**RECIPE, **overrides}), config,
                      maps=(maps, geo) if maps is not None or overrides.get("base") or overrides.get("relief") else None)
    if variant.split("_seed")[0] in ("HL", "VISHL"):
        sibling("grazing")
        from base_footprints import level_horizon_maps

        from neumip.core import weights as W
        trainer.material.set_maps(W.BASE, level_horizon_maps(geo, overrides["base"]))
    start, cpu = time.perf_counter(), time.process_time()
    pruned = PRUNED.get(variant.split("_seed")[0])
    held = trainer.run(pruning_callback(trainer, *pruned) if pruned else None)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    export_material(trainer.material, out, f"experiments/maps/maps.py {variant}", held)
    record = {"variant": variant, "data": data, "queries": len(trainer.data), "steps": trainer.state.step,
              "batch": config.batch, "train_seconds": round(seconds, 1), "cpu_seconds": round(cpu, 1), "held_out_mse": held["overall"]["mse"],
              "load_average": os.getloadavg(), "onnx_mb": round(out.stat().st_size / 1e6, 2),
              "progress": [[step, overall] for step, _, overall in trainer.state.progress],
              "device": str(trainer.device)}
    if reference is not None:
        from neumip.groundtruth.dataset import open_dataset
        from neumip.training.loop.fit import reference_error

        record["reference_log_mse"] = reference_error(trainer.material, open_dataset(reference))
    (runs / variant / f"{desc.name}.json").write_text(json.dumps(record, indent=1) + "\n")
    trainer.save_checkpoint()  # kept: `bake` re-evaluates a map model's encoder at other resolutions
    judged = f", reference log MSE {record['reference_log_mse'] * 1e3:.3f}e-3" if reference is not None else ""
    print(f"{variant}: {seconds:.0f} s on {trainer.device}, held-out MSE {held['overall']['mse'] * 1e3:.4f}e-3{judged}, "
          f"load {os.getloadavg()[0]:.1f} -> {out}", flush=True)


def bake(variant: str, material: str, runs: Path, resolution: int) -> None:
    """A trained map model's encoder evaluated on its maps prefiltered to a pyramid of `resolution`
    texels per side (its decoder and offset network unchanged) -> RUNS/VARIANT_bRESOLUTION/MATERIAL.onnx."""
    import torch

    from neumip.training.loop import checkpoint
    from neumip.training.export.graph import export_material
    from neumip.training.model.maps import prefilter
    from neumip.training.model.material import MapMaterial
    from neumip.groundtruth.description import find_description, resolve

    desc = find_description(material)
    trained, _ = checkpoint.load(runs / variant / f"{desc.name}.pt")
    config = replace(trained.config, resolution=resolution)
    features = prefilter(resolve(desc), config.level_sizes(), trained.maps.horizons)
    baked = MapMaterial(config, trained.maps, features)
    shared = {k: v for k, v in trained.state_dict().items()
              if k.split(".")[0] in ("encoder", "offset_encoder", "decoder", "offset_mlp")}
    missing = baked.load_state_dict(shared, strict=False)
    assert not missing.unexpected_keys, missing.unexpected_keys
    out = runs / f"{variant}_b{resolution}" / f"{desc.name}.onnx"
    with torch.no_grad():
        export_material(baked, out, f"experiments/maps/maps.py bake {variant} {resolution}")
    print(f"{variant} baked at {resolution}^2 -> {out} ({out.stat().st_size / 1e6:.2f} MB)")


def speed(variants: list[str], data: str, material: str, rounds: int, steps: int) -> None:
    """Seconds per training step of each variant (one thread), interleaved round by round, median
    of the rounds; steps inside the blur schedule (its most expensive part)."""
    import tempfile

    import torch

    from neumip.groundtruth.description import find_description, resolve
    from neumip.training.loop.train import Trainer

    torch.set_num_threads(1)
    geo = resolve(find_description(material))
    trainers = {}
    with tempfile.TemporaryDirectory() as tmp:
        for variant in variants:
            overrides, maps, config = VARIANTS[variant]
            trainers[variant] = Trainer(data, Path(tmp) / f"{variant}.pt", MaterialConfig(**{**RECIPE, **overrides}),
                                        replace(config, checkpoint_every=10**9),
                                        maps=None if maps is None else (maps, geo))
        times: dict = {v: [] for v in variants}
        for _ in range(rounds):
            for variant, trainer in trainers.items():
                start = time.perf_counter()
                for _ in range(steps):
                    trainer.step()
                times[variant].append((time.perf_counter() - start) / steps)
    print(f"load average {os.getloadavg()[0]:.1f}; seconds per step (batch {SHIP.batch}), median of {rounds} rounds:")
    for variant, t in times.items():
        print(f"  {variant:<10} {np.median(t):.4f}  ({np.median(t) / np.median(times[variants[0]]):.2f}x {variants[0]})")


def score(variants: list[str], material: str, runs: Path, cache_dir: str, camera_res: int, out: str,
          levels=LEVELS) -> None:
    from neumip.engines.kernel import KernelMaterials
    from neumip.groundtruth.description import find_description, resolve
    from neumip.report import metrics as Q
    from neumip.report.cache import RenderCache
    from neumip.report.config import FULL
    from neumip.report.pipeline import REFERENCE_SEEDS
    from neumip.report.renderer import MaterialRenderer

    desc = find_description(material)
    geo, name = resolve(desc), desc.name
    cache = RenderCache(cache_dir)
    config = replace(FULL, reference_spp=REFERENCE_SPP)
    renderers = {}
    for variant in variants:
        folder = runs / variant
        r = MaterialRenderer(name, desc, geo, folder, KernelMaterials(folder), config, cache)  # as `neumip render`
        r.resolution = camera_res  # every variant seen from the same cameras
        renderers[variant] = r
    first = renderers[variants[0]]
    for view in views(levels):
        refs = [first.render(view, "R", config.reference_spp, s)[0] for s in REFERENCE_SEEDS]
        first.release()
        ref = (refs[0] + refs[1]) / 2
        images = {"C": first.render(view, "C", SPP, SEED)[0]}
        first.release()
        for variant, r in renderers.items():
            images[variant] = r.render(view, "N", SPP, SEED)[0]
            r.release()
        for method, image in images.items():
            s, _ = Q.score(ref, image, Q.exposure_for(ref))
            row = {"material": name, "camera_res": camera_res, "view": view.name, "method": method,
                   "mse": s.mse, "flip": s.flip, "mean_ratio": s.mean_ratio, "p99_ratio": s.p99_ratio,
                   "load_average": os.getloadavg()[0]}
            with open(out, "a") as f:
                f.write(json.dumps(row) + "\n")
            print(f"{name} {view.name:<14} {method:<10} MSE {s.mse * 1e3:.3f}e-3 FLIP {s.flip:.3f} "
                  f"mean {s.mean_ratio:.3f} p99 {s.p99_ratio:.3f}", flush=True)
        saved = Path(Path(out).with_suffix("").as_posix() + f"_{name}_{camera_res}_{view.name}.npz")
        if saved.exists():  # keep the other variants' images of this view
            with np.load(saved) as old:
                images = {**{k: old[k] for k in old.files if k != "R"}, **images}
        np.savez_compressed(saved, R=ref, **images)


def table(path: str) -> None:
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    groups: dict = {}
    for r in rows:  # the last row of each (material, camera, view, method) wins
        groups.setdefault((r["material"], r["camera_res"]), {})[(r["view"], r["method"])] = r
    for (material, camera_res), cells in groups.items():
        view_names = list(dict.fromkeys(v for v, _ in cells))
        methods = list(dict.fromkeys(m for _, m in cells))
        print(f"\n== {material}, cameras for {camera_res}^2 texels: MSE x1e-3 / FLIP (mean luminance / R's)")
        print(f"{'view':<15}" + "".join(f"{m:>24}" for m in methods))
        for v in view_names:
            line = f"{v:<15}"
            for m in methods:
                c = cells.get((v, m))
                line += f"{c['mse'] * 1e3:>9.3f} / {c['flip']:.3f} ({c['mean_ratio']:.2f})" if c else f"{'-':>24}"
            print(line)
        first = next(m for m in methods if m != "C")  # the others against the first model scored
        for m in methods:
            if m in ("C", first):
                continue
            ratios = [cells[(v, m)]["mse"] / cells[(v, first)]["mse"] for v in view_names
                      if (v, m) in cells and (v, first) in cells]
            print(f"  {m} against {first}: MSE lower by more than 5 % in {sum(r < 0.95 for r in ratios)} of "
                  f"{len(ratios)} views, higher in {sum(r > 1.05 for r in ratios)}; ratios {min(ratios):.2f}-{max(ratios):.2f}")


def spread(path: str, seeds: list[str]) -> None:
    """Each view's MSE over the runs `seeds` (one recipe, other seeds), and every other variant scored against
    their median: the run-to-run spread that a lever measured on one run must beat."""
    rows = [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
    cells = {(r["material"], r["view"], r["method"]): r for r in rows}  # the last row of each wins
    for material in dict.fromkeys(r["material"] for r in rows):
        view_names = sorted({v for m, v, _ in cells if m == material})
        runs = [s for s in seeds if all((material, v, s) in cells for v in view_names)]
        if not runs:
            continue
        median = {v: float(np.median([cells[(material, v, s)]["mse"] for s in runs])) for v in view_names}
        print(f"\n== {material}: {len(runs)} runs of one recipe ({', '.join(runs)}); image MSE x1e-3")
        for v in view_names:
            mse = [cells[(material, v, s)]["mse"] for s in runs]
            mean = [cells[(material, v, s)]["mean_ratio"] for s in runs]
            print(f"  {v:<15} {min(mse) * 1e3:.3f}-{max(mse) * 1e3:.3f} (max / min {max(mse) / min(mse):.2f}); "
                  f"mean luminance / R's {min(mean):.2f}-{max(mean):.2f}")
        variants = dict.fromkeys(m for (mat, _, m) in cells if mat == material and m != "C")
        for m in variants:
            if not all((material, v, m) in cells for v in view_names):
                continue
            ratios = [cells[(material, v, m)]["mse"] / median[v] for v in view_names]
            print(f"  {m:<16} / the runs' median: geometric mean {np.exp(np.mean(np.log(ratios))):.2f}, lower by more "
                  f"than 5 % in {sum(r < 0.95 for r in ratios)} of {len(ratios)} views, higher in "
                  f"{sum(r > 1.05 for r in ratios)} ({' '.join(f'{r:.2f}' for r in ratios)})")


def ensemble(renders: list[str], members: list[str]) -> None:
    """The image of K runs' mean answer, against each run's: `score`'s saved renders (RUNS... .npz) of `members`
    averaged (the render is linear in the material's answers; the runs' renders share their sample paths)."""
    from neumip.report import metrics as Q

    ratios = []
    for path in renders:
        with np.load(path) as saved:
            ref, images = saved["R"], [saved[m] for m in members]
        exposure = Q.exposure_for(ref)
        single = [Q.score(ref, image, exposure)[0].mse for image in images]
        mean = Q.score(ref, np.mean(images, axis=0), exposure)[0]
        ratios.append(mean.mse / float(np.median(single)))
        print(f"{Path(path).stem:<40} runs {' '.join(f'{e * 1e3:.3f}' for e in single)}  their mean answer "
              f"{mean.mse * 1e3:.3f} ({ratios[-1]:.2f}x the median run; mean luminance {mean.mean_ratio:.2f})")
    print(f"the mean answer over the median run: geometric mean {np.exp(np.mean(np.log(ratios))):.2f} "
          f"({min(ratios):.2f}-{max(ratios):.2f}) over {len(ratios)} views")


def strip(out: str, renders: list[str], methods: list[str], scale: int = 3) -> None:
    """A PNG of close-ups: one row per saved view (`score`'s .npz files), R then `methods`, all
    tone-mapped with R's exposure (the report's tone mapping)."""
    from PIL import Image

    from neumip.report.metrics import exposure_for, tonemap

    rows = []
    for path in renders:
        with np.load(path) as d:
            e = exposure_for(d["R"])
            rows.append(np.concatenate([tonemap(d[m], e) for m in ["R", *methods]], axis=1))
    img = (np.concatenate(rows, axis=0) * 255).round().astype(np.uint8)
    Image.fromarray(img).resize((img.shape[1] * scale, img.shape[0] * scale), Image.NEAREST).save(out)


def main() -> None:
    if len(os.sys.argv) == 3 and os.sys.argv[1] == "--table":
        return table(os.sys.argv[2])
    if len(os.sys.argv) == 4 and os.sys.argv[1] == "--spread":  # --spread SCORES.jsonl SEED_VARIANT,...
        return spread(os.sys.argv[2], os.sys.argv[3].split(","))
    if len(os.sys.argv) > 3 and os.sys.argv[1] == "--ensemble":  # --ensemble VARIANT,... RENDER.npz ...
        return ensemble(os.sys.argv[3:], os.sys.argv[2].split(","))
    if len(os.sys.argv) > 4 and os.sys.argv[1] == "--strip":  # --strip OUT.png METHODS,... RENDER.npz ...
        return strip(os.sys.argv[2], os.sys.argv[4:], os.sys.argv[3].split(","))
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train")
    t.add_argument("variants", nargs="+", choices=tuple(VARIANTS))
    t.add_argument("--data", required=True)
    t.add_argument("--material", required=True, help="library name or .toml of the data's material")
    t.add_argument("--runs", type=Path, default=Path("runs/maps"))
    t.add_argument("--threads", type=int, default=1)
    t.add_argument("--validate-every", type=int, default=0, help="record the held-out MSE every this many steps")
    t.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    t.add_argument("--reference", help="a low-noise data set (make_models.sh's runs/NAME/reference): its log MSE")
    v = sub.add_parser("speed")
    v.add_argument("variants", nargs="+", choices=tuple(VARIANTS))
    v.add_argument("--data", required=True)
    v.add_argument("--material", required=True)
    v.add_argument("--rounds", type=int, default=3)
    v.add_argument("--steps", type=int, default=10)
    b = sub.add_parser("bake")
    b.add_argument("variant")
    b.add_argument("--material", required=True)
    b.add_argument("--runs", type=Path, default=Path("runs/maps"))
    b.add_argument("--resolution", type=int, required=True)
    s = sub.add_parser("score")
    s.add_argument("variants", nargs="+")
    s.add_argument("--material", required=True)
    s.add_argument("--runs", type=Path, default=Path("runs/maps"))
    s.add_argument("--cache", default="runs/maps/renders")
    s.add_argument("--camera-res", type=int, default=64)
    s.add_argument("--out", required=True)
    s.add_argument("--levels", type=int, nargs="+", default=list(LEVELS),
                   help="footprints at the image centre, 2^level texels (default: 1 and 4)")
    args = p.parse_args()
    if args.command == "train":
        for variant in args.variants:
            train(variant, args.data, args.material, args.runs, args.threads, args.validate_every, args.device,
                  args.reference)
    elif args.command == "bake":
        bake(args.variant, args.material, args.runs, args.resolution)
    elif args.command == "speed":
        speed(args.variants, args.data, args.material, args.rounds, args.steps)
    else:
        score(args.variants, args.material, args.runs, args.cache, args.camera_res, args.out, args.levels)


if __name__ == "__main__":
    main()
