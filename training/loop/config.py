"""Training configuration: optimiser, batches, blur schedule, loss, validation split, checkpoints.

Kept free of torch. Presets are plain values of `TrainConfig`; `PRESETS` names them for the CLI.
The schedule is counted in optimiser steps; the paper's recipe (30 000 steps, blur half-life 3 333)
is the `paper` preset, and the shorter presets scale every step count by the same factor.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from neumip.core.config import dataclass_from_dict

LOSSES = ("comb2", "mse", "relative", "log_weighted")
"""Names of the training losses (`TrainConfig.loss`, `losses.training_loss`)."""


@dataclass(frozen=True)
class TrainConfig:
    """How one material is fitted to its MBTF queries (defaults: the `ship` preset)."""

    steps: int = 2400
    """Optimiser steps in total (a resumed run continues up to this count)."""
    batch: int = 1 << 14
    """Queries per step, drawn uniformly with replacement from the training split."""
    lr: float = 1e-3
    """Adam learning rate (paper and author code: 1e-3, no scheduler)."""
    lr_schedule: str = "constant"
    """'constant' (paper) or 'cosine': the rate falls from `lr` to `lr * lr_final` along half a cosine
    over `steps` (a resumed run with another `steps` follows the new curve from where it is)."""
    lr_final: float = 0.05
    """Final learning rate of the cosine schedule, as a fraction of `lr`."""
    loss: str = "comb2"
    """'comb2': MSE of log1p(max(x, -0.1)) plus l1_weight x L1 of the same (author code); 'mse': plain MSE;
    'relative': MSE over the detached prediction squared (unbiased under noisy targets, `losses.relative_mse`);
    'log_weighted': MSE over (1 + the detached prediction) squared (comb2's weights, unbiased:
    `losses.log_weighted_mse`)."""
    l1_weight: float = 0.1
    """Weight of the L1 term in the comb2 loss."""
    finish_loss: str = ""
    """A loss for the run's last `finish_fraction` of its steps ('' none; a name from `LOSSES`): e.g. an
    unbiased one after `comb2`, whose log settles darker than the noisy targets' mean."""
    finish_fraction: float = 0.0
    """Fraction of `steps`, at the run's end, trained with `finish_loss` (rounded to whole steps)."""
    coarse_loss: str = ""
    """A loss for the queries whose level of detail is `coarse_level` or coarser ('' none; a name from `LOSSES`):
    e.g. an unbiased one where a glossy material's glints leave the coarse footprints' 16-spp targets noisy."""
    coarse_level: float = 3.0
    """The level of detail (log2(sigma R) + lod_bias, of the model's pyramid) from which `coarse_loss` applies."""
    distil: int = 0
    """Targets of the queries at `distil_level` or coarser distilled from the model's own answers at the footprint
    `distil_texels`: the mean of this many (even; 0: off, the data's targets) at aim points spread over the rest
    of the query's footprint, redrawn every step (`distil.distilled_targets`), from `distil_start` of the run on."""
    distil_texels: float = 1.0
    """The footprint sigma, in the model's finest texels, that `distil`'s answers read."""
    distil_level: float = 3.0
    """The level of detail (as `coarse_level`) from which `distil` applies."""
    distil_start: float = 0.5
    """The fraction of `steps` after which `distil` applies (the finer levels must be fitted first)."""
    distil_weight: float = 1.0
    """The distilled answers' weight in those targets; the data's target has the rest."""
    finish_lr_scale: float = 1.0
    """The learning rate of those steps, as a fraction of the schedule's."""
    average_fraction: float = 0.0
    """The run's weights are the mean of those after each of its last `average_fraction` of the steps (only the
    steps after the blur schedule's end count; Polyak averaging: it smooths the step-to-step noise a constant
    learning rate leaves in the last step's weights); 0: the last step's weights."""
    blur_start: float = 8.0
    """Gaussian blur sigma of the neural textures at step 0, in texels of the finest level."""
    blur_half_life: float = 267.0
    """Steps after which the blur sigma halves (paper: 3333 of 30 000)."""
    blur_min: float = 0.2
    """Blur sigmas below this are skipped; the schedule ends when the finest level's sigma drops below it."""
    offset_blur_floor: float = 1.0
    """The offset texture is blurred with at least this sigma while the schedule runs, then frozen."""
    offset_freeze: bool = True
    """Freeze the offset texture when the blur schedule ends (author code); False trains it to the end
    (still blurred by `offset_blur_floor`, baked into the texture when the run ends)."""
    holdout: float = 0.05
    """Fraction of the data set held out for validation (never trained on)."""
    max_holdout: int = 200_000
    """Upper bound on held-out queries (validation time stays small on large data sets)."""
    validate_every: int = 400
    """Steps between progress validations (per-level MSE of the held-out split with the step's blur,
    kept in the run's history; `neumip train` then redraws NAME.progress.png); 0: none."""
    checkpoint_every: int = 500
    """Steps between checkpoints (one is also written at the end)."""
    log_every: int = 50
    """Steps between loss-history records (loss curve, progress)."""
    seed: int = 0
    """Seeds the initial weights, the split and the batch sampling (a run is reproducible)."""
    candidates: int = 1
    """Instances started from different initial weights (seeds `seed`, `seed` + 1, ...). Each trains
    `candidate_steps` steps on the same batches; the one with the lowest held-out MSE goes on and the
    others are dropped (best-of-k: a single run's result depends on its initial weights)."""
    candidate_steps: int = 300
    """Steps each candidate trains before they are compared."""
    device: str = "auto"
    """'auto' (CUDA when available, else CPU), 'cpu' or 'cuda'."""
    preload_mb: int = 2048
    """Data sets up to this size are copied into memory (page cache can be evicted under memory
    pressure, and random batches then read from disk); larger ones stay memory-mapped."""
    compile: bool = False
    """Run the forward pass and loss through torch.compile (about a minute of compiling first)."""

    def __post_init__(self) -> None:
        if self.validate_every < 0:
            raise ValueError(f"validate_every must be >= 0, got {self.validate_every}")
        if self.steps < 1 or self.batch < 1:
            raise ValueError(f"steps and batch must be >= 1, got {self.steps}, {self.batch}")
        if self.lr_schedule not in ("constant", "cosine") or not 0 <= self.lr_final <= 1:
            raise ValueError(f"lr_schedule must be 'constant' or 'cosine' and lr_final in [0, 1], "
                             f"got {self.lr_schedule!r}, {self.lr_final}")
        if self.loss not in LOSSES or self.finish_loss not in LOSSES + ("",) or self.coarse_loss not in LOSSES + ("",):
            raise ValueError(f"loss, finish_loss and coarse_loss must be one of {LOSSES}, got {self.loss!r}, "
                             f"{self.finish_loss!r}, {self.coarse_loss!r}")
        if not 0 <= self.average_fraction <= 1:
            raise ValueError(f"average_fraction must be in [0, 1], got {self.average_fraction}")
        if not 0 <= self.finish_fraction <= 1 or (self.finish_fraction > 0) != bool(self.finish_loss):
            raise ValueError(f"finish_fraction must be in [0, 1], and > 0 exactly when finish_loss is set, got "
                             f"{self.finish_fraction} with {self.finish_loss!r}")
        if (self.distil < 0 or self.distil % 2 or not 0 <= self.distil_start < 1 or not 0 < self.distil_weight <= 1
                or self.distil_texels <= 0):
            raise ValueError(f"distil must be 0 or an even number of samples, distil_start in [0, 1), distil_weight "
                             f"in (0, 1] and distil_texels > 0, got {self.distil}, {self.distil_start}, "
                             f"{self.distil_weight}, {self.distil_texels}")
        if not 0 < self.holdout < 1:
            raise ValueError(f"holdout must be in (0, 1), got {self.holdout}")
        if self.blur_half_life <= 0 or self.blur_start < 0 or self.blur_min <= 0:
            raise ValueError("blur_half_life and blur_min must be > 0, blur_start >= 0")
        if self.candidates < 1 or (self.candidates > 1 and not 1 <= self.candidate_steps < self.steps):
            raise ValueError(f"candidates must be >= 1 and candidate_steps in [1, steps), got "
                             f"{self.candidates}, {self.candidate_steps}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be 'auto', 'cpu' or 'cuda', got {self.device!r}")

    def finishing(self, step: int) -> bool:
        """Whether step `step` (counted from 0) is one of the finish's (`finish_loss`)."""
        return bool(self.finish_loss) and step >= self.steps - round(self.steps * self.finish_fraction)

    def distilling(self, step: int) -> bool:
        """Whether step `step` (counted from 0) trains its coarse queries on distilled targets (`distil`)."""
        return self.distil > 0 and step >= round(self.steps * self.distil_start)

    def loss_at(self, step: int) -> str:
        """The loss that trains step `step` (counted from 0)."""
        return self.finish_loss if self.finishing(step) else self.loss

    @property
    def total_steps(self) -> int:
        """Optimiser steps of a whole run, the dropped candidates' included."""
        return self.steps + (self.candidates - 1) * self.candidate_steps

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TrainConfig":
        return dataclass_from_dict(cls, data)


