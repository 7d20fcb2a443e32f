"""In-process evaluation of exported materials with ONNX Runtime (no torch).

`LocalMaterials` loads every ``*.onnx`` in a folder (material name = file stem; `folder.ModelFolder`),
each read and checked by the one model-file reader (`neumip.core.modelfile`), and evaluates (N, 7)
query buffers, or query groups (N, 5 + 2 K) (`contract`), in chunks that run concurrently on a small
thread pool (``InferenceSession.run`` releases the GIL), each chunk on one ONNX Runtime thread.
How a batch is cut does not change the answers: the exported graph answers a query with the same
bits in any call (`neumip.training.export.graph`), so the thread count and chunk size only set the speed.
Measured in ``benchmarks/bench_inference.py`` (sections session and chunk).
"""

from __future__ import annotations

import logging
import os
import threading
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from neumip.core import contract as C
from neumip.core.modelfile import ModelError, ModelFile, read_model_file
from neumip.engines.folder import NAME_PATTERN, ModelFolder, UnknownMaterial, open_folder, read_model_bytes

__all__ = ["NAME_PATTERN", "LocalMaterials", "Material", "ModelError", "UnknownMaterial", "load_material"]

log = logging.getLogger(__name__)

DEFAULT_CHUNK = 16384
"""Answers per ONNX Runtime call of `LocalMaterials` (rows of single queries; a group of K lights
counts K). On the shipped models' graph (about 730 nodes a call) chunks of 2^14 rows ran 10-16 % more
queries per CPU second than 2^12 (per-node overhead paid less often; 2^15 and more were slower again),
for about 70 MB of ONNX Runtime arena on two workers instead of 18 (benchmarks/bench_engines.py; measured with an
arena per material, before every session shared one: `SESSION_CONFIG`)."""

MIN_SPLIT = 2048
"""Batches below twice this many rows run as one call (splitting them costs more than it saves)."""

SESSION_CONFIG = {"session.intra_op.allow_spinning": "0", "session.use_env_allocators": "1"}
"""Session config entries.
- Pool threads sleep instead of spinning between ops. On a machine shared with other jobs spinning threads take
  cores the other threads need (2 intra-op threads ran at about half the speed with spinning on under load).
- Every session allocates from one CPU arena of the process (`_onnxruntime` registers it), not an arena of its own.
  An arena keeps the peak of what its calls took, and two workers on one session grew it further: the six shipped
  models' sessions held 403-422 MiB after a call each and 629-636 MiB three rounds later with an arena each; with
  one shared arena, which keeps the peak of the calls that run at once, 223-231 and 264-265 MiB, at 12 % more
  queries per CPU second. Without an arena glibc maps and unmaps every call's buffers (`MALLOC_MMAP_THRESHOLD_`, as
  the Docker image sets it): 197 MiB, 28 % slower (`benchmarks/bench_loading.py --sections arena`)."""

_ARENA = threading.Lock()
_arena_registered = False


def _onnxruntime():
    """onnxruntime, imported with the process's shared CPU arena registered (`SESSION_CONFIG`)."""
    # ONNX Runtime >= 1.29 sends usage telemetry, and where it cannot write its cache (a container
    # user without a home) warns at start-up in raw ANSI colours; ORT_DISABLE_TELEMETRY=0 turns it back on
    os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
    try:
        import onnxruntime
    except ImportError as exc:  # pragma: no cover - base dependency
        raise ImportError("onnxruntime is missing: pip install neumip") from exc
    share_arena(onnxruntime)
    return onnxruntime


def share_arena(onnxruntime) -> None:
    """Register the process's one CPU arena, which sessions with `SESSION_CONFIG` allocate from (once a process)."""
    global _arena_registered
    with _ARENA:
        if not _arena_registered:
            memory = onnxruntime.OrtMemoryInfo("Cpu", onnxruntime.OrtAllocatorType.ORT_ARENA_ALLOCATOR, 0,
                                               onnxruntime.OrtMemType.DEFAULT)
            try:  # no limit, default growth, chunk sizes (-1: ONNX Runtime's defaults)
                onnxruntime.create_and_register_allocator(memory, onnxruntime.OrtArenaCfg(0, -1, -1, -1))
            except Exception as exc:  # one is registered already (another library in the process): sessions share it
                log.debug("ONNX Runtime's shared CPU arena not registered: %s", exc)
            _arena_registered = True


