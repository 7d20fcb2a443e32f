"""What a training run leaves next to its model: NAME.onnx, NAME.json, NAME.loss.png, NAME.progress.png.

NAME.json holds the validation table plus the run's settings; the ONNX metadata carries the same
table under `contract.META_VALIDATION`. The model is exported from the trained material in memory.
NAME.progress.png is redrawn at every progress validation while the run goes: the loss and the
held-out MSE per level against steps, and ground truth beside the model for a few views at a few
levels (training/loop/views.py).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.core.files import atomic_write
from neumip.training.export.graph import export_material
from neumip.training.loop.paths import progress_path, sidecar_paths, staging_folder
from neumip.training.loop.train import Trainer
from neumip.training.loop.validation import predict
from neumip.training.loop.views import ViewGrid, grid_levels, images, view_queries

log = logging.getLogger(__name__)




def _tonemap(x: np.ndarray, white: float) -> np.ndarray:
    """Linear RGB -> displayable [0, 1] (scaled so `white` maps to 1, sRGB-like gamma)."""
    return np.clip(np.maximum(x, 0) / white, 0, 1) ** (1 / 2.2)


def write_progress(trainer: Trainer, path: Path, views=None, grid: ViewGrid | None = None) -> Path:
    """Draw the run's progress so far: loss and held-out MSE per level against steps, and (with a
    `views` data set from `views.trace_views`) ground truth beside the model's images as it is now.
    Without `views` the image grid shows the model only. Written atomically (temp file, rename)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = grid or ViewGrid()
    resolution = trainer.material.config.resolution
    levels = grid_levels(grid, resolution)
    queries = view_queries(grid, resolution)
    trainer.material.eval()
    model = images(predict(trainer.material, queries, *trainer.current_textures()), grid, resolution)
    trainer.material.train()
    truth = images(np.asarray(views.rgb), grid, resolution) if views is not None else None
    panels = 2 if truth is not None else 1
    n_views, n_levels = model.shape[:2]
    fig = plt.figure(figsize=(4.5 + 1.3 * n_levels * panels, max(3.6, 1.3 * n_views + 0.6)), dpi=100)
    outer = fig.add_gridspec(1, 2, width_ratios=[4.5, 1.3 * n_levels * panels], wspace=0.15, left=0.07, right=0.98)
    ax = fig.add_subplot(outer[0])
    state = trainer.state
    if state.history:
        steps, losses = zip(*state.history)
        ax.plot(steps, losses, lw=1, color="0.5", label=f"training loss ({trainer.config.loss})")
    if state.progress:
        by_level: dict[int, list] = {}
        for step, rows, _overall in state.progress:
            for level, mse in rows:
                by_level.setdefault(level, []).append((step, mse))
        for level, points in sorted(by_level.items()):
            xs, ys = zip(*points)
            ax.plot(xs, ys, marker=".", lw=1, label=f"held-out MSE, level {level}")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_title(f"step {state.step} of {trainer.config.steps}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6)
    cells = outer[1].subgridspec(n_views, n_levels * panels, wspace=0.05, hspace=0.1)
    white = 1.25 * float(np.percentile(truth if truth is not None else model, 99)) or 1.0  # p99 -> 0.9
    for i in range(n_views):
        for j, level in enumerate(levels):
            shown = [("truth", truth), ("model", model)] if truth is not None else [("model", model)]
            for k, (label, stack) in enumerate(shown):
                a = fig.add_subplot(cells[i, j * panels + k])
                a.imshow(_tonemap(stack[i, j], white), origin="lower", interpolation="nearest")
                a.set_xticks([])
                a.set_yticks([])
                if i == 0:
                    a.set_title(f"L{level} {label}", fontsize=7)
                if j == 0 and k == 0:
                    light_az, light_zen, view_az, view_zen = grid.views[i]
                    a.set_ylabel(f"light {light_zen:.0f}\u00b0\nview {view_zen:.0f}\u00b0", fontsize=7)
    path.parent.mkdir(parents=True, exist_ok=True)  # mid-run: the model's folder may not exist yet
    try:
        return atomic_write(path, fig.savefig, keep_suffix=True)  # matplotlib's format: by the suffix
    finally:
        plt.close(fig)


def write_loss_curve(history: list, path: Path, title: str) -> Path:
    """Plot [step, loss] records (log scale) to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    if history:
        steps, losses = zip(*history)
        ax.plot(steps, losses, lw=1)
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def write_outputs(trainer: Trainer, table: dict, output: str | Path, views=None) -> dict[str, Path]:
    """Export the trained material to `output` (.onnx) and write the validation JSON, the loss PNG and
    the final progress PNG (`views`: the ground truth data set of the progress grid, or None)."""
    output = Path(output)
    json_path, png_path = sidecar_paths(output)
    record = {
        "model": output.name,
        "data": str(trainer.data.path),
        "data_meta": {k: trainer.data.meta[k] for k in ("material", "generator", "n") if k in trainer.data.meta},
        "material_config": json.loads(trainer.material.config.to_json()),
        "train_config": trainer.config.to_dict(),
        "validation": table,
    }
    onnx_path = export_material(trainer.material, output, trainer.description, table, trainer.sampling)
    json_path.write_text(json.dumps(record, indent=2) + "\n")
    write_loss_curve(trainer.state.history, png_path, f"{output.stem}: {trainer.config.loss} loss")
    progress = write_progress(trainer, progress_path(output), views)
    log.info("wrote %s (%.2f MB), %s, %s, %s", onnx_path, onnx_path.stat().st_size / 1e6, json_path, png_path,
             progress)
    return {"onnx": onnx_path, "json": json_path, "png": png_path, "progress": progress}


def install_outputs(trainer: Trainer, table: dict, output: str | Path, views=None) -> dict[str, Path]:
    """`write_outputs` into a hidden staging folder beside `output`, then move each file into place,
    ``NAME.json`` last: a model whose record exists is whole, and an interrupted export leaves no
    half-written file under the model's name."""
    output = Path(output)
    staging = staging_folder(output)
    shutil.rmtree(staging, ignore_errors=True)  # left by an interrupted export
    staging.mkdir(parents=True)
    paths = write_outputs(trainer, table, staging / output.name, views)
    output.with_name(paths["json"].name).unlink(missing_ok=True)  # an old record must not vouch for new files
    for kind in sorted(paths, key=lambda k: k == "json"):  # the record last: it marks the model whole
        final = output.with_name(paths[kind].name)
        os.replace(paths[kind], final)
        paths[kind] = final
    staging.rmdir()
    return paths


def export_checkpoint(checkpoint: str | Path, out: str | Path, description: str = "",
                      sampling: C.SamplingLobe | None | str = "keep", half_textures: bool = False) -> Path:
    """`neumip export`: read a training checkpoint, write the ONNX model.

    A checkpoint written mid-run holds raw textures while training evaluated blurred copies: the
    blur of its step is baked in first, so the model computes what training computed. `sampling`: the
    sampling lobe to declare (None: none), or ``"keep"`` the checkpoint's. `half_textures`: store its textures in
    float16 (`MaterialConfig.half_textures`), rounded where the run kept them float32.
    """
    from neumip.training.loop.blur import bake_checkpoint_textures
    from neumip.training.loop.checkpoint import load

    material, extra = load(checkpoint)
    if half_textures:
        material.config = replace(material.config, half_textures=True)
    if bake_checkpoint_textures(material, extra):
        log.warning(
            "%s was written mid-run (step %d): exporting with that step's blurred textures",
            checkpoint, extra["state"]["step"],
        )
    description = description or extra.get("description", "")
    if sampling == "keep":  # the checkpoint's own (`Trainer.sampling`)
        sampling = C.SamplingLobe(**extra["sampling"]) if extra.get("sampling") else None
    return export_material(material, out, description, extra.get("validation"), sampling)