PAPER = TrainConfig(steps=30_000, batch=1 << 20, blur_half_life=3333.0, checkpoint_every=1000)
"""The paper / author preset: 30 000 steps of ~1 M queries, blur halving every 3 333 steps."""

SHIP = TrainConfig()
"""What the shipped 64^2 materials use on 2 shared CPU cores: the paper's schedule scaled by 0.08
(2 400 steps; blur reaches 1 texel at step 800 and ends at ~1 420), batches of 16 384."""

QUICK = replace(SHIP, steps=1200, blur_half_life=133.0, checkpoint_every=200, validate_every=200)
"""Half of `ship`: the same schedule scaled by 0.04."""

QUALITY = replace(SHIP, steps=10_000, blur_half_life=1111.0, checkpoint_every=1000, validate_every=1000)
"""The paper's schedule scaled by 1/3 in steps (10 000 steps; blur reaches 1 texel at step ~3 330, ends
at ~5 900, then the offset freezes) at ship's batch of 16 384: 4.2x ship's queries
(`neumip fit NAME --preset quality`, `FLAGS="--preset quality" bash models/make_models.sh`: for a GPU;
training/TRAINING.md)."""

TEST = replace(SHIP, steps=300, batch=4096, blur_start=2.0, blur_half_life=50.0, checkpoint_every=100, log_every=10,
               validate_every=100)
