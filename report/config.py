"""Sizes of a report run: the full one and the tiny `--quick` one run the same pipeline."""

from __future__ import annotations

from dataclasses import dataclass, field

from neumip.report.views import Film

MATERIALS = ("flat", "rock", "yarn", "turtle", "foam")
"""Every shipped material with height, and `flat` as the known-answer control."""


@dataclass(frozen=True)
class ReportConfig:
    """How large a report run is."""

    film: Film = field(default_factory=lambda: Film(192, 144))
    """Image size of the views (large enough that one method's 64-spp render takes ~0.5 s on 2 cores)."""
    max_reference_tiles: float = 24_000
    """Most tiles a view of real geometry may show: a far view of fine maps gets a smaller film
    (R's instances of a tile block: their cost grows with their count)."""
    reference_spp: int = 128
    """Samples per pixel of each of the reference's two seeds (the reference is their mean)."""
    spp: int = 64
    """Samples per pixel of each method's two-seed renders (scores, bias and noise)."""
    ladder: tuple[int, ...] = (1, 4, 16, 64)
    """spp ladder of every method (error against time), in the views of the ladder light; R's time
    beyond its last rung is extrapolated (it is unbiased: its error above R's noise falls as 1/spp)."""
    rounds: int = 3
    """Timed interleaved rounds of the ladder, after one untimed round (the fastest is reported)."""
    retime: bool = False
    """Render every ladder view's timed rungs anew, every method's, whatever the cache holds (`neumip report
    --retime`): the timings of this run alone, say on a quiet machine; the scored images still come from the cache."""
    smoke: bool = False
    """A smoke run (tiny sizes): its timings mean nothing and the report draws no timing verdicts."""
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

    def __post_init__(self) -> None:
        if self.spp not in self.ladder:
            raise ValueError(f"the scored spp {self.spp} must be a rung of the ladder {self.ladder}")


FULL = ReportConfig()
QUICK = ReportConfig(
    film=Film(24, 18), max_reference_tiles=2_000, reference_spp=64, spp=16, ladder=(1, 16), rounds=1, smoke=True,
    tradeoff_steps=30, tradeoff_batch=1024, tradeoff_queries=1 << 13, tradeoff_reference_queries=1 << 10,
    tradeoff_resolutions=(32, 64), sweep_points=64, horizon_film=Film(32, 32),
)
"""The same pipeline at tiny sizes (tests, a first look)."""
