"""Fit a NeuMIP material to MBTF queries: Adam on random batches with progressive texture blur.

One run reads a data set folder (`dataset.open_dataset`, memory-mapped), holds out a seeded random
split for validation, and trains with the schedule of a `TrainConfig`. Checkpoints carry the
optimiser state, step, loss history and the sampler's RNG state, so an interrupted run resumed
from its checkpoint continues exactly as if it had not stopped. A non-finite loss or weight stops
the run with `TrainingDiverged`; checkpoints are only ever written from finite weights.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import threading
import time
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.errors import NeumipError, differences

from neumip.training.loop import checkpoint
from neumip.training.loop.blur import bake, blur_sigma, blur_texture, effective_textures, schedule_end
from neumip.core.config import MaterialConfig
from neumip.groundtruth.dataset import Dataset, open_dataset
from neumip.core.head import answer_bias
from neumip.training.loop.losses import training_loss
from neumip.training.model.base import base_maps
from neumip.training.model.maps import MapConfig, prefilter
from neumip.training.model.material import MapMaterial, NeuMIPMaterial
from neumip.training.model.relief import landed_positions, relief_heights
from neumip.training.loop.distil import coarse_mask, distilled_targets, mix_targets
from neumip.training.loop.energy import fit_material
from neumip.groundtruth.description import Microgeometry
from neumip.groundtruth.lobe import sampling_lobe
from neumip.training.loop.config import TrainConfig
from neumip.training.loop.validation import predict, validation_table

log = logging.getLogger(__name__)

MAY_CHANGE_ON_RESUME = {"steps", "device", "compile", "preload_mb", "checkpoint_every", "validate_every"}
"""TrainConfig fields a resumed run may set differently (they do not change what is learned)."""

Callback = Callable[[int, float], None]
"""Called after every optimiser step with (steps done, loss of that step)."""

ProgressCallback = Callable[["Trainer"], None]
"""Called after every progress validation with the trainer (its state.progress has the new record)."""


class TrainingDiverged(NeumipError, RuntimeError):
    """The loss or the weights became NaN/Inf; the last good checkpoint is kept."""


class TrainingError(NeumipError, ValueError):
    """A run that cannot start: wrong data, or a checkpoint from a different run."""


@dataclass
class TrainState:
    """Everything of a run that a checkpoint must carry besides the weights."""

    step: int = 0
    """Optimiser steps done."""
    history: list = field(default_factory=list)
    """[step, mean loss of the steps since the previous record] every `log_every` steps."""
    seconds: float = 0.0
    """Wall time spent training so far, over all resumed parts."""
    offset_frozen: bool = False
    """The offset texture has been baked with its blur floor and no longer trains."""
    baked: bool = False
    """The run ended inside the blur schedule and its blurred textures were stored as the weights."""
    progress: list = field(default_factory=list)
    """[step, [[level, MSE], ...], overall MSE] of each progress validation (`Trainer.check_progress`)."""
    candidates: list = field(default_factory=list)
    """[seed, held-out MSE] of each candidate instance compared (`TrainConfig.candidates`)."""
    dropped_steps: int = 0
    """Steps trained by the candidates that were dropped."""
    averaged: int = 0
    """Steps whose weights are in the running mean (`TrainConfig.average_fraction`)."""
    average_applied: bool = False
    """The run ended and its weights were replaced by their running mean."""
    energy_fitted: bool = False
    """The run ended and its energy table was fitted (`MaterialConfig.energy_bins`, `loop.energy`)."""


def claim_checkpoint(path: Path):
    """Lock ``CHECKPOINT.lock`` for this process (a POSIX record lock, released when the process ends, however
    it ends) -> the open lock file, to keep while training. A second process training into the same checkpoint
    would resume it too, and the two would overwrite each other's checkpoints and outputs: it is refused."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        return None
    path.parent.mkdir(parents=True, exist_ok=True)
    lock = open(path.with_name(path.name + ".lock"), "a+")
    try:
        fcntl.lockf(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        lock.close()
        raise TrainingError(f"another process is training into {path}: wait for it to end, or pass another "
                            "--checkpoint (--work for `neumip fit`)") from None
    return lock


def data_ceiling(data: Dataset) -> float:
    """The data's largest target (`MaterialConfig.ceiling`), read in chunks of the memory-mapped file."""
    rgb = data.rgb
    return float(max(np.max(rgb[lo:lo + (1 << 20)]) for lo in range(0, len(rgb), 1 << 20)))


def data_lobe(data: Dataset) -> C.SamplingLobe | None:
    """The sampling lobe of a data set's material, rebuilt from its meta.json (None where it cannot be)."""
    from neumip.groundtruth.description import DescriptionError, resolve
    from neumip.training.loop.views import data_material

    try:
        geo = resolve(data_material(data.meta.get("material") or {}, None, data.meta.get("description_dir")))
    except (DescriptionError, OSError, ValueError) as exc:
        log.info("%s: no sampling lobe (its material cannot be rebuilt: %s)", data.path, exc)
        return None
    return sampling_lobe(geo)


def resolve_device(name: str) -> torch.device:
    """'auto' -> CUDA when available, else CPU; 'cuda' without a GPU is an error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise TrainingError("device 'cuda' requested but torch sees no CUDA device")
    return torch.device(name)


def split_indices(n: int, config: TrainConfig) -> tuple[np.ndarray, np.ndarray]:
    """(train, held-out) row indices of an n-row data set, seeded by config.seed; both sorted."""
    held = min(max(1, int(n * config.holdout)), config.max_holdout)
    if n - held < 1:
        raise TrainingError(f"data set has {n} queries: too few to hold out {held} and train")
    rng = np.random.default_rng(config.seed)
    perm = rng.permutation(n)
    return np.sort(perm[held:]), np.sort(perm[:held])


class BatchSampler:
    """Uniform random batches of the training split, drawn from the (memory-mapped) data."""

    def __init__(self, data: Dataset, train_idx: np.ndarray, batch: int, seed: int, preload_mb: int,
                 landed: np.ndarray | None = None) -> None:
        """`landed`: (N, 2) u, v of every row where the relief stage lands (`relief.landed_positions`); the
        batches then carry them in place of the rows' own u, v."""
        self.batch = batch
        self.queries, self.rgb = data.queries, data.rgb
        if (data.queries.nbytes + data.rgb.nbytes) / 2**20 <= preload_mb:
            self.queries, self.rgb = np.array(data.queries), np.array(data.rgb)
        self.landed = landed
        self.train_idx = torch.from_numpy(train_idx)
        self.generator = torch.Generator().manual_seed(seed)

    def draw(self, device: torch.device, aims: bool = False) -> tuple[torch.Tensor, ...]:
        """-> queries (B, 7), rgb (B, 3) float32 on `device`; rows read in file order (page locality). With
        `aims`, also the rows as the data holds them (B, 7): their u, v where the relief has not moved them."""
        pick = torch.randint(len(self.train_idx), (self.batch,), generator=self.generator)
        rows = np.sort(self.train_idx[pick].numpy())
        own = torch.from_numpy(self.queries[rows])
        q = own
        if self.landed is not None:
            q = own.clone()
            q[:, C.U:C.V + 1] = torch.from_numpy(self.landed[rows])
        rgb = torch.from_numpy(self.rgb[rows])
        out = (q.to(device, non_blocking=True), rgb.to(device, non_blocking=True))
        return out + (own.to(device, non_blocking=True),) if aims else out


@torch.no_grad()
def init_output(material: NeuMIPMaterial, rgb_sample: np.ndarray) -> None:
    """Start the decoder's output at the data's mean colour ((n, 3) sample), with small slopes.

    The decoder ends in a ReLU: a channel whose output starts negative for every query gets no
    gradient and never recovers (seen on a flat plane with default init).
    """
    last = material.decoder[-1]
    mean = np.maximum(np.asarray(rgb_sample, np.float64).mean(axis=0), 1e-3)
    last.bias.copy_(torch.as_tensor(answer_bias(material.config.head, mean), dtype=last.bias.dtype))
    last.weight.mul_(0.1)


def _make_optimizer(material: NeuMIPMaterial, config: TrainConfig) -> torch.optim.Adam:
    return torch.optim.Adam(material.parameters(), lr=config.lr, foreach=True)


def learning_rate(step: int, config: TrainConfig) -> float:
    """Learning rate of the step after `step` steps done (TrainConfig.lr_schedule)."""
    scale = config.finish_lr_scale if config.finishing(step) else 1.0
    if config.lr_schedule == "constant":
        return config.lr * scale
    t = min(step / config.steps, 1.0)
    return scale * config.lr * (config.lr_final + (1.0 - config.lr_final) * 0.5 * (1.0 + math.cos(math.pi * t)))


def _maps_dict(source: NeuMIPMaterial | MapConfig | None) -> dict:
    """The map encoder's settings of a material or a MapConfig ({} for the paper's model)."""
    maps = source.maps if isinstance(source, MapMaterial) else source
    return asdict(maps) if isinstance(maps, MapConfig) else {}


def _finite(material: NeuMIPMaterial) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in material.parameters())


