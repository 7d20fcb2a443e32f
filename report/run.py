"""One report run: images of every material, stability, the model trade-off; then results.json,
the charts and report.md. Each render and each trained configuration is cached, so a re-run after
an interruption continues where it stopped."""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from neumip.core.errors import NeumipError

from neumip.report import charts, stability, tradeoff
from neumip.report import metrics as Q
from neumip.report.analysis import close_up_checks, headline, time_to_error, verdicts
from neumip.report.cache import RenderCache
from neumip.report.config import ReportConfig
from neumip.report.methods import NEURAL_MODELS, NO_OFFSET, neural_models
from neumip.report.pipeline import REFERENCE_SEEDS, run_material, view_steps
from neumip.report.renderer import CACHE_VERSION, NEURAL_VERSION, file_digest
from neumip.report.views import DISTANCE_VIEWS, LADDER_LIGHT, VIEWS, View

log = logging.getLogger(__name__)

TRADEOFF_MATERIAL = "rock"
"""The material whose configurations the trade-off trains (the deepest shipped relief)."""
TRADEOFF_VIEW = next(v for v in DISTANCE_VIEWS if v.light == LADDER_LIGHT and v.level == 2)
"""The view whose image error the trade-off reports (4 map texels, the ladder light)."""
HORIZON_MATERIAL = "yarn"
"""The material of the plane-to-the-horizon render."""


class Progress:
    """Progress callbacks: ``stage(name, total)`` then ``tick()`` per step."""

    def stage(self, name: str, total: int) -> None:
        log.info("%s (%d steps)", name, total)

    def tick(self) -> None:
        pass


def _jsonable(results: dict) -> dict:
    """The view results without images, spp keys as strings."""
    out = {}
    for view, res in results.items():
        out[view] = {
            "reference": res["reference"], "mip_level": res["mip_level"], "fits": res["fits"], "film": res["film"],
            "methods": {m: {str(s): e for s, e in sorted(entries.items())} for m, entries in res["methods"].items()},
        }
    return out


def find_materials(materials: list[str], models: Path) -> dict:
    """``{name: description}`` of shipped names and description files alike, each with its model
    ``models/<description's name>.onnx``. Everything is checked before anything is written: a
    description that cannot be read, or a model file missing or unusable (corrupt, another contract
    version) raises one :class:`NeumipError`."""
    from neumip.engines.local import load_material
    from neumip.groundtruth.description import find_description

    descriptions = {}
    for arg in materials:
        desc = find_description(arg)
        if desc.name in descriptions:
            raise ReportError(f"material {desc.name!r} is given twice ({arg})")
        for path in neural_models(desc.name, models).values():  # raises if NAME.onnx is missing
            load_material(path)  # a corrupt or outdated file fails here, before any render (ModelError)
        descriptions[desc.name] = desc
    return descriptions


def missing_ablations(name: str, present: tuple[str, ...], models: Path) -> list[str]:
    """A note per judged neural method present whose no-offset ablation is not (its offset's gain is not shown)."""
    return [f"no {NEURAL_MODELS[ablation].format(name=name)} model in {models}: {ablation} and {method}'s offset "
            "gain not shown" for method, ablation in NO_OFFSET.items() if method in present and ablation not in present]


class ReportError(NeumipError, ValueError):
    """Arguments of a report that cannot be run."""


