"""Generate an MBTF training set for a material: sample queries, path-trace them, write chunks.

Chunk ``k`` is fully determined by ``(seed, k)``: its queries come from ``numpy`` seeded with
``[seed, k]`` and its path samples from PCG32 streams seeded the same way, so an interrupted run
resumes at the first unfinished chunk (``DatasetWriter``) and the same seed gives the same data.
Chunks are traced in this process or as Ray tasks (:mod:`neumip.core.cluster`); either way this
process writes them, in order, so the data set is the same bit for bit.
The data set format (``.npy`` + ``meta.json``, memory-mapped for training) is
:mod:`neumip.groundtruth.dataset`; ``meta.json`` carries the material description and these settings.
"""

from __future__ import annotations

import importlib.metadata
import json
import logging
import time
from contextlib import closing
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from neumip.client.mitsuba.runtime import import_mitsuba
from neumip.core import cluster
from neumip.core import contract as C
from neumip.core.cluster import RayConfig
from neumip.groundtruth.dataset import Dataset, DatasetWriter

from neumip.groundtruth.description import MaterialDescription, Microgeometry, resolve
from neumip.groundtruth.mesh import TilingConfig
from neumip.groundtruth.sampling import QuerySampling, sample_queries
from neumip.groundtruth.tracer import QueryTracer, TracerConfig

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
    coarse_spp: int = 0
    """Path samples per query of the queries whose footprint is `coarse_texels` finest texels or wider (0: `spp`;
    else more than `spp`: their `spp` samples, then more).
    A glossy material's rare glints make a coarse footprint's 16-sample estimate noisy, and training's log loss
    settles below a noisy target's mean (experiments/level_share)."""
    coarse_texels: float = 8.0
    """Where `coarse_spp` starts: sigma * resolution >= this (8: level of detail 3)."""
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
    """Tiled geometry around the central tile; its margin is widened for the sampling's largest zenith angle
    where that is larger (a grazing shadow ray must cross geometry, not leave it)."""

    def __post_init__(self) -> None:
        if self.sampling.max_zenith_deg > self.tiling.max_zenith_deg:
            self.tiling = replace(self.tiling, max_zenith_deg=self.sampling.max_zenith_deg)
        if self.queries is not None and self.queries < 1:
            raise ValueError(f"queries must be >= 1, got {self.queries}")
        coarse_ok = (not self.coarse_spp or self.coarse_spp > self.spp) and self.coarse_texels > 0
        if self.spp < 1 or self.chunk < 1 or not coarse_ok:
            raise ValueError(f"spp and chunk must be >= 1, coarse_spp 0 or more than spp ({self.spp}) and "
                             f"coarse_texels > 0, got {self.coarse_spp} and {self.coarse_texels}")
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
        sampling = asdict(self.sampling)
        if sampling["directions"] == "disk":  # the only kind before the option: older data sets stay valid
            del sampling["directions"]
        if sampling["levels_resolution"] is None:  # likewise
            del sampling["levels_resolution"]
        if not sampling["sub_texel_levels"]:  # likewise
            del sampling["sub_texel_levels"]
        coarse = {"coarse_spp": self.coarse_spp, "coarse_texels": self.coarse_texels} if self.coarse_spp else {}
        return {
            "name": GENERATOR,
            "queries": self.query_count(desc),
            "spp": self.spp,
            **coarse,  # only where set: older data sets stay valid
            "seed": self.seed,
            "resolution": self.sampling_resolution(desc),
            "sampling": sampling,
            "tracer": tracer,
            "tiling": asdict(self.tiling),
        }


def chunk_seeds(seed: int, index: int) -> tuple[np.random.Generator, int]:
    """The query generator and the path-sample seed of chunk `index`."""
    path_seed = int(np.random.SeedSequence([seed, index, 1]).generate_state(1, np.uint64)[0])
    return np.random.default_rng([seed, index]), path_seed


