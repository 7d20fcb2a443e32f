"""Where a trained model's files go: ``models/NAME.onnx`` and the files beside it.

    models/NAME.onnx             the model
    models/NAME.json             its record (config, validation): moved into place last, so it marks the model whole
    models/NAME.loss.png         the loss curve
    models/NAME.progress.png     the progress grid
    models/.NAME.partial/        the files being written, before they are moved into place
    models/NAME.run/             the run: checkpoint, ground truth of the progress grid (or --work)

Paths only: nothing here imports torch, so the commands can check their output before they import it.
"""

from __future__ import annotations

from pathlib import Path


def sidecar_paths(output: str | Path) -> tuple[Path, Path]:
    """models/NAME.onnx -> (models/NAME.json, models/NAME.loss.png)."""
    output = Path(output)
    return output.with_suffix(".json"), output.with_name(output.stem + ".loss.png")


def progress_path(output: str | Path) -> Path:
    """models/NAME.onnx -> models/NAME.progress.png."""
    output = Path(output)
    return output.with_name(output.stem + ".progress.png")


def work_folder(output: str | Path, work: str | Path | None = None) -> Path:
    """models/NAME.onnx -> models/NAME.run (or `work` when given)."""
    output = Path(output)
    return Path(work) if work is not None else output.with_name(output.stem + ".run")


def staging_folder(output: str | Path) -> Path:
    """models/NAME.onnx -> models/.NAME.partial: where a model's files are written before they are moved into place
    (`outputs.install_outputs`); it outlives an install cut short."""
    output = Path(output)
    return output.with_name(f".{output.stem}.partial")


def fitted(output: str | Path) -> bool:
    """Whether the model at `output` and its record (NAME.json, moved in last) are both in place."""
    output = Path(output)
    return output.exists() and output.with_suffix(".json").exists()


def cut_short(output: str | Path) -> bool:
    """Whether the model at `output` is one whose install was interrupted after it was moved into place: its record
    (``NAME.json``, moved last) still waits in the staging folder, the model no longer does. The same command may
    finish it. Any other file at `output` is someone's model."""
    output = Path(output)
    staging = staging_folder(output)
    return (output.exists() and not fitted(output) and (staging / output.with_suffix(".json").name).is_file()
            and not (staging / output.name).exists())


def occupied(output: str | Path) -> bool:
    """Whether a file at `output` may be replaced only with ``--force``: any but a model whose install was cut
    short (`cut_short`), which the same command finishes."""
    return Path(output).exists() and not cut_short(output)
