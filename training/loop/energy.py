"""Fitting a model's energy table (`MaterialConfig.energy_bins`, `training.model.energy`) on its data: at the end of a
training run (`Trainer.run`, on its training split) or for a model file already made (`calibrate.calibrate_file`,
`neumip calibrate`).

The answers the table is fitted to are the model's without a table (every gain 1), so a fit gives the same table
however often it is repeated; the queries are a seeded sample of the training split (`ENERGY_QUERIES` at most).
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from neumip.core import weights as W
from neumip.training.model.energy import fit_energy

log = logging.getLogger(__name__)

ENERGY_QUERIES = 1 << 22
"""Queries of the training split a fit reads at most (a cell of a coarse level and a bin still holds thousands)."""


def fit_rows(train_idx: np.ndarray, seed: int, count: int = ENERGY_QUERIES) -> np.ndarray:
    """The rows of the training split a fit reads: all of them, or a sorted sample of `count` seeded by `seed`."""
    if len(train_idx) <= count:
        return train_idx
    return np.sort(np.random.default_rng([seed, 0xE7]).choice(train_idx, count, replace=False))


def fit_table(config, queries: np.ndarray, answers: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """numpy in and out of `model.energy.fit_energy`: the table ((L + 1) B^2, 3), and a log line of its range."""
    table = fit_energy(config, torch.from_numpy(np.asarray(queries, np.float32)), torch.from_numpy(answers),
                       torch.from_numpy(np.asarray(targets, np.float32))).numpy()
    log.info("energy table fitted on %d queries: gains %.3f-%.3f", len(queries), table.min(), table.max())
    return table


def fit_material(material, data, train_idx: np.ndarray, seed: int) -> np.ndarray:
    """Fit a torch material's table on its training split and store it in the material (`W.ENERGY`); returns it."""
    from neumip.training.loop.validation import predict

    rows = fit_rows(train_idx, seed)
    queries, targets = np.asarray(data.queries[rows]), np.asarray(data.rgb[rows])
    buffer = getattr(material, W.ENERGY)
    with torch.no_grad():
        buffer.fill_(1.0)
    training = material.training
    material.eval()
    answers = predict(material, queries)
    material.train(training)
    table = fit_table(material.config, queries, answers, targets)
    with torch.no_grad():
        buffer.copy_(torch.from_numpy(table))
    return table
