"""The model's own trade-off: one point per configuration (finest resolution, channels, MLP width,
offset on or off, and the same configuration with three training seeds), each trained the same
short way on one data set, then measured in one run: queries per second in-process, validation
error on low-noise reference queries, and image error in one view against the real geometry.

The configurations are trained with the `quick` preset's schedule halved (``tradeoff_steps``
steps of ``tradeoff_batch`` queries, blur half-life scaled the same way) on a data set of
``tradeoff_queries`` 4-spp queries sampled for the finest 256^2 level, so they compare with one
another, not with the shipped models (trained 8x longer). Validation uses ``tradeoff_reference_queries``
new queries at 64 spp (seed 1). Training, data and models are cached: a re-run only measures.
"""

from __future__ import annotations

import json
import logging
import time
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.training.model.maps import MapConfig

from neumip.report.config import ReportConfig

log = logging.getLogger(__name__)

QPS_ROWS = 1 << 17
"""Random queries per throughput measurement."""
QPS_ROUNDS = 9
"""Interleaved rounds of the throughput measurement (median)."""


@dataclass(frozen=True)
class Variant:
    """One trained configuration."""

    name: str
    resolution: int = 64
    channels: int = 7
    hidden: int = 25
    offset: bool = True
    seed: int = 0
    maps: MapConfig | None = None
    """The map encoder of a map-informed variant (None: the paper's model)."""
    classical: bool = False
    """The classical base (`MaterialConfig.base` at the maps' resolution) under the decoder."""
    relief: int = 0
    """Steps of the relief stage (`MaterialConfig.relief` at the height map's resolution), 0: none."""


MAP_VARIANTS = {"maps": MapConfig(), "maps_hz": MapConfig(horizons=8)}
"""The map-informed stages: the map encoder, and the same with horizons towards 8 azimuths."""


def variants(config: ReportConfig, maps: bool = True) -> list[Variant]:
    """Every configuration of the trade-off; the map-informed ones only where the material has maps."""
    base = Variant("base")
    out = [base]
    out += [replace(base, name=f"res{r}", resolution=r) for r in config.tradeoff_resolutions if r != base.resolution]
    out += [replace(base, name="ch4", channels=4), replace(base, name="ch12", channels=12)]
    out += [replace(base, name="mlp16", hidden=16), replace(base, name="mlp48", hidden=48)]
    out += [replace(base, name="no_offset", offset=False)]
    if maps:  # (a height map: the relief marches it)
        out += [replace(base, name=f"relief{k}", relief=k) for k in (4, 8, 16)]
        out += [replace(base, name="relief8_no_offset", relief=8, offset=False)]
        out += [replace(base, name=name, maps=m) for name, m in MAP_VARIANTS.items()]
        out += [replace(base, name="classical", classical=True),
                replace(base, name="maps_hz_classical", maps=MAP_VARIANTS["maps_hz"], classical=True)]
    out += [replace(base, name=f"seed{s}", seed=s) for s in (1, 2)]
    return out


def datasets(desc, folder: Path, config: ReportConfig, on_chunk=None) -> tuple[Path, Path]:
    """Training data (4 spp) and low-noise validation queries (64 spp) of the material described by
    ``desc`` (a `MaterialDescription`; resumable)."""
    from neumip.groundtruth.dataset import DatasetError, open_dataset
    from neumip.groundtruth.generate import GenerateSettings, generate

    material = desc.name
    resolution = max(config.tradeoff_resolutions)
    train = folder / f"{material}_train"
    ref = folder / f"{material}_reference"
    for path, settings in (
        (train, GenerateSettings(queries=config.tradeoff_queries, spp=4, seed=0, resolution=resolution, chunk=1 << 15)),
        (ref, GenerateSettings(queries=config.tradeoff_reference_queries, spp=64, seed=1, resolution=resolution,
                               chunk=1 << 12)),
    ):
        try:
            data = open_dataset(path)  # complete already: reuse it
        except DatasetError:
            generate(desc, path, settings, on_chunk)  # new, or resumes an interrupted one
            continue
        if data.meta.get("generator") != settings.to_meta(desc):
            raise DatasetError(f"{path} was generated with other settings: remove it to generate it again")
    return train, ref


