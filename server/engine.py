"""The engine: what evaluates the server's materials (``NEUMIP_ENGINE``).

- ``onnxruntime`` (default): each material is an ONNX Runtime session running the file's graph
  (`neumip.client.local.load_material`); ``NEUMIP_ORT_WORKERS`` calls run at once (default one per
  core), each of at most ``NEUMIP_CHUNK_ROWS`` answers on ``NEUMIP_ORT_THREADS`` threads.
- ``kernel``: each material's graph, the same file's, is interpreted as drjit LLVM kernels
  (`neumip.client.kernel.KernelMaterial`, the renderer's in-process engine; needs the ``kernel``
  extra). One call runs at a time: drjit runs one frozen call at a time per process and
  spreads each call over every core itself. Calls hold up to ``NEUMIP_KERNEL_CHUNK_ROWS`` answers
  (default 2^18: fewer, larger calls than ONNX Runtime's, so the batcher's work between calls, while
  drjit's workers wait, is paid less often). Answers agree with ONNX Runtime's within the
  export's parity tolerance, and each row is computed alone, so they do not depend on the batch.

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

from neumip.core.errors import NeumipError
from neumip.client.local import Material, load_material

from .settings import Settings, available_cores

log = logging.getLogger(__name__)


ONNX_PLATFORM = "onnxruntime_onnx"
"""Triton's platform name of an ONNX model run by ONNX Runtime (its onnxruntime backend), which the
``onnxruntime`` engine is too."""
KERNEL_PLATFORM = "neumip_drjit_llvm"
"""The platform the model metadata names under the ``kernel`` engine: the file's graph as drjit LLVM
kernels."""


class EngineUnavailable(NeumipError, ImportError):
    """The engine asked for cannot run here (a missing extra or library); the message says how to fix it."""


@dataclass
class KernelModel(Material):
    """A material of the ``kernel`` engine: ``session`` is its `neumip.client.kernel.KernelMaterial`."""

    def run(self, queries: np.ndarray) -> np.ndarray:
        """One call: validated (n, 5 + 2 K) float32 queries -> (n, 3 K) float32 RGB."""
        return self.session.run(queries)


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
    platform: str = ONNX_PLATFORM
    """What runs the model files, as the Open Inference Protocol's model metadata names it (``platform``;
    ``onnxruntime_onnx`` is Triton's name for ONNX files run by ONNX Runtime)."""

    @classmethod
    def onnxruntime(cls, threads: int = 1, workers: int = 1, chunk_rows: int = 8192) -> "Engine":
        """ONNX Runtime sessions of `threads` intra-op threads each."""
        return cls("onnxruntime", lambda path, data: load_material(path, threads, data=data), workers, chunk_rows)

    @classmethod
    def kernel(cls, chunk_rows: int = 262144) -> "Engine":
        """drjit LLVM kernels, one call at a time; EngineUnavailable without drjit or a usable LLVM. Its
        `start` sizes drjit's pool, the process's, to the cores this process may run on, the calling
        thread counted (on one core: no worker thread). drjit's own default counts every core of the
        machine, whatever the process's CPU affinity; a pinned server's extra workers would only take
        turns, and each spins for 20 ms after a call (nanothread's ``NANOTHREAD_MAX_IDLE_MS``) on the
        cores the event loop needs."""
        try:
            from neumip.client.kernel import KernelMaterial
        except ImportError as exc:  # drjit or onnx missing, or only a libLLVM < 16: the message says which
            raise EngineUnavailable(f"NEUMIP_ENGINE=kernel cannot run: {exc}") from None
        import drjit as dr

        if not dr.has_backend(dr.JitBackend.LLVM):
            raise EngineUnavailable("NEUMIP_ENGINE=kernel cannot run: drjit found no libLLVM >= 16 (Debian: "
                                    "apt-get install libllvm19, or set DRJIT_LIBLLVM_PATH)")

        def load(path: Path, data: bytes) -> Material:
            kernel = KernelMaterial(path, data=data)
            return KernelModel(path.stem, path, kernel, kernel.metadata, len(data))

        return cls("kernel", load, 1, chunk_rows, lambda: dr.set_thread_count(available_cores()),
                   platform=KERNEL_PLATFORM)

    @classmethod
    def from_settings(cls, settings: Settings) -> "Engine":
        if settings.engine == "kernel":
            return cls.kernel(settings.kernel_chunk_rows)
        return cls.onnxruntime(settings.ort_threads, settings.workers(), settings.chunk_rows)