class StepBoundary:
    """Ctrl-C (SIGINT) while training ends the run after the step under way, not inside it: a checkpoint written
    inside a step would hold its batch drawn but its update not made, which a resumed run replays differently.
    A second Ctrl-C stops at once (the last checkpoint then stands). Only in the main thread, and only where SIGINT
    has Python's default handler; elsewhere a KeyboardInterrupt arrives as it comes."""

    def __init__(self) -> None:
        self.pending = False
        self._previous = None

    def __enter__(self) -> "StepBoundary":
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self._previous = signal.signal(signal.SIGINT, self._interrupted)
        return self

    def _interrupted(self, signum, frame) -> None:
        if self.pending:
            raise KeyboardInterrupt
        self.pending = True
        # straight to the descriptor: the handler may run inside a write to sys.stderr (a progress bar's), and
        # writing there again would raise
        os.write(2, b"\ninterrupted: stopping after this step (Ctrl-C again to stop at once)\n")

    def check(self) -> None:
        """Between steps: KeyboardInterrupt if a Ctrl-C came."""
        if self.pending:
            raise KeyboardInterrupt

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


class Trainer:
    """One training run of one material; `run()` trains to `config.steps` and validates."""

    def __init__(
        self,
        data_path: str | Path,
        checkpoint_path: str | Path,
        material_config: MaterialConfig,
        config: TrainConfig,
        description: str = "",
        maps: tuple[MapConfig | None, Microgeometry] | None = None,
    ) -> None:
        """`maps`: the material's maps. With a MapConfig, train a map-informed material (`MapMaterial`)
        whose encoder reads them, prefiltered to the pyramid's levels (None: the paper's model); with
        `MaterialConfig.base` they make the base (`base.base_maps`), with `MaterialConfig.relief` the relief's
        heights (`relief.relief_heights`)."""
        self.data = open_dataset(data_path)
        self.map_config = maps[0] if maps is not None else None
        if (material_config.base or material_config.relief) and maps is None:
            raise TrainingError("a material with a base or a relief needs the material's maps (the data's description)")
        self._geometry = maps[1] if maps is not None else None
        self.sampling = sampling_lobe(self._geometry) if self._geometry is not None else data_lobe(self.data)
        """The sampling lobe the export declares (`contract.SamplingLobe`), from the material's maps
        (None where the data's material cannot be rebuilt, e.g. imported queries: the cosine alone)."""
        self.checkpoint_path = Path(checkpoint_path)
        self._claim = claim_checkpoint(self.checkpoint_path)
        self.config, self.description = config, description
        self.device = resolve_device(config.device)
        self.train_idx, self.val_idx = split_indices(len(self.data), config)
        landed = None
        if material_config.relief:  # the heights are fixed: each row is marched once, not at every step
            landed = landed_positions(relief_heights(self._geometry, material_config.relief), material_config,
                                      self.data.queries)
        self.sampler = BatchSampler(self.data, self.train_idx, config.batch, config.seed, config.preload_mb, landed)
        generator = self.data.meta.get("generator")
        reach = (generator.get("sampling") or {}).get("sub_texel_levels", 0) if isinstance(generator, dict) else None
        if reach is not None and reach != material_config.lod_bias:  # (imported or hand-made data: not known)
            log.warning("the model's finest level answers footprints of 2^-%d texel (lod_bias), the data's reach 2^-%d "
                        "(neumip generate --sub-texel-levels %d draws them for it)", material_config.lod_bias, reach,
                        material_config.lod_bias)
        self.state = TrainState()
        self._average: dict[str, torch.Tensor] = {}  # running mean of the weights (a resumed run's: `_resume`)
        if self.checkpoint_path.exists():
            self.material = self._resume(material_config)
        else:
            if not material_config.ceiling:  # (0: the data's; a resumed run keeps its checkpoint's)
                material_config = replace(material_config, ceiling=data_ceiling(self.data))
            features = (None if self.map_config is None
                        else prefilter(maps[1], material_config.level_sizes(), self.map_config.horizons))
            self._new_material = lambda seed: self._initial_material(material_config, features, seed)
            self.material = self._new_material(config.seed)
            self.optimizer = _make_optimizer(self.material, config)
        self._end = schedule_end(config)
        self._window: list[float] = []  # losses since the last history record
        self._loss = torch.compile(self._batch_loss, dynamic=False) if config.compile else self._batch_loss

    def _initial_material(self, material_config: MaterialConfig, features: list | None, seed: int) -> NeuMIPMaterial:
        """A new material with the initial weights of `seed` (map-informed when `features` are given)."""
        torch.manual_seed(seed)
        if features is None:
            material = NeuMIPMaterial(material_config)
        else:
            material = MapMaterial(material_config, self.map_config, features)
        if material_config.base:  # the answer starts as the base's (the decoder's last layer is zero)
            material.set_maps(W.BASE, base_maps(self._geometry, material_config.base, material_config.base_energy))
        else:
            init_output(material, self.data.rgb[self.train_idx[:: max(1, len(self.train_idx) // 4096)]])
        if material_config.relief:
            material.set_maps(W.RELIEF, relief_heights(self._geometry, material_config.relief))
        return material.to(self.device)

    @property
    def steps_done(self) -> int:
        """Optimiser steps taken so far, the dropped candidates' included."""
        return self.state.step + self.state.dropped_steps

    def _batch_loss(
        self, queries: torch.Tensor, target: torch.Tensor, levels: list[torch.Tensor], otex: torch.Tensor | None,
        loss: str,
    ) -> torch.Tensor:
        """(B, 7) queries, (B, 3) target, effective textures, the loss's name -> scalar training loss."""
        answers = self.material(queries, levels, otex, landed=self.sampler.landed is not None, ceiling=False)
        if not self.config.coarse_loss:
            return training_loss(answers, target, self.config, loss)
        cfg = self.material.config
        coarse = coarse_mask(queries, cfg.resolution, cfg.lod_bias, self.config.coarse_level)
        return training_loss(answers, target, self.config, loss, coarse=coarse)

    # --- checkpoints -----------------------------------------------------------------------------

    def _data_identity(self) -> dict:
        """What the checkpoint's data must match: its size, material and footprints' resolution."""
        generator = self.data.meta.get("generator")  # (a dict for `neumip generate`'s data)
        return {"n": len(self.data), "material": str(self.data.meta.get("material", "")),
                "sampling_resolution": generator.get("resolution") if isinstance(generator, dict) else None}

    def _resume(self, material_config: MaterialConfig) -> NeuMIPMaterial:
        material, extra = checkpoint.load(self.checkpoint_path)
        if not material_config.ceiling:  # the data's, as the run began (0 for a run begun before it existed)
            material_config = replace(material_config, ceiling=material.config.ceiling)
        # fields added since the checkpoint was written take their defaults (the behaviour before them)
        saved_config = {**{f.name: f.default for f in fields(TrainConfig)}, **extra.get("train_config", {})}
        mismatches = [
            ("material config", differences(asdict(material.config), asdict(material_config))),
            ("training settings", differences(saved_config, self.config.to_dict(),
                                              ignore=MAY_CHANGE_ON_RESUME)),
            ("data", differences(extra.get("data", {}),  # (fields a checkpoint predates are not compared)
                                 {k: v for k, v in self._data_identity().items() if k in extra.get("data", {})})),
            ("map encoder", differences(_maps_dict(material), _maps_dict(self.map_config))),
        ]
        for what, diff in mismatches:
            if diff:
                raise TrainingError(
                    f"{self.checkpoint_path} was written with another {what}: {'; '.join(diff)}. "
                    "To resume it, run with the checkpoint's values; to start a new run, pass another "
                    "--checkpoint or move this one away"
                )
        material.to(self.device)
        self.state = TrainState(**extra["state"])
        if self.state.offset_frozen:
            material.freeze_offset()
        self.optimizer = _make_optimizer(material, self.config)
        self.optimizer.load_state_dict(extra["optimizer"])
        self.sampler.generator.set_state(extra["rng"])
        self._average = {k: v.to(self.device) for k, v in extra.get("average", {}).items()}
        log.info("resuming %s at step %d of %d", self.checkpoint_path, self.state.step, self.config.steps)
        return material

    def save_checkpoint(self, validation: dict | None = None) -> Path:
        """Write the checkpoint (refuses non-finite weights: the last good one stays)."""
        if not _finite(self.material):
            raise TrainingDiverged(self._diverged_message("weights"))
        extra = {
            "state": vars(self.state),
            "optimizer": self.optimizer.state_dict(),
            "rng": self.sampler.generator.get_state(),
            "train_config": self.config.to_dict(),
            "data": self._data_identity(),
            "description": self.description,
            "sampling": self.sampling._asdict() if self.sampling else None,
        }
        if self._average:
            extra["average"] = self._average
        if validation is not None:
            extra["validation"] = validation
        return checkpoint.save(self.checkpoint_path, self.material, extra)

    def _diverged_message(self, what: str) -> str:
        kept = (
            f"the last good checkpoint ({self.checkpoint_path}) is kept"
            if self.checkpoint_path.exists()
            else "no checkpoint had been written yet"
        )
        return (
            f"training diverged: the {what} became NaN/Inf at step {self.state.step + 1}; {kept}. "
            "Try a lower learning rate (--lr) or check the data for NaN/Inf values."
        )

    # --- training --------------------------------------------------------------------------------

    def _freeze_offset(self) -> None:
        """End of the blur schedule: bake the offset texture's floor blur and stop training it."""
        with torch.no_grad():
            otex = self.material.textures()[1]
            self.material.store_textures(None, blur_texture(otex, self.config.offset_blur_floor))
        self.material.freeze_offset()
        self.state.offset_frozen = True
        log.info("step %d: blur schedule ended, offset texture frozen", self.state.step)

    def step(self) -> float:
        """One optimiser step; returns its loss. Raises TrainingDiverged on a non-finite loss."""
        cfg, state = self.config, self.state
        if cfg.offset_freeze and self.material.config.offset and not state.offset_frozen and state.step >= self._end:
            self._freeze_offset()
        levels, otex = effective_textures(self.material, blur_sigma(state.step, cfg), cfg, state.offset_frozen)
        if cfg.distilling(state.step):
            queries, target, aims = self.sampler.draw(self.device, aims=True)
            target = self._distilled(queries, target, aims, levels, otex)
        else:
            queries, target = self.sampler.draw(self.device)
        name = cfg.loss_at(state.step)
        try:
            loss = self._loss(queries, target, levels, otex, name)
        except Exception as exc:  # torch.compile needs a working C++ toolchain; eager always works
            if self._loss == self._batch_loss:
                raise
            log.warning("torch.compile failed (%s): training continues uncompiled", exc)
            self._loss = self._batch_loss
            loss = self._loss(queries, target, levels, otex, name)
        value = float(loss.detach())
        if not np.isfinite(value):
            raise TrainingDiverged(self._diverged_message("loss"))
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        for group in self.optimizer.param_groups:
            group["lr"] = learning_rate(state.step, cfg)
        self.optimizer.step()
        state.step += 1
        if cfg.average_fraction and state.step > max(cfg.steps - round(cfg.steps * cfg.average_fraction), self._end):
            self._accumulate_average()
        self._window.append(value)
        if state.step % cfg.log_every == 0 or state.step == cfg.steps:
            state.history.append([state.step, float(np.mean(self._window))])
            self._window = []
        return value

    def _distilled(self, queries: torch.Tensor, target: torch.Tensor, aims: torch.Tensor, levels: list[torch.Tensor],
                   otex: torch.Tensor | None) -> torch.Tensor:
        """The batch's targets with its coarse queries' distilled from the model's finer answers (`distil`);
        `aims`: the batch's rows as the data holds them (the relief marches the distilled answers' own)."""
        cfg = self.material.config
        coarse = coarse_mask(queries, cfg.resolution, cfg.lod_bias, self.config.distil_level)
        if not bool(coarse.any()):
            return target

        def answer(q: torch.Tensor) -> torch.Tensor:  # (at most the data's largest target, as a target is)
            return self.material(q, levels, otex)

        distilled = distilled_targets(answer, aims[coarse], self.config.distil, self.sampler.generator,
                                      self.config.distil_texels / cfg.resolution)
        return mix_targets(target, distilled, coarse, self.config.distil_weight)

    def _accumulate_average(self) -> None:
        """Add the weights after this step to the running mean of the trained parameters (`average_fraction`)."""
        self.state.averaged += 1
        with torch.no_grad():
            for name, p in self.material.named_parameters():
                if not p.requires_grad:  # (a frozen offset texture keeps its value)
                    continue
                mean = self._average.setdefault(name, p.detach().clone())
                mean.add_((p.detach() - mean) / self.state.averaged)

    def _apply_average(self) -> None:
        """The run's end: its trained parameters become their running mean."""
        with torch.no_grad():
            for name, p in self.material.named_parameters():
                if name in self._average:
                    p.copy_(self._average[name])
        self.state.average_applied = True
        log.info("weights: the mean of the last %d steps'", self.state.averaged)

    def current_textures(self) -> tuple[list[torch.Tensor], torch.Tensor | None]:
        """The textures the material is evaluated with at the current step (blurred during the schedule)."""
        with torch.no_grad():
            return effective_textures(self.material, blur_sigma(self.state.step, self.config), self.config,
                                      self.state.offset_frozen)

    def check_progress(self) -> list:
        """Per-level MSE on the held-out split (at most `max_holdout` queries) with the current step's
        blur; appended to state.progress (and so kept in checkpoints) and returned. The whole split,
        not a sample: a few bright outliers carry much of the MSE (a half sample of 52 000 stones
        queries read 2.5e-3 where the whole split reads 3.7e-3)."""
        queries = np.asarray(self.data.queries[self.val_idx])
        target = np.asarray(self.data.rgb[self.val_idx])
        self.material.eval()
        pred = predict(self.material, queries, *self.current_textures())
        self.material.train()
        table = validation_table(pred, target, queries[:, C.SIGMA], self.material.config.resolution)
        record = [self.state.step, [[r["level"], r["mse"]] for r in table["levels"]], table["overall"]["mse"]]
        self.state.progress.append(record)
        return record

    def pick_candidate(self, callback: Callback | None = None) -> None:
        """Train `config.candidates` instances `candidate_steps` steps each, on the same batches, and
        go on with the one of the lowest held-out MSE (at the step's blur); no checkpoint is written
        before the choice, so an interrupted run starts the comparison again."""
        cfg, start = self.config, time.perf_counter()
        batches = self.sampler.generator.get_state()
        best = None
        for i in range(cfg.candidates):
            if i > 0:
                self.material = self._new_material(cfg.seed + i)
                self.optimizer = _make_optimizer(self.material, cfg)
                self.state = TrainState(candidates=self.state.candidates, dropped_steps=self.steps_done)
                self._window = []
                self.sampler.generator.set_state(batches)
            self.material.train()
            try:
                while self.state.step < cfg.candidate_steps:
                    loss = self.step()
                    if callback is not None:
                        callback(self.steps_done, loss)
            except TrainingDiverged:  # a bad start is what the comparison is for
                self.state.candidates.append([cfg.seed + i, math.inf])
                log.warning("candidate %d of %d (seed %d) diverged", i + 1, cfg.candidates, cfg.seed + i)
                continue
            except KeyboardInterrupt:  # back to the first start: a re-run compares them all again
                self.material, self.state = self._new_material(cfg.seed), TrainState()
                self.optimizer = _make_optimizer(self.material, cfg)
                self.sampler.generator.set_state(batches)
                raise
            mse = self.check_progress()[2]
            self.state.candidates.append([cfg.seed + i, mse])
            log.info("candidate %d of %d (seed %d): held-out MSE %.4g after %d steps",
                     i + 1, cfg.candidates, cfg.seed + i, mse, cfg.candidate_steps)
            if best is None or mse < best[0]:
                best = (mse, self.material, self.optimizer, self.sampler.generator.get_state(), self._window, self.state)
        if best is None:
            raise TrainingDiverged(f"all {cfg.candidates} candidate starts diverged; try a lower learning rate (--lr)")
        records, done = self.state.candidates, self.steps_done
        _, self.material, self.optimizer, rng, self._window, self.state = best
        self.sampler.generator.set_state(rng)
        self.state.candidates, self.state.dropped_steps = records, done - self.state.step
        self.state.seconds = time.perf_counter() - start
        kept = min(records, key=lambda r: r[1])
        log.info("kept candidate seed %d (held-out MSE %.4g)", kept[0], kept[1])
        self.save_checkpoint()

    def run(self, callback: Callback | None = None, on_progress: ProgressCallback | None = None) -> dict:
        """Train up to config.steps (from wherever the checkpoint left off), then validate.

        A new run with `config.candidates` > 1 first picks its best candidate (`pick_candidate`).
        Every `config.validate_every` steps a progress validation is recorded and `on_progress` called.
        `callback(steps_done, loss)` counts the dropped candidates' steps too (of `config.total_steps`).
        Returns the validation table (also stored in the final checkpoint's extra["validation"]).
        """
        if self.state.step == 0 and self.config.candidates > 1:
            self.pick_candidate(callback)
        cfg, state = self.config, self.state
        self.material.train()
        log.info(
            "training %s: %d queries (%d held out), %d steps of %d on %s",
            self.data.path, len(self.data), len(self.val_idx), cfg.steps, cfg.batch, self.device,
        )
        started = time.perf_counter()
        done_before = state.seconds
        if state.baked and state.step < cfg.steps:
            log.warning("continuing a run whose final blurred textures were baked: they are blurred again")
            state.baked = False
        if state.average_applied and state.step < cfg.steps:
            log.warning("continuing a run from its averaged weights: the average starts again")
            state.average_applied, state.averaged, self._average = False, 0, {}
        if state.energy_fitted and state.step < cfg.steps:  # the table is fitted to the final weights' answers
            with torch.no_grad():
                getattr(self.material, W.ENERGY).fill_(1.0)
            state.energy_fitted = False
        in_step = False
        try:
            with StepBoundary() as boundary:
                while state.step < cfg.steps:
                    boundary.check()
                    in_step = True
                    loss = self.step()
                    in_step = False
                    state.seconds = done_before + time.perf_counter() - started
                    if cfg.validate_every and state.step % cfg.validate_every == 0:
                        self.check_progress()
                        if on_progress is not None:
                            on_progress(self)
                    if state.step % cfg.checkpoint_every == 0:
                        self.save_checkpoint()
                    if callback is not None:
                        callback(self.steps_done, loss)
                boundary.check()  # a Ctrl-C inside the last step ends the run here too
        except KeyboardInterrupt:
            if in_step:  # half a step (its batch drawn, its update perhaps made): the last checkpoint stands
                log.info("interrupted inside step %d: the last checkpoint stands", state.step + 1)
            elif state.step > 0:  # keep the steps done since the last periodic checkpoint
                self.save_checkpoint()
                log.info("interrupted at step %d: checkpoint %s written", state.step, self.checkpoint_path)
            raise
        if self._average and not state.average_applied:
            self._apply_average()
        sigma = blur_sigma(state.step, cfg)
        if not state.baked and (sigma > 0 or (self.material.config.offset and not state.offset_frozen)):
            log.warning("run ended inside the blur schedule (sigma %.3g): baking the blurred textures", sigma)
            bake(self.material, *effective_textures(self.material, sigma, cfg, state.offset_frozen))
            state.baked = True
        if self.material.config.energy_bins and not state.energy_fitted:
            fit_material(self.material, self.data, self.train_idx, cfg.seed)
            state.energy_fitted = True
        table = self.validate()
        if not state.progress or state.progress[-1][0] != state.step:
            state.progress.append([state.step, [[r["level"], r["mse"]] for r in table["levels"]],
                                   table["overall"]["mse"]])
        table["train_seconds"] = round(state.seconds, 1)
        table["steps"] = state.step
        table["dropped_steps"] = state.dropped_steps
        table["batch"] = cfg.batch
        self.save_checkpoint(table)
        return table

    def validate(self) -> dict:
        """Validation table of the material (as stored) on the held-out split."""
        self.material.eval()
        queries = np.asarray(self.data.queries[self.val_idx])
        target = np.asarray(self.data.rgb[self.val_idx])
        pred = predict(self.material, queries)
        self.material.train()
        return validation_table(pred, target, queries[:, C.SIGMA], self.material.config.resolution)