@dataclass
class Material:
    """One loaded material: its ONNX Runtime session and what its file declares."""

    name: str
    path: Path
    session: object
    file: ModelFile
    """The model file's metadata, config, trim and sampling lobe (`core.modelfile.read_model_file`)."""
    single_queries: bool = False
    """Whether the graph's input is fixed at 7 columns (a graph made by another tool that takes no
    query groups): each light of a group is then answered as its single query, as the in-kernel engine
    answers it."""

    @property
    def metadata(self) -> dict[str, str]:
        return self.file.metadata

    @property
    def bytes(self) -> int:
        """Size of the model file it was loaded from."""
        return self.file.size

    @property
    def config(self) -> dict:
        """The model's config as a dict ({} for a graph without neumip metadata)."""
        return self.file.config_dict()

    @property
    def sampling(self) -> C.SamplingLobe | None:
        """The sampling lobe the model declares (`contract.SamplingLobe`; None: the cosine alone)."""
        return self.file.sampling

    def run(self, queries: np.ndarray) -> np.ndarray:
        """One call: validated (n, 5 + 2 K) float32 queries -> (n, 3 K) float32 RGB (`run_call`)."""
        if self.single_queries and queries.shape[1] != C.QUERY_DIM:
            return run_call(self.session, C.ungroup(queries)).reshape(queries.shape[0], -1)
        return run_call(self.session, queries)

    def info(self) -> dict:
        """What a listing shows of this material."""
        file = self.file
        return {
            "name": self.name,
            "contract_version": file.metadata.get(C.META_CONTRACT),
            "description": file.description,
            "config": self.config,
            "validation": file.validation,
            "trim": asdict(file.trim) if file.trim else None,
            "sampling": file.sampling._asdict() if file.sampling else None,
            "bytes": file.size,
        }


def load_material(path: str | Path, threads: int = 0, data: bytes | None = None) -> Material:
    """Open one ``.onnx`` material (from `data`, the file's bytes already read, if given); raises
    ModelError for a file the model-file reader refuses (`core.modelfile.read_model_file`: unreadable,
    corrupt, another contract version, non-finite weights...) or a graph that does not map queries to
    answers."""
    ort = _onnxruntime()
    path = Path(path)
    data = read_model_bytes(path) if data is None else data  # read once: for the reader and the session
    file = read_model_file(path, data)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    for key, value in SESSION_CONFIG.items():
        opts.add_session_config_entry(key, value)
    try:
        session = ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for corrupt files
        raise ModelError(f"{path.name}: cannot load ONNX model: {exc}") from exc
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if [i.name for i in inputs] != [C.ONNX_INPUT] or [o.name for o in outputs] != [C.ONNX_OUTPUT]:
        raise ModelError(f"{path.name}: graph must map '{C.ONNX_INPUT}' to '{C.ONNX_OUTPUT}'")
    if len(inputs[0].shape) != 2:
        raise ModelError(f"{path.name}: '{C.ONNX_INPUT}' must be 2-D, (N, {C.QUERY_DIM}) or (N, 5 + 2 K)")
    width = inputs[0].shape[1]
    if isinstance(width, int) and width != C.QUERY_DIM:
        raise ModelError(f"{path.name}: '{C.ONNX_INPUT}' must be (N, {C.QUERY_DIM}) or query groups "
                         f"(N, 5 + 2 K), not (N, {width})")
    return Material(path.stem, path, session, file, single_queries=width == C.QUERY_DIM)


def run_call(session, queries: np.ndarray) -> np.ndarray:
    """One ONNX Runtime call: validated (n, 7) float32 queries -> (n, 3), or query groups (n, 5 + 2 K)
    -> (n, 3 K)."""
    return session.run([C.ONNX_OUTPUT], {C.ONNX_INPUT: queries})[0]


