"""In-process evaluation of exported materials with ONNX Runtime (no torch).

`LocalMaterials` loads every ``*.onnx`` in a folder (material name = file stem), checks each file's
contract version, and evaluates (N, 7) query buffers, or query groups (N, 5 + 2 K) (`contract`), in
chunks that run concurrently on a small thread pool (``InferenceSession.run`` releases the GIL), each
chunk on one ONNX Runtime thread.
How a batch is cut does not change the answers: the exported graph answers a query with the same
bits in any call (`neumip.training.export.graph`), so the thread count and chunk size only set the speed.
Measured in ``benchmarks/bench_inference.py`` (sections session and chunk).
"""

from __future__ import annotations

import json
import logging
import os
import re
import threading
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Generic, TypeVar

import numpy as np

from neumip.core import contract as C
from neumip.core.errors import NeumipError

log = logging.getLogger(__name__)

DEFAULT_CHUNK = 4096
"""Answers per ONNX Runtime call of `LocalMaterials` (rows of single queries; a group of K lights
counts K). With the default export graph, chunks of 2^11 to 2^12 rows ran about
10 % more queries per CPU second than chunks of 2^14 to 2^16 (the intermediates stay in cache), and a
single call on 2^20 rows was slowest (benchmarks/bench_inference.py, section chunk)."""

MIN_SPLIT = 2048
"""Batches below twice this many rows run as one call (splitting them costs more than it saves)."""

SESSION_CONFIG = {"session.intra_op.allow_spinning": "0"}
"""Session config entries: pool threads sleep instead of spinning between ops. On a machine shared
with other jobs spinning threads take cores the other threads need (2 intra-op threads ran at about
half the speed with spinning on under load)."""

T = TypeVar("T")

NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
"""What a material name may look like (also guards paths built from names)."""


class ModelError(NeumipError, RuntimeError):
    """A model file that cannot be used: unreadable, corrupt, or of another contract."""


class UnknownMaterial(NeumipError, KeyError):
    """A material name that is not loaded."""

    def __str__(self) -> str:
        return str(self.args[0])


def _onnxruntime():
    # ONNX Runtime >= 1.29 sends usage telemetry, and where it cannot write its cache (a container
    # user without a home) warns at start-up in raw ANSI colours; ORT_DISABLE_TELEMETRY=0 turns it back on
    os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
    try:
        import onnxruntime
    except ImportError as exc:  # pragma: no cover - base dependency
        raise ImportError("onnxruntime is missing: pip install neumip") from exc
    return onnxruntime


@dataclass
class Material:
    """One loaded material: its ONNX Runtime session and the metadata that travelled with it."""

    name: str
    path: Path
    session: object
    metadata: dict[str, str]
    bytes: int = 0
    """Size of the model file it was loaded from."""
    single_queries: bool = False
    """Whether the graph's input is fixed at 7 columns (a graph made by another tool that takes no
    query groups): each light of a group is then answered as its single query, as the in-kernel engine
    answers it."""

    @property
    def config(self) -> dict:
        return json.loads(self.metadata.get(C.META_CONFIG, "{}"))

    @property
    def sampling(self) -> C.SamplingLobe | None:
        """The sampling lobe the model declares (`contract.SamplingLobe`; None: the cosine alone)."""
        return C.sampling_lobe(self.metadata)

    def run(self, queries: np.ndarray) -> np.ndarray:
        """One call: validated (n, 5 + 2 K) float32 queries -> (n, 3 K) float32 RGB (`run_call`)."""
        if self.single_queries and queries.shape[1] != C.QUERY_DIM:
            return run_call(self.session, C.ungroup(queries)).reshape(queries.shape[0], -1)
        return run_call(self.session, queries)

    def info(self) -> dict:
        """What a listing shows of this material."""
        validation = self.metadata.get(C.META_VALIDATION)
        trim = self.metadata.get(C.META_TRIM)
        return {
            "name": self.name,
            "contract_version": self.metadata.get(C.META_CONTRACT),
            "description": self.metadata.get(C.META_DESCRIPTION, ""),
            "config": self.config,
            "validation": json.loads(validation) if validation else None,
            "trim": json.loads(trim) if trim else None,
            "sampling": self.sampling._asdict() if self.sampling else None,
            "bytes": self.bytes,
        }