def trace_chunk(
    tracer: QueryTracer, settings: GenerateSettings, resolution: int, index: int, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Chunk `index` of `size` queries: its (size, 7) queries and their (size, 3) estimates. With `coarse_spp`, those
    of footprints from `coarse_texels` texels get `coarse_spp - spp` more samples, traced as a pass of their own, and
    the rest keep the bits they have without it."""
    rng, path_seed = chunk_seeds(settings.seed, index)
    queries = sample_queries(size, rng, resolution, settings.sampling)  # (size, 7)
    rgb = tracer.estimate(queries, settings.spp, path_seed)
    if not settings.coarse_spp:
        return queries, rgb
    coarse = queries[:, C.SIGMA] * resolution >= settings.coarse_texels
    if coarse.any():
        more = settings.coarse_spp - settings.spp
        extra = tracer.estimate(queries[coarse], more, path_seed ^ 1)
        rgb[coarse] = ((settings.spp * rgb[coarse].astype(np.float64) + more * extra) / settings.coarse_spp)
    return queries, rgb


Chunks = Iterator[tuple[int, np.ndarray, np.ndarray]]
"""(index, queries, rgb) of each chunk, in index order."""


def generate(
    desc: MaterialDescription,
    out: str | Path,
    settings: GenerateSettings | None = None,
    on_chunk: Callable[[int, int], None] | None = None,
    ray: RayConfig | None = None,
) -> Dataset:
    """Write (or resume) the data set for `desc` at `out`; returns it opened read-only.

    ``on_chunk(done, total)`` is called with query counts once at the start and after every chunk.
    With `ray`, chunks are traced as Ray tasks (same data, bit for bit); this process still writes.
    """
    settings = settings or GenerateSettings()
    n = settings.query_count(desc)
    meta = {"material": desc.to_dict(), "generator": settings.to_meta(desc)}
    if desc.base_dir is not None and "map_sha256" in meta["material"]:
        meta["description_dir"] = str(desc.base_dir.resolve())  # where its map files are (training's views)
    writer = DatasetWriter(out, n, settings.chunk, meta)
    if writer.complete:
        log.info("%s is already complete with these settings: nothing to do", out)
    elif writer.done:
        log.info("resuming %s at chunk %d of %d", out, writer.done, writer.chunks)
    report = on_chunk or (lambda done, total: None)
    report(writer.chunk_range(writer.done)[0] if writer.done < writer.chunks else n, n)
    jobs = []  # (chunk index, queries in it) of the chunks still to do
    for index in range(writer.done, writer.chunks):
        lo, hi = writer.chunk_range(index)
        jobs.append((index, hi - lo))
    if jobs:
        chunks = _local_chunks(desc, settings, jobs) if ray is None else _ray_chunks(desc, settings, jobs, ray)
        with closing(chunks):
            for index, queries, rgb in chunks:
                writer.write_chunk(index, queries, rgb)
                report(writer.chunk_range(index)[1], n)
    return writer.finalize()


def _local_chunks(desc: MaterialDescription, settings: GenerateSettings, jobs: list[tuple[int, int]]) -> Chunks:
    tracer = QueryTracer(resolve(desc), settings.tracer, settings.tiling)
    resolution = settings.sampling_resolution(desc)
    for index, size in jobs:
        start = time.perf_counter()
        queries, rgb = trace_chunk(tracer, settings, resolution, index, size)
        log.debug("chunk %d: %.0f samples/s", index, size * settings.spp / (time.perf_counter() - start))
        yield index, queries, rgb


# --- Ray: chunks as tasks; the description is resolved once here, so workers need no map files ------

def _ray_chunks(
    desc: MaterialDescription, settings: GenerateSettings, jobs: list[tuple[int, int]], config: RayConfig
) -> Chunks:
    geo = resolve(desc)
    key = json.dumps([desc.to_dict(), settings.to_meta(desc), asdict(settings.tracer)], sort_keys=True)
    resolution = settings.sampling_resolution(desc)
    shared = (geo, key, settings, resolution, config.cpus_per_task, _versions())
    results = cluster.ordered(_chunk_task, jobs, config, shared)
    with closing(results):
        for (index, _), (queries, rgb) in zip(jobs, results):
            yield index, queries, rgb


_worker_tracer: dict[str, QueryTracer] = {}
"""The tracer of the material this worker process traced last (building its scene takes seconds)."""

VERSIONED = ("neumip", "mitsuba", "drjit", "numpy")
"""Packages whose versions must match between the driver and every worker for identical bits."""


def _versions() -> dict[str, str]:
    def version(name: str) -> str:
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            return "not installed"

    return {name: version(name) for name in VERSIONED}


def _chunk_task(
    geo: Microgeometry, key: str, settings: GenerateSettings, resolution: int, threads: int,
    driver_versions: dict[str, str], index: int, size: int,
) -> tuple[np.ndarray, np.ndarray]:
    """One chunk in a Ray worker, with `threads` drjit threads (its CPU share, not every core)."""
    tracer = _worker_tracer.get(key)
    if tracer is None:
        if _versions() != driver_versions:
            raise RuntimeError(f"this Ray node has {_versions()}, the driver {driver_versions}: the same "
                               "versions on every node give the same data")
        _worker_tracer.clear()
        import_mitsuba(settings.tracer.variant)
        import drjit as dr

        dr.set_thread_count(threads)
        tracer = _worker_tracer[key] = QueryTracer(geo, settings.tracer, settings.tiling)
    return trace_chunk(tracer, settings, resolution, index, size)