def train_variant(variant: Variant, data: Path, folder: Path, config: ReportConfig, geo=None) -> tuple[Path, dict]:
    """Train (or resume, or reuse) one configuration (a map-informed one reads the maps of ``geo``, a
    `Microgeometry`); returns its .onnx and what its training cost (:func:`training_cost`)."""
    import torch

    from neumip.core.config import MaterialConfig
    from neumip.training.loop.outputs import write_outputs
    from neumip.training.loop.train import Trainer
    from neumip.training.loop.config import QUICK

    onnx = folder / f"{variant.name}.onnx"
    if onnx.exists():
        return onnx, training_cost(folder, variant.name)
    if (variant.maps is not None or variant.classical or variant.relief) and geo is None:
        raise ValueError(f"variant {variant.name} reads the material's maps: pass them")
    scale = config.tradeoff_steps / QUICK.steps
    train = replace(QUICK, steps=config.tradeoff_steps, batch=config.tradeoff_batch, seed=variant.seed,
                    blur_half_life=QUICK.blur_half_life * scale, checkpoint_every=config.tradeoff_steps,
                    log_every=max(1, config.tradeoff_steps // 20), device="cpu")
    from neumip.training.model.base import base_resolution
    from neumip.training.model.relief import relief_resolution

    material = MaterialConfig(resolution=variant.resolution, channels=variant.channels, hidden=variant.hidden,
                              offset=variant.offset, base=base_resolution(geo) if variant.classical else 0,
                              relief=relief_resolution(geo) if variant.relief else 0,
                              relief_steps=variant.relief or MaterialConfig.relief_steps)
    torch.set_num_threads(1)  # one torch thread: faster than two on the shared, busy machine
    start = time.perf_counter()
    maps = None if variant.maps is None and not variant.classical and not variant.relief else (variant.maps, geo)
    trainer = Trainer(data, folder / f"{variant.name}.pt", material, train, f"trade-off {variant.name}", maps=maps)
    setup = time.perf_counter() - start  # opening the data; a map-informed variant also prefilters its maps
    table = trainer.run()
    cost = {"training_seconds": setup + trainer.state.seconds, "setup_seconds": setup,
            "training_load": os.getloadavg()[0]}
    log.info("trained %s in %.0f s (load %.1f)", variant.name, cost["training_seconds"], cost["training_load"])
    write_outputs(trainer, table, onnx)
    (folder / f"{variant.name}.cost.json").write_text(json.dumps(cost))
    return onnx, cost


def training_cost(folder: Path, name: str) -> dict:
    """``{"training_seconds", "setup_seconds", "training_load"}`` recorded when configuration ``name``
    was trained: the wall time of setting it up (opening the data, prefiltering a map-informed one's
    maps) and of every (resumed) part of its training, the set-up alone, and the 1-minute load average
    at its end (None where not recorded)."""
    path = folder / f"{name}.cost.json"
    if not path.exists():
        return {"training_seconds": None, "setup_seconds": None, "training_load": None}
    return json.loads(path.read_text())


def validation_mse(evaluator, name: str, reference: Path) -> float:
    """MSE (linear RGB) of material ``name`` against the low-noise reference queries."""
    from neumip.groundtruth.dataset import open_dataset

    data = open_dataset(reference)
    pred = evaluator.evaluate(name, np.ascontiguousarray(data.queries[:], np.float32))
    diff = pred.astype(np.float64) - data.rgb[:]
    return float(np.mean(diff * diff))


def queries_per_second(evaluator, names: list[str], rounds: int = QPS_ROUNDS) -> dict[str, float]:
    """In-process throughput of each material on the same random queries, interleaved rounds, median."""
    queries = C.random_queries(QPS_ROWS, seed=0)
    times: dict[str, list[float]] = {name: [] for name in names}
    for name in names:  # warm-up
        evaluator.evaluate(name, queries[:4096])
    for _ in range(rounds):
        for name in names:
            start = time.perf_counter()
            evaluator.evaluate(name, queries)
            times[name].append(time.perf_counter() - start)
    return {name: QPS_ROWS / float(np.median(ts)) for name, ts in times.items()}


def describe(variant: Variant) -> dict:
    return {k: v for k, v in asdict(variant).items() if k != "name"}


def summary(points: dict) -> dict:
    """Spread over the training seeds (base, seed1, seed2) of validation and image error."""
    seeds = [points[n] for n in ("base", "seed1", "seed2") if n in points]
    out = {}
    for key in ("validation_mse", "image_mse"):
        values = np.array([p[key] for p in seeds if p.get(key) is not None])
        if len(values):
            out[key] = {"values": values.tolist(), "mean": float(values.mean()), "std": float(values.std(ddof=1)) if len(values) > 1 else 0.0,
                        "spread": float((values.max() - values.min()) / values.mean())}
    return out


def save(points: dict, path: Path) -> None:
    path.write_text(json.dumps(points, indent=2))
