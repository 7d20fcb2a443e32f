"""Regression guard: every shipped model's error on fresh ground-truth queries stays at or below the
validation error its NAME.json records, plus a margin.

The queries are drawn and path-traced on the fly exactly as the data the json describes (its
material description, sampling, tracer and tiling settings, its spp), with a seed the training data
did not use, so the expected MSE is the recorded held-out MSE. The set is small but fixed (seed), so
the check is deterministic; the margin of 50 % covers its sampling error (the shipped models land at
0.92-1.08x their recorded value). A retrained model that got clearly worse, or a model file swapped
for another material's, fails (checked: rock or yarn evaluated on another material's queries is at
least 1.7x over that material's limit).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from neumip.engines.local import LocalMaterials
from neumip.groundtruth.description import MaterialDescription, resolve
from neumip.groundtruth.mesh import TilingConfig
from neumip.groundtruth.sampling import QuerySampling, sample_queries
from neumip.groundtruth.tracer import QueryTracer, TracerConfig

MODELS = Path(__file__).resolve().parents[2] / "models"
RECORDS = sorted(MODELS.glob("*.json"))
QUERIES = 3000
SEED = 12345


@pytest.fixture(scope="module")
def materials():
    return LocalMaterials(MODELS, threads=2)


@pytest.fixture(scope="module")
def fresh_queries():
    """(queries, rgb) per material description, traced once for a model and its ablation."""
    cache: dict = {}

    def get(meta: dict) -> tuple[np.ndarray, np.ndarray]:
        key = json.dumps([meta["material"], meta["generator"]], sort_keys=True)
        if key not in cache:
            gen = meta["generator"]
            desc = MaterialDescription.from_dict({k: v for k, v in meta["material"].items() if k != "map_sha256"})
            tracer_cfg = TracerConfig(**{k: v for k, v in gen["tracer"].items() if k != "variant"})
            tracer = QueryTracer(resolve(desc), tracer_cfg, TilingConfig(**gen["tiling"]))
            queries = sample_queries(QUERIES, np.random.default_rng(SEED), gen["resolution"],
                                     QuerySampling(**gen["sampling"]))
            cache[key] = queries, tracer.estimate(queries, gen["spp"], SEED)
        return cache[key]

    return get


@pytest.mark.parametrize("record", RECORDS, ids=[p.stem for p in RECORDS])
def test_model_error_within_its_recorded_validation(record, materials, fresh_queries):
    meta = json.loads(record.read_text())
    queries, target = fresh_queries(meta["data_meta"])
    pred = materials.evaluate(record.stem, queries)
    sq = np.mean((pred.astype(np.float64) - target) ** 2, axis=1)
    mse = sq.mean()
    recorded = meta["validation"]["overall"]["mse"]
    assert mse <= 1.5 * recorded + 1e-6, (
        f"{record.stem}: MSE {mse * 1e3:.3f}e-3 on fresh queries, recorded {recorded * 1e3:.3f}e-3"
    )