def run_report(out: Path, materials: list[str], config: ReportConfig, models: Path, cache_dir: Path,
               progress: Progress | None = None, stages: tuple[str, ...] = ("images", "stability", "tradeoff"),
               views: tuple[View, ...] = VIEWS, command: str = "neumip report") -> dict:
    """Run the report on ``materials`` (shipped names or description files) and write it to ``out``."""
    from neumip.engines.local import LocalMaterials
    from neumip.engines.kernel import KernelMaterials
    from neumip.groundtruth.description import resolve

    from neumip.report.renderer import MaterialRenderer

    descriptions = find_materials(materials, models)
    progress = progress or Progress()
    final, out = out, staging_folder(out)
    cache = RenderCache(cache_dir / "renders")
    evaluator = LocalMaterials(models, threads=config.threads)  # query sweeps: the ONNX graph
    renders = KernelMaterials(models)  # neural renders: in the render's kernels, as `neumip render`
    start = time.perf_counter()
    results: dict = {"config": asdict(config), "command": command, "materials": {}, "notes": []}
    renderers = {}
    for name, desc in descriptions.items():
        renderers[name] = MaterialRenderer(name, desc, resolve(desc), models, renders, config, cache)
        results["notes"] += missing_ablations(name, renderers[name].methods, models)
    images: dict = {}
    if "images" in stages:
        progress.stage("renders", sum(view_steps(r, v) for r in renderers.values() for v in views))
        for name, r in renderers.items():
            images[name] = run_material(r, views, progress.tick)
            results["materials"][name] = _jsonable(images[name])
            for view, res in images[name].items():
                charts.strip(res, out / "strips" / f"{name}_{view}.png", f"{name}, {view}")
            ladder_views = [v.name for v in views if v.ladder]
            if ladder_views:
                charts.error_time(images[name], ladder_views, out / f"error_time_{name}.png", f"{name}: error against time")
            mat = results["materials"][name]
            mat["headline"] = headline(images[name], config.spp)
            mat["verdicts"] = verdicts(mat["headline"])
            mat["close_up"] = close_up_checks(images[name], config.spp)
            if not config.smoke:
                mat["time_to_error"] = time_to_error(images[name], config.spp)
    if "stability" in stages:
        results["stability"] = run_stability(out, descriptions, config, evaluator, renders, cache, progress, models)
    if "tradeoff" in stages and TRADEOFF_MATERIAL in renderers:
        results["tradeoff"] = run_tradeoff(out, renderers[TRADEOFF_MATERIAL], config, cache_dir, progress)
    results["seconds"] = time.perf_counter() - start
    results["cached_renders_reused"] = cache.hits
    results["render_seconds"] = cache.seconds
    (out / "results.json").write_text(json.dumps(results, indent=1, default=float))
    from neumip.report.writer import write_markdown

    write_markdown(out, results, config)
    publish(out, final)
    return results


def staging_folder(out: Path) -> Path:
    """An empty folder beside ``out`` where a run writes its report until it is whole."""
    stage = out.parent / f".{out.name}.partial"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir(parents=True)
    return stage


def publish(stage: Path, out: Path) -> None:
    """Move a whole report from ``stage`` into ``out``, replacing what a run writes (its files and its
    ``strips/``, whole) and leaving anything else in ``out`` alone; ``report.md`` goes last. An
    interrupted run never reaches this: ``out`` keeps the previous whole report."""
    out.mkdir(parents=True, exist_ok=True)
    for entry in sorted(stage.iterdir(), key=lambda p: p.name == "report.md"):
        target = out / entry.name
        if target.is_dir():
            shutil.rmtree(target)
        os.replace(entry, target)
    stage.rmdir()


def run_stability(out, materials, config, evaluator, renders, cache, progress, models: Path) -> dict:
    names = [f.stem for m in materials for f in neural_models(m, models).values()]
    progress.stage("stability", len(names) + 2)
    sweeps = {}
    for name in names:
        resolution = evaluator.get(name).file.require_config("the stability sweeps read its resolution").resolution
        sweeps[name] = stability.sweeps(evaluator, name, config.sweep_points, resolution)
        progress.tick()
    charts.sweeps(sweeps, out / "stability_sweeps.png")
    result = {"sweeps": {n: _summary(s) for n, s in sweeps.items()}}
    if HORIZON_MATERIAL in materials:
        result["horizon"] = horizon(out, materials[HORIZON_MATERIAL], config, evaluator, renders, cache, progress)
    return result


def _summary(sweep: dict) -> dict:
    """The sweep figures without the curves (the curves are in the chart)."""
    return {kind: {k: v for k, v in r.items() if not isinstance(v, list) or k in ("shift_tiles", "max_rel_change")}
            for kind, r in sweep.items()}


