"""Sizes of a report run: the full one and the tiny `--quick` one run the same pipeline."""

from __future__ import annotations

from dataclasses import dataclass, field

from .views import Film

MATERIALS = ("flat", "rock", "yarn", "turtle", "foam")
"""Every shipped material with height, and `flat` as the known-answer control."""


@dataclass(frozen=True)
class ReportConfig:
    """How large a report run is."""

    film: Film = field(default_factory=lambda: Film(64, 48))
    """Image size of every view."""
    reference_spp: int = 256
    """Samples per pixel of each of the reference's two seeds (the reference is their mean)."""
    spp: int = 64
    """Samples per pixel of each method's two-seed renders (scores, bias and noise)."""
    reference_ladder: tuple[int, ...] = (1, 4, 16, 64, 256)
    """spp ladder of R (error against time)."""
    ladder: tuple[int, ...] = (1, 4, 16, 64)
    """spp ladder of the other methods (their error flattens earlier: a bias floor)."""
    rounds: int = 2
    """Interleaved timing rounds of the ladder (the median is reported)."""
    max_lanes: int = 1 << 20
    """Most pixels x samples in one render pass."""
    threads: int = 2
    """Threads of the in-process neural evaluator."""
    tradeoff_steps: int = 600
    """Training steps of each trade-off configuration (the `quick` preset's schedule, halved)."""
    tradeoff_batch: int = 8192
    """Queries per training step of the trade-off configurations."""
    tradeoff_queries: int = 1 << 18
    """Training queries of the trade-off data set (4 spp each)."""
    tradeoff_reference_queries: int = 1 << 14
    """Low-noise validation queries of the trade-off (64 spp each)."""
    tradeoff_resolutions: tuple[int, ...] = (32, 64, 128, 256)
    """Finest resolutions of the trade-off configurations."""
    sweep_points: int = 256
    """Points of each query-domain sweep."""
    horizon_film: Film = field(default_factory=lambda: Film(96, 96))
    """Image of the plane-to-the-horizon render."""


FULL = ReportConfig()
QUICK = ReportConfig(
    film=Film(24, 18), reference_spp=64, spp=16, reference_ladder=(1, 16), ladder=(1, 16), rounds=1,
    tradeoff_steps=30, tradeoff_batch=1024, tradeoff_queries=1 << 13, tradeoff_reference_queries=1 << 10,
    tradeoff_resolutions=(32, 64), sweep_points=64, horizon_film=Film(32, 32),
)
"""The same pipeline at tiny sizes (tests, a first look)."""