def load_material(path: str | Path, threads: int = 0, data: bytes | None = None) -> Material:
    """Open one ``.onnx`` material (from `data`, the file's bytes already read, if given); raises
    ModelError if unreadable or of another contract version (`contract.version_problem`)."""
    ort = _onnxruntime()
    path = Path(path)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    for key, value in SESSION_CONFIG.items():
        opts.add_session_config_entry(key, value)
    try:
        source = data if data is not None else path.read_bytes()
        session = ort.InferenceSession(source, opts, providers=["CPUExecutionProvider"])
    except OSError as exc:
        raise ModelError(f"{path.name}: cannot read: {exc.strerror or exc}") from exc
    except Exception as exc:  # onnxruntime raises its own exception types for corrupt files
        raise ModelError(f"{path.name}: cannot load ONNX model: {exc}") from exc
    meta = dict(session.get_modelmeta().custom_metadata_map)
    problem = C.engine_problem(meta, str(path))
    if problem:
        raise ModelError(f"{path.name}: {problem}")
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if [i.name for i in inputs] != [C.ONNX_INPUT] or [o.name for o in outputs] != [C.ONNX_OUTPUT]:
        raise ModelError(f"{path.name}: graph must map '{C.ONNX_INPUT}' to '{C.ONNX_OUTPUT}'")
    if len(inputs[0].shape) != 2:
        raise ModelError(f"{path.name}: '{C.ONNX_INPUT}' must be 2-D, (N, {C.QUERY_DIM}) or (N, 5 + 2 K)")
    width = inputs[0].shape[1]
    if isinstance(width, int) and width != C.QUERY_DIM:
        raise ModelError(f"{path.name}: '{C.ONNX_INPUT}' must be (N, {C.QUERY_DIM}) or query groups "
                         f"(N, 5 + 2 K), not (N, {width})")
    return Material(path.stem, path, session, meta, len(source), single_queries=width == C.QUERY_DIM)


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
    (`open_folder` with `load_material`)."""
    return open_folder(folder, lambda path: load_material(path, threads))


def open_folder(folder: Path, load: Callable[[Path], T]) -> tuple[dict[str, T], dict[str, str]]:
    """``load`` every ``*.onnx`` in `folder` -> (loaded by name, {name: reason} of files that failed).

    A file fails when it cannot be loaded (`load` raises ModelError: corrupt, another contract
    version, wrong graph) or when its stem is not a material name (`NAME_PATTERN`); failures are
    logged, the others still load.
    """
    loaded: dict[str, T] = {}
    failed: dict[str, str] = {}
    for path in sorted(Path(folder).glob("*.onnx")):
        if not NAME_PATTERN.match(path.stem):
            failed[path.stem] = "file name is not a valid material name"
        else:
            try:
                loaded[path.stem] = load(path)
                continue
            except ModelError as exc:
                failed[path.stem] = str(exc)
        log.error("skipping %s: %s", path.name, failed[path.stem])
    return loaded, failed


class ModelFolder(Generic[T]):
    """The materials of a model folder (``NAME.onnx``), each opened once by ``load(path)``: every file
    at once (those that fail are logged and listed in `errors`), or with ``lazy=True`` each on its
    first `get` (a file that fails then raises ModelError there, and is listed in `errors`). Shared by
    the evaluators of a folder (`LocalMaterials`, the renderer's `KernelMaterials`)."""

    def __init__(self, folder: str | Path, load: Callable[[Path], T], lazy: bool = False) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise FileNotFoundError(f"model folder {self.folder} does not exist")
        self._load = load
        self._lock = threading.Lock()
        if lazy:
            self._loaded, self.errors = {}, {}
            self._listed = sorted(p.stem for p in self.folder.glob("*.onnx") if NAME_PATTERN.match(p.stem))
        else:
            self._loaded, self.errors = open_folder(self.folder, load)
            self._listed = sorted(self._loaded)

    def names(self) -> list[str]:
        """Names served: loaded ones (lazy: every listed file that has not failed)."""
        return sorted(set(self._listed) - set(self.errors))

    def loaded(self) -> list[str]:
        """Names of the materials loaded so far."""
        return sorted(self._loaded)

    def get(self, name: str) -> T:
        """Material `name`, loaded on first use; raises UnknownMaterial or ModelError."""
        material = self._loaded.get(name)
        if material is not None:
            return material
        if name not in self.names():
            known = ", ".join(self.names()) or "none"
            raise UnknownMaterial(f"unknown material {name!r} (served: {known})")
        with self._lock:  # lazy: load once, whichever thread asks first
            if name not in self._loaded:
                try:
                    self._loaded[name] = self._load(self.folder / f"{name}.onnx")
                except ModelError as exc:
                    self.errors[name] = str(exc)
                    raise
                log.info("loaded %s on first use (as %s)", name, type(self._loaded[name]).__name__)
            return self._loaded[name]


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
        self._models = ModelFolder(folder, lambda path: load_material(path, threads=1), lazy)
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
