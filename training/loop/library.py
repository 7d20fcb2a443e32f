"""Training a material library: one `neumip train` run per material, in this process or as Ray tasks.

Each material's outputs (``NAME.onnx``, ``NAME.json``, ``NAME.loss.png``) are written into a hidden
folder beside them and moved into place one by one, ``NAME.json`` last. A material whose
``NAME.onnx`` and ``NAME.json`` both exist is finished and a re-run skips it; an interrupted one
resumes from its checkpoint ``RUNS/NAME/checkpoint.pt``, as `neumip train` does. With Ray, the
data sets, models and runs folders must be on a file system every node sees (or one machine).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable

from neumip.core.cluster import RayConfig, as_completed
from neumip.core.config import MaterialConfig
from neumip.training.loop.config import TrainConfig

if TYPE_CHECKING:
    from neumip.training.model.maps import MapConfig

log = logging.getLogger(__name__)

Progress = Callable[[int, float], None]
"""Called with (step, loss) after every training step."""


@dataclass
class MaterialJob:
    """One material of the library."""

    name: str
    """Model name: the outputs are MODELS/NAME.onnx, .json, .loss.png."""
    data: str
    """Data set folder it is trained on."""
    material: MaterialConfig
    """Architecture (resolution, neural offset)."""
    description: str = ""
    """Stored in the model's metadata."""
    maps: MapConfig | None = None
    """The map encoder of a map-informed model (its data's material's maps), None: the paper's latents."""


@dataclass
class LibrarySettings:
    """What every material of the library shares."""

    models: Path
    """Folder of the exported materials."""
    runs: Path
    """Folder of the checkpoints (RUNS/NAME/checkpoint.pt)."""
    config: TrainConfig
    """Training schedule."""
    threads: int = 1
    """Torch CPU threads of each material (with Ray: the CPUs each task reserves)."""


def finished(job: MaterialJob, settings: LibrarySettings) -> bool:
    """Whether the material's model and its record are in place (the record is moved in last)."""
    return all((settings.models / f"{job.name}{suffix}").exists() for suffix in (".onnx", ".json"))


def train_material(job: MaterialJob, settings: LibrarySettings, progress: Progress | None = None) -> dict:
    """Train (or resume) one material and move its outputs into place; returns the validation table."""
    import torch

    from neumip.training.loop.outputs import install_outputs
    from neumip.training.loop.train import Trainer

    torch.set_num_threads(settings.threads)
    checkpoint = settings.runs / job.name / "checkpoint.pt"
    maps = None
    if job.maps or job.material.relief or job.material.base:  # the data's material's maps
        from neumip.training.loop.views import data_geometry

        maps = (job.maps, data_geometry(job.data))
    trainer = Trainer(job.data, checkpoint, job.material, settings.config, job.description, maps)
    table = trainer.run(progress)
    install_outputs(trainer, table, settings.models / f"{job.name}.onnx")
    return table


def train_library(
    jobs: list[MaterialJob],
    settings: LibrarySettings,
    ray: RayConfig | None = None,
    on_done: Callable[[MaterialJob, dict | Exception], None] | None = None,
    progress: Callable[[MaterialJob], Progress] | None = None,
) -> dict[str, dict | Exception]:
    """Train every unfinished material; returns each one's validation table or the error it met.

    In this process the materials run one after another (`progress(job)` gives a step callback);
    with `ray`, one task per material, each reserving `settings.threads` CPUs. A failed material does
    not stop the others.
    """
    if len({job.name for job in jobs}) != len(jobs):
        raise ValueError("two materials of the library have the same name")
    settings.models.mkdir(parents=True, exist_ok=True)
    todo = [job for job in jobs if not finished(job, settings)]
    results: dict[str, dict | Exception] = {}
    report = on_done or (lambda job, result: None)
    if ray is None:
        for job in todo:
            try:
                results[job.name] = train_material(job, settings, progress(job) if progress else None)
            except (ValueError, RuntimeError) as exc:  # the data, checkpoint or training errors
                results[job.name] = exc
            report(job, results[job.name])
        return results
    ray = replace(ray, cpus_per_task=settings.threads)
    for (job, _), result in as_completed(_material_task, [(job, settings) for job in todo], ray):
        results[job.name] = result
        report(job, result)
    return results


def _material_task(job: MaterialJob, settings: LibrarySettings) -> dict:
    """One material in a Ray worker; logs its progress (Ray forwards worker logs to the driver)."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    total = settings.config.total_steps
    every = max(1, total // 10)

    def progress(step: int, loss: float) -> None:
        if step % every == 0:
            log.info("%s: step %d of %d, loss %.4g", job.name, step, total, loss)

    return train_material(job, settings, progress)

