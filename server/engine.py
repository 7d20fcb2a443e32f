"""The engine: what evaluates the server's materials (``NEUMIP_ENGINE``).

- ``auto`` (default): ``kernel`` where it can run (drjit and a libLLVM >= 16), else ``onnxruntime``;
- ``onnxruntime``: each material is an ONNX Runtime session running the file's graph
  (`neumip.engines.local.load_material`); ``NEUMIP_ORT_WORKERS`` calls run at once (default one per
  core), each of at most ``NEUMIP_CHUNK_ROWS`` answers on ``NEUMIP_ORT_THREADS`` threads.
- ``kernel``: each material's graph, the same file's, is interpreted as drjit LLVM kernels
  (`neumip.engines.kernel.KernelMaterial`, the renderer's in-process engine; needs the ``kernel``
  extra). One call runs at a time: drjit runs one frozen call at a time per process and
  spreads each call over every core itself. Calls hold up to ``NEUMIP_KERNEL_CHUNK_ROWS`` answers
  (default 2^18: fewer, larger calls than ONNX Runtime's, so the batcher's work between calls, while
  drjit's workers wait, is paid less often). Answers agree with ONNX Runtime's within the
  export's parity tolerance, and each row is computed alone, so they do not depend on the batch.

The kernel engine traces (compiles) its arithmetic once per number of lights in a group, seconds for
each width with an empty drjit cache (more for wider groups, every material again), holding the process-wide drjit
lock that every other material's calls need. So it only ever runs the widths the registry's warm-up
traced, `WARM_LIGHTS` (1-3 lights): a wider group is split into groups of three lights (and one group of
the rest), evaluated in one call each, and put back together. The bits are those of the group's single
queries either way; the cost is not: each group computes its position's lookups once, so three lights
evaluated as a pair and a single query cost about 1.6x one group of three (server/README.md).

Both engines read a file through the one model-file reader (`neumip.core.modelfile`), so both refuse
a file with a non-finite weight (NaN or Inf in any float initializer) when it loads, naming the
tensors, and both answer 500 naming the material and the row for an answer that is not finite
(`batching`), e.g. from a graph that gives NaN for some inputs.

Either way the registry and the batcher see one thing per material: a `Material` whose
``run(queries) -> answers`` evaluates one call and whose ``bytes`` count against the memory budget
(the file's size).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.core.errors import NeumipError
from neumip.engines.local import Material, load_material

from neumip.server.settings import Settings, available_cores

log = logging.getLogger(__name__)


ONNX_PLATFORM = "onnxruntime_onnx"
"""Triton's platform name of an ONNX model run by ONNX Runtime (its onnxruntime backend), which the
``onnxruntime`` engine is too."""
KERNEL_PLATFORM = "neumip_drjit_llvm"
"""The platform the model metadata names under the ``kernel`` engine: the file's graph as drjit LLVM
kernels."""


class EngineUnavailable(NeumipError, ImportError):
    """The engine asked for cannot run here (a missing extra or library); the message says how to fix it."""


WARM_LIGHTS = (1, 2, 3)
"""Lights of the query groups the kernel engine evaluates as they are: the widths the registry warms up
(`Registry`'s warm-up runs single queries and groups of two and three: a renderer's next-event estimation
towards one or two emitters, plus its BSDF sample), so the engine compiles nothing once a material is
loaded. A wider group runs as groups of the widest (`in_groups`)."""


@dataclass
class KernelModel(Material):
    """A material of the ``kernel`` engine: ``session`` is its `neumip.engines.kernel.KernelMaterial`."""

    def run(self, queries: np.ndarray) -> np.ndarray:
        """One call: validated (n, 5 + 2 K) float32 queries -> (n, 3 K) float32 RGB; groups of more lights
        than `WARM_LIGHTS` holds as groups of its widest (`in_groups`)."""
        if C.group_lights(queries.shape[1]) in WARM_LIGHTS:
            return self.session.run(queries)
        return in_groups(self.session.run, queries, max(WARM_LIGHTS))


def in_groups(run: Callable[[np.ndarray], np.ndarray], queries: np.ndarray, width: int) -> np.ndarray:
    """Query groups of K > `width` lights (n, 5 + 2 K) -> (n, 3 K) RGB, evaluated by `run` as groups of
    `width` lights, (n (K // width), 5 + 2 width), and the last K % width lights of each group as one group
    (or single queries) of their own: each call computes a group's position once, so fewer, wider groups
    cost less. Every light answers with the bits of its single query (`contract.ungroup`)."""
    n, lights = queries.shape[0], C.group_lights(queries.shape[1])
    wi = np.empty((n, lights, 2), C.DTYPE)  # every light's wi, in order
    wi[:, 0] = queries[:, C.WI_X:C.WI_Y + 1]
    wi[:, 1:] = queries[:, C.QUERY_DIM:].reshape(n, lights - 1, 2)
    rgb = np.empty((n, lights, C.RGB_DIM), C.DTYPE)
    whole = lights // width
    for first, count, parts in ((0, width, whole), (whole * width, lights % width, 1)):
        if not count or not parts:
            continue
        part = wi[:, first:first + count * parts].reshape(n, parts, count, 2)
        groups = np.empty((n, parts, C.group_width(count)), C.DTYPE)
        groups[:, :, :C.WI_X] = queries[:, None, :C.WI_X]
        groups[:, :, C.WI_X:C.WI_Y + 1] = part[:, :, 0]
        groups[:, :, C.WO_X:C.QUERY_DIM] = queries[:, None, C.WO_X:C.QUERY_DIM]
        groups[:, :, C.QUERY_DIM:] = part[:, :, 1:].reshape(n, parts, 2 * (count - 1))
        rgb[:, first:first + count * parts] = run(groups.reshape(n * parts, -1)).reshape(n, count * parts, C.RGB_DIM)
    return rgb.reshape(n, lights * C.RGB_DIM)


@dataclass(frozen=True)
class Engine:
    """How materials are loaded and how many rows, and calls at once, one evaluation takes."""

    name: str
    """``onnxruntime`` or ``kernel`` (`Settings.engine`)."""
    load: Callable[[Path, bytes], Material]
    """A model file's path and bytes -> the material, warmed up by its first call; raises ModelError."""
    workers: int = 1
    """Calls that run at once (the batcher's worker threads)."""
    chunk_rows: int = 8192
    """Most answers in one call."""
    start: Callable[[], None] = lambda: None
    """Process-wide set-up before the first call, run once by the batcher when it starts (the kernel
    engine: drjit's pool size). Building an engine changes nothing else in the process."""
    idle: Callable[[], object] = lambda: None
    """Process-wide tidy-up once no request has been in flight for a second, before the heap is trimmed
    (`admission`; the kernel engine: drjit's cache of freed blocks, `release_cached_memory`)."""
    platform: str = ONNX_PLATFORM
    """What runs the model files, as the Open Inference Protocol's model metadata names it (``platform``;
    ``onnxruntime_onnx`` is Triton's name for ONNX files run by ONNX Runtime)."""

    @classmethod
    def onnxruntime(cls, threads: int = 1, workers: int = 1, chunk_rows: int = 8192) -> "Engine":
        """ONNX Runtime sessions of `threads` intra-op threads each (`load_material`: ModelError for a
        file it cannot run, non-finite weights included)."""

        def load(path: Path, data: bytes) -> Material:
            return load_material(path, threads, data=data)

        return cls("onnxruntime", load, workers, chunk_rows)

    @classmethod
    def kernel(cls, chunk_rows: int = 262144) -> "Engine":
        """drjit LLVM kernels, one call at a time; EngineUnavailable without drjit or a usable LLVM. Its
        `start` sizes drjit's pool, the process's, to the cores this process may run on, the calling
        thread counted (on one core: no worker thread). drjit's own default counts every core of the
        machine, whatever the process's CPU affinity; a pinned server's extra workers would only take
        turns, and each spins for 20 ms after a call (nanothread's ``NANOTHREAD_MAX_IDLE_MS``) on the
        cores the event loop needs."""
        try:
            from neumip.engines.kernel import KernelMaterial, release_cached_memory
        except ImportError as exc:  # drjit or onnx missing, or only a libLLVM < 16: the message says which
            raise EngineUnavailable(f"NEUMIP_ENGINE=kernel cannot run: {exc}") from None
        import drjit as dr

        if not dr.has_backend(dr.JitBackend.LLVM):
            raise EngineUnavailable("NEUMIP_ENGINE=kernel cannot run: drjit found no libLLVM >= 16 (Debian: "
                                    "apt-get install libllvm19, or set DRJIT_LIBLLVM_PATH)")

        def load(path: Path, data: bytes) -> Material:
            kernel = KernelMaterial(path, data=data)
            return KernelModel(path.stem, path, kernel, kernel.file)

        return cls("kernel", load, 1, chunk_rows, lambda: dr.set_thread_count(available_cores()),
                   idle=release_cached_memory, platform=KERNEL_PLATFORM)

    @classmethod
    def from_settings(cls, settings: Settings) -> "Engine":
        """The engine `settings.engine` names; ``auto``: the kernel engine where it can run, else ONNX Runtime."""
        if settings.engine in ("kernel", "auto"):
            try:
                return cls.kernel(settings.kernel_chunk_rows)
            except EngineUnavailable as exc:
                if settings.engine == "kernel":
                    raise
                log.info("NEUMIP_ENGINE=auto: ONNX Runtime (%s)", str(exc).split(": ", 1)[-1])
        return cls.onnxruntime(settings.ort_threads, settings.workers(), settings.chunk_rows)