def run_chunked(
    call: Callable[[np.ndarray], np.ndarray], queries: np.ndarray, chunk: int = DEFAULT_CHUNK,
    executor: Executor | None = None,
) -> np.ndarray:
    """Evaluate validated (N, 7) float32 queries, or query groups (N, 5 + 2 K), in calls of `chunk`
    rows of `call` (`Material.run`) -> (N, 3 K) float32.

    With an `executor` the chunks run concurrently on its threads.
    """
    n = queries.shape[0]
    out = np.empty((n, C.RGB_DIM * C.group_lights(queries.shape[1])), dtype=C.DTYPE)

    def run(lo: int) -> None:
        hi = min(lo + chunk, n)
        out[lo:hi] = call(queries[lo:hi])

    starts = range(0, n, chunk)
    if executor is None or len(starts) < 2:
        for lo in starts:
            run(lo)
    else:
        for future in [executor.submit(run, lo) for lo in starts]:
            future.result()
    return out


def split_chunk(rows: int, workers: int, chunk: int = DEFAULT_CHUNK) -> int:
    """Rows per call for `rows` rows on `workers` threads: at most `chunk`, in a number of calls that
    is a multiple of `workers` (no worker idles while another runs the last call: 9 calls on 2 threads
    took 5 rounds of calls, 10 take 5 too), and not below MIN_SPLIT unless `chunk` is (splitting small
    batches costs more than it saves)."""
    if workers <= 1:
        return min(chunk, max(rows, MIN_SPLIT))
    calls = -(-max(rows, 1) // chunk)
    calls = -(-calls // workers) * workers
    return max(-(-rows // calls), min(MIN_SPLIT, chunk))


def load_folder(folder: Path, threads: int = 1) -> tuple[dict[str, Material], dict[str, str]]:
    """Open every ``*.onnx`` in `folder` -> (materials by name, {name: reason} of files that failed)
    (`folder.open_folder` with `load_material`)."""
    return open_folder(folder, lambda path, data: load_material(path, threads, data))


class LocalMaterials:
    """Evaluate exported materials in this process.

    ``LocalMaterials("models/")`` loads every ``.onnx`` file there; files that fail to load are
    logged and listed in :attr:`errors`, the others still serve. `threads` (0: one per CPU) chunks
    of a batch run at once, each on a single-threaded session. With ``lazy=True`` only the folder is
    listed, and a material loads on its first use (a render loads only its scene's materials, when it
    binds them); a file that fails to load then raises ModelError there.
    """

    def __init__(self, folder: str | Path, threads: int = 0, chunk: int = DEFAULT_CHUNK, lazy: bool = False) -> None:
        if chunk < 1:
            raise ValueError(f"chunk must be at least 1 row, got {chunk}")
        self._models = ModelFolder(folder, lambda path, data: load_material(path, 1, data), lazy)
        self.folder = self._models.folder
        self.errors = self._models.errors
        """{name: reason} of the files that failed to load."""
        self.chunk = chunk
        self.threads = threads or os.cpu_count() or 1
        self._executor = ThreadPoolExecutor(self.threads, "neumip-ort") if self.threads > 1 else None

    def materials(self) -> list[str]:
        """Names served: loaded ones (lazy: every listed file that has not failed)."""
        return self._models.names()

    def loaded(self) -> list[str]:
        """Names of the materials loaded so far."""
        return self._models.loaded()

    def get(self, name: str) -> Material:
        return self._models.get(name)

    def sampling(self, material: str) -> C.SamplingLobe | None:
        """The sampling lobe the material's model declares (`contract.SamplingLobe`; None: the cosine)."""
        return self.get(material).sampling

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        """(N, 7) queries -> (N, 3) float32 RGB; query groups (N, 5 + 2 K) -> (N, 3 K). Raises
        QueryError for a bad buffer."""
        mat = self.get(material)
        queries = C.as_queries(queries, groups=True)
        per_call = max(self.chunk // C.group_lights(queries.shape[1]), 1)  # `chunk` counts answers
        return run_chunked(mat.run, queries, split_chunk(queries.shape[0], self.threads, per_call),
                           self._executor)
