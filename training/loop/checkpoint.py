"""Checkpoint files: model config, weights and training state, written atomically.

A checkpoint is a `torch.save` dict ``{"format", "config", "state", "extra"}``, plus ``"maps"`` (the
`MapConfig` JSON) for a map-informed material. It is written to a
temporary file and renamed into place, so an interrupted write never leaves a truncated checkpoint.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from neumip.core.errors import NeumipError
from neumip.core.files import atomic_write

from neumip.core.config import MaterialConfig
from neumip.training.model.maps import MapConfig
from neumip.training.model.material import MapMaterial, NeuMIPMaterial

FORMAT = "neumip-checkpoint-1"


class CheckpointError(NeumipError, RuntimeError):
    """A checkpoint file that cannot be read as a NeuMIP checkpoint."""


def save(path: str | Path, material: NeuMIPMaterial, extra: dict[str, Any] | None = None) -> Path:
    """Write `material` (and optional training state in `extra`) to `path` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "config": material.config.to_json(),
        "state": {k: v.detach().cpu() for k, v in material.state_dict().items()},
        "extra": extra or {},
    }
    if isinstance(material, MapMaterial):
        payload["maps"] = material.maps.to_json()
    return atomic_write(path, lambda tmp: torch.save(payload, tmp))


def load(path: str | Path) -> tuple[NeuMIPMaterial, dict[str, Any]]:
    """Read a checkpoint -> (material on CPU, extra). Raises CheckpointError if it is not one."""
    path = Path(path)
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as exc:  # torch raises several types for corrupt files
        raise CheckpointError(f"{path} is not a readable checkpoint: {exc}") from exc
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a NeuMIP checkpoint (format {FORMAT} expected)")
    config = MaterialConfig.from_json(payload["config"])
    maps = payload.get("maps")
    material = NeuMIPMaterial(config) if maps is None else MapMaterial(config, MapConfig.from_json(maps))
    material.load_state_dict(payload["state"])
    return material, payload["extra"]
