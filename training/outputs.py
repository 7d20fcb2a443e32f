"""What a finished training run leaves next to its model: NAME.onnx, NAME.json, NAME.loss.png.

NAME.json holds the validation table plus the run's settings; the ONNX metadata carries the same
table under `contract.META_VALIDATION`. The model is exported from the trained material in memory.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from .export import export_material
from .train import Trainer

log = logging.getLogger(__name__)


def sidecar_paths(output: str | Path) -> tuple[Path, Path]:
    """models/NAME.onnx -> (models/NAME.json, models/NAME.loss.png)."""
    output = Path(output)
    return output.with_suffix(".json"), output.with_name(output.stem + ".loss.png")


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


def write_outputs(trainer: Trainer, table: dict, output: str | Path) -> dict[str, Path]:
    """Export the trained material to `output` (.onnx) and write the validation JSON and loss PNG."""
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
    onnx_path = export_material(trainer.material, output, trainer.description, table)
    json_path.write_text(json.dumps(record, indent=2) + "\n")
    write_loss_curve(trainer.state.history, png_path, f"{output.stem}: {trainer.config.loss} loss")
    log.info("wrote %s (%.2f MB), %s, %s", onnx_path, onnx_path.stat().st_size / 1e6, json_path, png_path)
    return {"onnx": onnx_path, "json": json_path, "png": png_path}