"""Unit-test sized: a few seconds for a 16 x 16 material."""

PRESETS = {"paper": PAPER, "quality": QUALITY, "ship": SHIP, "quick": QUICK, "test": TEST}


@dataclass(frozen=True)
class Recipe:
    """What a model is made of, beyond its schedule: what `neumip fit` (and `train --recipe`) makes when no flag
    says otherwise. A flag given on the command line wins over the recipe's value."""

    material: dict = field(default_factory=dict)
    """`MaterialConfig` fields over the config's defaults."""
    maps: dict | None = None
    """`MapConfig` fields of the map encoder (None: the paper's free latent textures)."""
    base: bool = False
    """The classical material on the material's maps as the base the decoder corrects."""
    relief: int = 0
    """Steps of the relief stage's march over the material's height map (0: none)."""


RECIPES = {
    "paper": Recipe(material={"half_textures": True}),
    "maps": Recipe(material={"lod_bias": 1, "local_frame": True, "terminator": "none", "half_textures": True,
                             "offset_mip": True, "energy_bins": 6, "energy_azimuths": 16},
                   maps={"horizons": 8}, base=True, relief=8),
}
"""Both store their textures in float16 (`MaterialConfig.half_textures`). `paper`: the paper's model (free latents,
neural offset); `maps`: the shipped map-informed model (latents encoded
from the prefiltered maps with horizons towards 8 azimuths, on the classical base, read in its normal's frame, the
relief marched in 8 steps, the finest level answering footprints of half a texel), its neural offset read at the
footprint on its mip pyramid (`MaterialConfig.offset_mip`: a far object's trimmed model sheds the offset's fine
levels too), its answers' energy table fitted at the end (`MaterialConfig.energy_bins` 6: the coarse levels' energy
that the log loss loses under noisy targets, `training/model/energy.py`; `energy_azimuths` 16: per azimuth of the
half vector, which an anisotropic material's coarse texels need). `neumip fit` makes `maps` for a
material with principled maps and `paper` for one without (a homogeneous [bsdf])."""
