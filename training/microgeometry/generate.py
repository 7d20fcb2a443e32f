"""Generate an MBTF training set for a material: sample queries, path-trace them, write chunks.

Chunk ``k`` is fully determined by ``(seed, k)``: its queries come from ``numpy`` seeded with
``[seed, k]`` and its path samples from PCG32 streams seeded the same way, so an interrupted run
resumes at the first unfinished chunk (``DatasetWriter``) and the same seed gives the same data.
The data set format (``.npy`` + ``meta.json``, memory-mapped for training) is
:mod:`neumip.training.dataset`; ``meta.json`` carries the material description and these settings.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from neumip.training.dataset import Dataset, DatasetWriter

from .description import MaterialDescription, resolve
from .mesh import TilingConfig
from .sampling import QuerySampling, sample_queries
from .tracer import QueryTracer, TracerConfig

log = logging.getLogger(__name__)

GENERATOR = "neumip.microgeometry/1"
"""Identifies this generator (and its version) in data set metadata."""


@dataclass
class GenerateSettings:
    """What to generate for one material."""

    queries: int | None = None
    """Number of queries; None: ``sampling.queries_per_texel`` per finest texel."""
    spp: int = 16
    """Path samples per query."""
    seed: int = 0
    """Seed of the whole data set (same seed, same data)."""
    chunk: int = 1 << 16
    """Queries per chunk (the unit of resumption)."""
    resolution: int | None = None
    """Finest texel count per tile side that sigma is sampled for; None: the description's resolution."""
    sampling: QuerySampling = field(default_factory=QuerySampling)
    """Distribution of (u, sigma, wi, wo)."""
    tracer: TracerConfig = field(default_factory=TracerConfig)
    """Path tracing settings."""
    tiling: TilingConfig = field(default_factory=TilingConfig)
    """Tiled geometry around the central tile."""

    def __post_init__(self) -> None:
        if self.queries is not None and self.queries < 1:
            raise ValueError(f"queries must be >= 1, got {self.queries}")
        if self.spp < 1 or self.chunk < 1:
            raise ValueError("spp and chunk must be >= 1")
        if not 0 <= self.seed < 2**63:
            raise ValueError(f"seed must be in [0, 2^63), got {self.seed}")

    def query_count(self, desc: MaterialDescription) -> int:
        if self.queries is not None:
            return self.queries
        return max(1, round(self.sampling.queries_per_texel * self.sampling_resolution(desc) ** 2))

    def sampling_resolution(self, desc: MaterialDescription) -> int:
        return self.resolution or desc.resolution

    def to_meta(self, desc: MaterialDescription) -> dict:
        """What identifies the data (pass sizes and the wavefront width do not change it)."""
        tracer = {k: v for k, v in asdict(self.tracer).items() if k != "lanes"}
        return {
            "name": GENERATOR,
            "queries": self.query_count(desc),
            "spp": self.spp,
            "seed": self.seed,
            "resolution": self.sampling_resolution(desc),
            "sampling": asdict(self.sampling),
            "tracer": tracer,
            "tiling": asdict(self.tiling),
        }


def chunk_seeds(seed: int, index: int) -> tuple[np.random.Generator, int]:
    """The query generator and the path-sample seed of chunk `index`."""
    path_seed = int(np.random.SeedSequence([seed, index, 1]).generate_state(1, np.uint64)[0])
    return np.random.default_rng([seed, index]), path_seed


def generate(
    desc: MaterialDescription,
    out: str | Path,
    settings: GenerateSettings | None = None,
    on_chunk: Callable[[int, int], None] | None = None,
) -> Dataset:
    """Write (or resume) the data set for `desc` at `out`; returns it opened read-only.

    ``on_chunk(done, total)`` is called with query counts once at the start and after every chunk.
    """
    settings = settings or GenerateSettings()
    n = settings.query_count(desc)
    meta = {"material": desc.to_dict(), "generator": settings.to_meta(desc)}
    writer = DatasetWriter(out, n, settings.chunk, meta)
    if writer.complete:
        log.info("%s is already complete with these settings: nothing to do", out)
    elif writer.done:
        log.info("resuming %s at chunk %d of %d", out, writer.done, writer.chunks)
    report = on_chunk or (lambda done, total: None)
    report(writer.chunk_range(writer.done)[0] if writer.done < writer.chunks else n, n)
    if writer.done < writer.chunks:
        tracer = QueryTracer(resolve(desc), settings.tracer, settings.tiling)
        resolution = settings.sampling_resolution(desc)
        for index in range(writer.done, writer.chunks):
            lo, hi = writer.chunk_range(index)
            rng, path_seed = chunk_seeds(settings.seed, index)
            start = time.perf_counter()
            queries = sample_queries(hi - lo, rng, resolution, settings.sampling)  # (n_chunk, 7)
            rgb = tracer.estimate(queries, settings.spp, path_seed)  # (n_chunk, 3)
            writer.write_chunk(index, queries, rgb)
            seconds = time.perf_counter() - start
            log.debug("chunk %d: %.0f samples/s", index, (hi - lo) * settings.spp / seconds)
            report(hi, n)
    return writer.finalize()
