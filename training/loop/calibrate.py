"""`neumip calibrate`: a model file's energy table (`MaterialConfig.energy_bins`) fitted on the training split of the
data it was trained on (split as `neumip train` split it), and its validation table recomputed on the held-out
split; no retraining. The fit itself is `loop/energy.py`'s, the one a training run ends with."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import onnx

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.engines.local import load_material, run_chunked
from neumip.groundtruth.dataset import open_dataset
from neumip.training.export.graph import build_onnx, save_onnx
from neumip.training.export.read import read_model
from neumip.training.loop.config import RECIPES, TrainConfig
from neumip.training.loop.energy import fit_rows, fit_table
from neumip.training.loop.train import split_indices
from neumip.training.loop.validation import validation_table
from neumip.training.model.energy import ones_table

RUN_FIELDS = ("train_seconds", "steps", "dropped_steps", "batch")
"""The fields of a validation table that describe the training run (`Trainer.run`), which a calibration keeps."""
ENERGY_BINS = RECIPES["maps"].material["energy_bins"]
"""The table's bins for a model without one (the `maps` recipe's)."""
ENERGY_AZIMUTHS = RECIPES["maps"].material["energy_azimuths"]
"""The table's azimuth bins for a model without one (the `maps` recipe's)."""


def calibrate_file(model_path: str | Path, data_path: str | Path, out: str | Path, bins: int | None = None,
                   seed: int = 0, azimuths: int | None = None, luminance: bool | None = None) -> dict:
    """Write the model at `model_path` with its energy table fitted on the training split of the data set at
    `data_path` (`train.split_indices` with training seed `seed`, as `neumip train` split it) and its validation
    table recomputed on the held-out split. `bins`: the table's bins (default: the model's own, else `ENERGY_BINS`);
    `azimuths`: its azimuth bins (`MaterialConfig.energy_azimuths`, 0: none; default: the model's own where it has a
    table, else `ENERGY_AZIMUTHS`); `luminance`: one gain a cell for the three channels
    (`MaterialConfig.energy_luminance`; default: the model's own). Returns
    the new validation table. ValueError for a trimmed model (its fine levels are gone) or one whose config cannot
    take a table."""
    config, weights, meta, finest = read_model(onnx.load(str(model_path)), str(model_path))
    if finest:
        raise ValueError(f"{model_path} is trimmed (finest level {finest}): calibrate the whole model, then trim it")
    if azimuths is None:
        azimuths = config.energy_azimuths if config.energy_bins else ENERGY_AZIMUTHS
    config = replace(config, energy_bins=bins or config.energy_bins or ENERGY_BINS, energy_azimuths=azimuths,
                     energy_luminance=config.energy_luminance if luminance is None else luminance)
    data = open_dataset(data_path)
    train_idx, held_idx = split_indices(len(data), TrainConfig(seed=seed))
    rows = fit_rows(train_idx, seed)
    owned = {C.META_CONTRACT, C.META_CONFIG, C.META_DESCRIPTION}
    rest = {k: v for k, v in meta.items() if k not in owned}
    description = meta.get(C.META_DESCRIPTION, "")

    def model(table: np.ndarray) -> onnx.ModelProto:
        return build_onnx(config, {**weights, W.ENERGY: table}, description, rest)

    def answers(graph: onnx.ModelProto, queries: np.ndarray) -> np.ndarray:  # in memory, no file; in chunks (one
        material = load_material(model_path, data=graph.SerializeToString())  # call of 4 M rows held 6 GB)
        return run_chunked(material.run, np.asarray(queries, np.float32))

    queries = np.asarray(data.queries[rows])
    table = fit_table(config, queries, answers(model(ones_table(config)), queries), np.asarray(data.rgb[rows]))
    held = np.asarray(data.queries[held_idx])
    calibrated = model(table)
    validation = validation_table(answers(calibrated, held), np.asarray(data.rgb[held_idx]), held[:, C.SIGMA],
                                  config.resolution)
    before = json.loads(meta.get(C.META_VALIDATION) or "{}")
    validation.update({k: before[k] for k in RUN_FIELDS if k in before})  # the run that trained the weights
    props = {p.key: p.value for p in calibrated.metadata_props}
    onnx.helper.set_model_props(calibrated, {**props, C.META_VALIDATION: json.dumps(validation)})
    save_onnx(calibrated, out)
    return validation