def horizon(out, desc, config, evaluator, renders, cache, progress) -> dict:
    from neumip.client.mitsuba import render as R
    from neumip.groundtruth.description import resolve

    from neumip.report.methods import classical_bsdf

    mi = R.mi
    geo = resolve(desc)  # the description given (a user's file may be named like a shipped material)
    bsdfs = {
        "N": lambda scale: {"type": "neumip", "material": HORIZON_MATERIAL, "uv_scale": scale},
        "C": lambda scale: classical_bsdf(mi, geo, scale),
    }
    images, rows = {}, {}
    for method, make in bsdfs.items():
        key = {"version": CACHE_VERSION, "horizon": HORIZON_MATERIAL, "method": method, "film": asdict(config.horizon_film), "spp": config.spp}
        if method == "N":
            key["model"], key["neural_version"] = file_digest(evaluator.get(HORIZON_MATERIAL).path), NEURAL_VERSION
        cached = cache.get(key)
        if cached is None:
            integrator = "neumip_path" if method == "N" else "path"
            scene = mi.load_dict(stability.horizon_scene(mi, config.horizon_film, make, integrator))
            result = R.render_scene(scene, renders, R.RenderConfig(spp=config.spp, max_lanes=config.max_lanes))
            cache.put(key, result.image[..., :3], result.seconds)
            images[method] = result.image[..., :3]
        else:
            images[method] = cached.image
        rows[method] = stability.row_banding(images[method])
        progress.tick()
    exposure = Q.exposure_for(images["C"])
    charts.horizon(images, exposure, rows, out / "horizon.png")
    return {m: {k: v for k, v in r.items() if k != "row_mean"} for m, r in rows.items()}


def run_tradeoff(out, renderer, config, cache_dir, progress) -> dict:
    from neumip.engines.local import LocalMaterials
    from neumip.engines.kernel import KernelMaterials

    folder = cache_dir / "tradeoff"
    has_maps = renderer.geo.height.shape[0] > 1
    variants = tradeoff.variants(config, maps=has_maps)
    progress.stage("trade-off: data", 1)
    train, ref = tradeoff.datasets(renderer.desc, folder / "data", config)
    progress.tick()
    progress.stage("trade-off: training", len(variants))
    costs = {}
    for v in variants:
        _, costs[v.name] = tradeoff.train_variant(v, train, folder / "models", config, renderer.geo)
        progress.tick()
    evaluator = LocalMaterials(folder / "models", threads=config.threads)
    renders = KernelMaterials(folder / "models")
    names = [v.name for v in variants]
    qps = tradeoff.queries_per_second(evaluator, names)
    view = TRADEOFF_VIEW
    spec = renderer.spec(view)
    reference_images = [renderer.render(view, "R", config.reference_spp, s)[0] for s in REFERENCE_SEEDS]
    reference = (reference_images[0] + reference_images[1]) / 2
    renderer.release()  # the reference scene's instances slow every other render while alive
    points = {}
    progress.stage("trade-off: measure", len(variants))
    for v in variants:
        image = _render_variant(renderer, spec, renders, v.name, folder / "models" / f"{v.name}.onnx", config, view)
        points[v.name] = {**tradeoff.describe(v), **costs[v.name], "queries_per_second": qps[v.name],
                          "validation_mse": tradeoff.validation_mse(evaluator, v.name, ref),
                          "image_mse": Q.mse(reference, image), "image_view": view.name}
        progress.tick()
    charts.tradeoff(points, out / "tradeoff.png")
    note = None if has_maps else (f"{renderer.name} has no height map (its height is 1 x 1): no map-informed "
                                  "variants")
    return {"material": renderer.name, "points": points, "seeds": tradeoff.summary(points),
            "steps": config.tradeoff_steps, "batch": config.tradeoff_batch, "note": note}


def _render_variant(renderer, spec, renders, name, onnx, config, view) -> np.ndarray:
    from neumip.client.mitsuba import render as R

    from neumip.report.methods import neural_scene

    key = {"version": CACHE_VERSION, "tradeoff": name, "model": file_digest(onnx), "view": asdict(view), "film": asdict(spec.film),
           "spp": config.spp, "resolution": spec.resolution, "neural_version": NEURAL_VERSION}
    cached = renderer.cache.get(key)
    if cached is not None:
        return cached.image
    scene = R.mi.load_dict(neural_scene(R.mi, spec, name))
    result = R.render_scene(scene, renders, R.RenderConfig(spp=config.spp, max_lanes=config.max_lanes))
    renderer.cache.put(key, result.image[..., :3], result.seconds)
    return result.image[..., :3]
