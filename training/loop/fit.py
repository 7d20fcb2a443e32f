"""One material description to one model: ground truth, training, validation and export in one run.

`fit` chains what `neumip generate` and `neumip train` do, in a work folder beside the model
(``NAME.run/`` next to ``NAME.onnx`` unless told otherwise; `neumip train` keeps its checkpoint there
too)::

    NAME.run/
      data/            the path-traced MBTF data set (resumable chunks, groundtruth/dataset.py)
      checkpoint.pt    the training run (resumes exactly where it stopped)
      views/           ground truth of the progress grid (training/loop/views.py)

Every stage resumes when the same call is made again after an interruption: the data set continues
at its first unfinished chunk, training at its last checkpoint. The model and its sidecar files are
written into a staging folder and moved into place one by one, ``NAME.json`` last, so a model
whose ``NAME.json`` exists is whole (`fitted`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from neumip.core.config import MaterialConfig
from neumip.training.loop.paths import work_folder

from neumip.training.model.maps import MapConfig
from neumip.training.loop.config import SHIP, TrainConfig

if TYPE_CHECKING:  # Mitsuba is imported only when a fit runs
    from neumip.groundtruth.generate import GenerateSettings

log = logging.getLogger(__name__)

BASE_MARGIN = 0.10
"""`FitSettings.choose_base` keeps the base only when its error on the reference queries (`reference_error`) is
this much lower (a fraction) than the model's without it: a new stage is kept for a clear gain (why this
margin: training/TRAINING.md)."""
REFERENCE_QUERIES = 1 << 14
"""Queries of the low-noise reference set that `FitSettings.choose_base` compares on (``WORK/reference``)."""
REFERENCE_SPP = 256
"""Path samples per reference query (16x the training data's: its noise adds 1/16 of theirs to an MSE)."""

MIN_QUERIES = 1 << 20
"""The queries `fit` traces by default for a 1 x 1 model (a material without maps, a homogeneous [bsdf]), whose answer
still varies with the footprint and both directions: the 2^20 of a 64^2 model at 256 a texel, not 256."""

STAGES = ("ground truth", "progress views", "training", "noise check", "export")
"""The stages of a fit, in order, as `Report` names them."""

Report = Callable[[str, int, int | None], None]
"""Called with (stage, done, total) as a fit goes: queries traced, steps trained (total None where
a stage has no count)."""


@dataclass
class FitSettings:
    """How one material description becomes a model."""

    material: MaterialConfig
    """Architecture. The ground truth has `queries_per_texel` queries per texel of its finest level,
    with footprints sampled for the material's own resolution (its maps') where that is finer: the
    renders that look closest ask for footprints that small."""
    train: TrainConfig = SHIP
    """Training schedule (a `train_config.PRESETS` value, possibly with overrides)."""
    generate: GenerateSettings | None = None
    """Ground-truth settings (None: the defaults); their `resolution` and `queries`, when given,
    replace the footprints' resolution and the count above."""
    work: Path | None = None
    """Folder of the data, checkpoint and views (None: ``NAME.run/`` beside the model)."""
    data: Path | None = None
    """Data set folder (None: ``WORK/data``); models of one material with other architectures, e.g.
    without the neural offset, can share one."""
    description: str = ""
    """Stored in the model's metadata."""
    views_material: str | None = None
    """Description whose ground truth the progress grid shows (None: the fitted one)."""
    maps: MapConfig | None = None
    """Train a map-informed material whose encoder reads the description's maps (None: the paper's model)."""
    choose_base: bool = False
    """Train the model without and with the classical base (`MaterialConfig.base` at the maps' resolution,
    ``WORK/checkpoint.pt`` and ``WORK/base/checkpoint.pt``) on the same data, and keep the base only where it
    lowers the error on a low-noise reference set (`REFERENCE_QUERIES` at `REFERENCE_SPP`, `reference_error`)
    by `BASE_MARGIN` (`material.base` is then ignored). The held-out split is no judge of it: its 16-spp noise
    is most of its MSE on a glossy material (turtle: 0.8 % lower held-out MSE with the base)."""
    seeds: int = 1
    """Train the model (with `choose_base`, the kept one's configuration) from this many initial weights, seeds
    ``train.seed``, ``train.seed + 1``, ... (``FOLDER/seedK/checkpoint.pt`` beside its first run's), on the same data,
    and keep the one with the lowest error on the reference set (`reference_error`)."""


def data_queries(queries_per_texel: float, resolution: int) -> int:
    """The queries `fit` traces for a model of `resolution`^2 texels at its finest level, unless told: that many per
    texel, and `MIN_QUERIES` for a 1 x 1 model."""
    return max(MIN_QUERIES if resolution == 1 else 1, round(queries_per_texel * resolution**2))


def coarse_texels(train: TrainConfig, material: MaterialConfig, data_resolution: int) -> float:
    """The footprint, in texels of a data set sampled at `data_resolution`, from which `train.coarse_level` applies to a
    model of `material` (`contract.level_of_detail(sigma, material.resolution, lod_bias) >= coarse_level`):
    where `fit --coarse-spp` traces more samples; 0 where the model has no such level (no query is coarse)."""
    if train.coarse_level > math.log2(material.resolution):
        return 0.0
    return 2.0 ** (train.coarse_level - material.lod_bias) * data_resolution / material.resolution


def reference_error(material, data) -> float:
    """Error of a trained material's answers to a data set's queries: the MSE of log1p values (`validation.errors`'
    log_mse; what the comb2 loss trains). Linear MSE is no judge here: a glossy material's glints make it
    heavy-tailed (turtle: the same model's linear MSE on two 16 384-query reference sets 3.98e-3 and 6.21e-3)."""
    import numpy as np

    from neumip.training.loop.validation import errors, predict

    return errors(predict(material, np.asarray(data.queries)), np.asarray(data.rgb, np.float64))["log_mse"]










def fit(description, output: str | Path, settings: FitSettings, report: Report | None = None,
        on_progress: Callable | None = None) -> tuple[dict, dict[str, Path]]:
    """Generate, train, validate and export `description` (a `MaterialDescription`) to `output`.

    Returns the validation table and the files written (`outputs.write_outputs`' keys).
    `report(stage, done, total)` follows the run; `on_progress(trainer)` is called after each
    progress validation (the progress grid is redrawn before it).
    """
    from neumip.groundtruth.generate import GenerateSettings, generate
    from neumip.training.loop.outputs import install_outputs, write_progress
    from neumip.training.loop.paths import progress_path
    from neumip.groundtruth.description import resolve
    from neumip.training.loop.train import Trainer
    from neumip.training.loop.views import ViewGrid, trace_views

    if settings.seeds < 1:
        raise ValueError(f"seeds must be >= 1, got {settings.seeds}")
    report = report or (lambda stage, done, total: None)
    work = work_folder(output, settings.work)
    resolution = settings.material.resolution
    gen = settings.generate or GenerateSettings()
    gen = replace(gen, resolution=gen.resolution or max(resolution, description.resolution),
                  queries=gen.queries or data_queries(gen.sampling.queries_per_texel, resolution))
    if gen.coarse_spp:  # more samples where the coarse loss applies: its level, in texels of the data's resolution
        texels = coarse_texels(settings.train, settings.material, gen.resolution)
        gen = replace(gen, coarse_texels=texels) if texels else replace(gen, coarse_spp=0)
    log.info("fitting %s into %s (work folder %s)", description.name, output, work)
    data = generate(description, settings.data or work / "data", gen,
                    lambda done, total: report(STAGES[0], done, total))  # (N, 7) queries, (N, 3) RGB
    if settings.choose_base or settings.seeds > 1:  # the same footprints and directions, another seed, 16x the samples
        reference = generate(description, work / "reference",
                             replace(gen, queries=REFERENCE_QUERIES, spp=REFERENCE_SPP, coarse_spp=0, seed=gen.seed + 1,
                                     chunk=min(gen.chunk, 1 << 12)),
                             lambda done, total: report(STAGES[0], len(data) + done, len(data) + total))
    report(STAGES[1], 0, None)
    views = trace_views(data.meta.get("material") or {}, ViewGrid(), resolution, work / "views",
                        settings.views_material, data.meta.get("description_dir"))
    geo = resolve(description)
    maps = (settings.maps, geo)
    if settings.choose_base:
        from neumip.training.model.base import base_resolution
        candidates = [(replace(settings.material, base=0, local_frame=False, terminator=MaterialConfig.terminator,
                               visibility_input=False), work),  # (the frame, the terminator, the visibility: the base's)
                      (replace(settings.material, base=base_resolution(geo)), work / "base")]
    else:
        candidates = [(settings.material, work)]
    grid_png = progress_path(output)

    def progress(trainer: Trainer) -> None:
        write_progress(trainer, grid_png, views)
        if on_progress is not None:
            on_progress(trainer)

    total = (len(candidates) + settings.seeds - 1) * settings.train.total_steps
    runs = 0  # trained so far (for the progress report)

    def train(material: MaterialConfig, checkpoint: Path, config: TrainConfig):
        nonlocal runs
        before = runs * settings.train.total_steps  # steps of the runs trained before this one
        runs += 1
        trainer = Trainer(data.path, checkpoint, material, config, settings.description, maps)
        report(STAGES[2], before + trainer.steps_done, total)
        return trainer, trainer.run(lambda step, loss: report(STAGES[2], before + step, total), progress)

    trained = [train(material, folder / "checkpoint.pt", settings.train) for material, folder in candidates]
    (trainer, table), (material, folder) = trained[0], candidates[0]
    choices = {}  # recorded in NAME.json and the model's metadata beside the validation table
    if settings.choose_base:
        without, with_base = (reference_error(t.material, reference) for t, _ in trained)
        keep = with_base < (1.0 - BASE_MARGIN) * without
        if keep:
            (trainer, table), (material, folder) = trained[1], candidates[1]
        choices["base_choice"] = {"reference_log_mse_without": without, "reference_log_mse_with": with_base,
                                  "margin": BASE_MARGIN, "kept": "with" if keep else "without"}
    if settings.seeds > 1:
        seeds = [settings.train.seed + k for k in range(settings.seeds)]
        runs_of_seeds = [(trainer, table)] + [
            train(material, folder / f"seed{k}" / "checkpoint.pt", replace(settings.train, seed=seed))
            for k, seed in enumerate(seeds[1:], 1)]
        errors = [reference_error(t.material, reference) for t, _ in runs_of_seeds]
        best = min(range(len(seeds)), key=errors.__getitem__)
        trainer, table = runs_of_seeds[best]
        choices["seed_choice"] = {"seeds": seeds, "reference_log_mse": errors, "kept": seeds[best]}
        log.info("kept seed %d of %s (reference log MSE %s)", seeds[best], seeds, errors)
    report(STAGES[3], 0, None)
    from neumip.training.loop.validation import predict
    from neumip.training.loop.verdict import noise_check

    choices["noise"] = noise_check(lambda q: predict(trainer.material, q), description, data.meta["generator"])
    table = {**table, **choices}
    report(STAGES[4], 0, None)
    return table, install_outputs(trainer, table, output, views)
