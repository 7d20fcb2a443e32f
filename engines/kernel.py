"""In-kernel evaluation: a material's exported ONNX graph traced as drjit arithmetic.

The buffered path (`shading.NeuralShading` with `LocalMaterials` or a server) copies each bounce's
queries out of drjit, runs the ONNX graph, and copies the answers back. `KernelMaterials` instead
writes the same ``.onnx`` file's graph as drjit operations on the lanes themselves
(`client.onnx_kernel.LaneGraph`: each operator evaluated per lane, the weights literals of the
kernel, the textures flat arrays read with `dr.gather`). drjit compiles it, once per material and
number of lights (cached on disk like every drjit kernel), into one vectorised kernel per bounce that
also gathers the lanes' queries and scatters the answers: no buffers, no copies, no separate
inference engine. The graph is the one runtime definition of the material: ONNX Runtime, the server
and Triton run it too, and any ONNX material that follows the query contract (`core.contract`) with
the operators `onnx_ops.OPERATORS` lists renders in the kernel, whoever wrote it.

It computes what ONNX Runtime computes, in another order of float operations: answers agree with
ONNX Runtime's within the export's parity tolerance (1e-5 absolute plus 1e-4 relative;
tests/engines/test_kernel.py checks it on random queries of every model layout). Each lane is computed
alone, so an answer does not depend on the batch it is in, and light j of a query group is answered
with the bits of its single query.

As an `Evaluator` (`evaluate(material, queries)`), it also answers numpy query buffers and query
groups: how the server's ``kernel`` engine answers, and how its answers are compared with ONNX
Runtime's.

Needs drjit and onnx (the ``kernel`` extra), not Mitsuba. The arrays are those of a drjit backend
namespace chosen at construction: ``drjit.llvm.ad`` by default, the renderer passes its Mitsuba
variant's (`namespace_of(mi.Float)`; ``mi.Float`` in ``llvm_ad_rgb`` is ``drjit.llvm.ad.Float``).
"""

from __future__ import annotations

import gc
import importlib
import logging
import threading
from pathlib import Path
from types import ModuleType

import numpy as np

from neumip.core import contract as C
from neumip.core.modelfile import ModelError, read_model_file
from neumip.engines.folder import ModelFolder, read_model_bytes
from neumip.engines.llvm import ensure_llvm

ensure_llvm(required=False)  # drjit's LLVM backend loads libLLVM, and one older than 16 aborts the process
try:
    import drjit as dr
    import onnx

    from neumip.engines.onnx_kernel import LaneGraph
    from neumip.engines.onnx_ops import GraphError
except ImportError as exc:
    raise ImportError(f"{exc.name or exc} is not installed: pip install 'neumip[kernel]'") from exc

log = logging.getLogger(__name__)

Rgb = list  # three Floats: one answer per lane
Float = object
"""A drjit Float array type of the material's backend (`KernelMaterial.backend.Float`)."""

DEFAULT_BACKEND = "drjit.llvm.ad"


def namespace_of(array_type: type) -> ModuleType:
    """The drjit backend namespace of an array type: ``drjit.llvm.ad`` for ``mi.Float`` in
    ``llvm_ad_rgb``, ``drjit.cuda.ad`` in ``cuda_ad_rgb``."""
    return importlib.import_module(array_type.__module__)


DRJIT_LOCK = threading.RLock()
"""Held around every drjit operation of this module's materials - building one, evaluating it,
recording or replaying its frozen call, freeing its arrays - so that they run one at a time in this
process. drjit 1.5 deadlocks (holding the GIL: the whole process stops) or aborts when one thread
records a frozen function while another does other drjit work: four threads calling two materials
hung or crashed in 2 runs of 3, and a server thread loading a material while its engine thread
answered hung in 1 run of 3 (`tests/server/test_engine.py`). Re-entrant: `answers` runs inside `run`."""


def release_cached_memory() -> bool:
    """Hand drjit's cache of freed blocks back to the C heap (``drjit.flush_malloc_cache``), unless a drjit
    operation is under way (then nothing waits: False). drjit keeps the blocks of a call's arrays for the next
    call; after a server's largest calls they hold tens of MB that the heap's trim cannot return while drjit
    holds them."""
    if not DRJIT_LOCK.acquire(blocking=False):
        return False
    try:
        dr.flush_malloc_cache()
    finally:
        DRJIT_LOCK.release()
    return True


class KernelMaterial:
    """One material's graph, ready to be traced: `answers` writes its arithmetic on drjit arrays."""

    def __init__(self, path: str | Path, backend: ModuleType | None = None, data: bytes | None = None) -> None:
        """Read the model file `path` (from `data`, its bytes already read, if given); raises
        ModelError if it cannot be evaluated here. `backend`: drjit namespace of the arrays (default
        ``drjit.llvm.ad``)."""
        path = Path(path)
        data = read_model_bytes(path) if data is None else data
        self.file = read_model_file(path, data)
        """What the file declares (`core.modelfile.read_model_file`: it refuses a file of another
        contract version, bad metadata or non-finite weights)."""
        self.metadata = self.file.metadata
        """The model's metadata (a graph made by another tool may have none)."""
        self.config = self.file.config
        """The material's config from its metadata (resolution, levels...), for callers that need it
        (a report's scenes); None for a graph without it. The kernel itself reads only the graph."""
        self.sampling = self.file.sampling
        """The sampling lobe the model declares (`contract.SamplingLobe`; None: the cosine alone)."""
        try:
            model = onnx.load_model_from_string(data)
        except Exception as exc:  # onnx's parser raises its own types for a corrupt file
            raise ModelError(f"{path.name}: cannot load ONNX model: {exc}") from exc
        self.backend = backend or importlib.import_module(DEFAULT_BACKEND)
        """The drjit namespace whose arrays `answers` takes and gives (``drjit.llvm.ad``)."""
        self.name = path.stem
        with DRJIT_LOCK:
            try:
                self.graph = LaneGraph(model, self.backend)
                # a trial trace on one literal lane (nothing runs): a graph the interpreter cannot
                # follow is refused here, not in the middle of a render
                self.graph.trace(self.graph.tables, [self.backend.Float(0.0)] * C.QUERY_DIM)
            except GraphError as exc:
                raise ModelError(f"{path.name}: {exc}") from exc
            self._frozen = dr.freeze(self._trace)

    def __del__(self) -> None:
        """Free the drjit arrays under `DRJIT_LOCK`, whichever thread drops the material last (at
        interpreter exit the lock may already be gone: drjit frees them then)."""
        if DRJIT_LOCK is None:
            return
        with DRJIT_LOCK:
            self.__dict__.pop("graph", None)
            self.__dict__.pop("_frozen", None)

    @property
    def traces(self) -> int:
        """How often the arithmetic was traced: once per number of lights, unless a call's inputs
        changed the frozen function's layout (see `dr.freeze`)."""
        return self._frozen.n_recordings

    def answers(self, columns: list[Float]) -> list[Rgb]:
        """RGB of each light of the query groups whose columns (contract order: u, v, sigma, wi_x,
        wi_y, wo_x, wo_y, then wi_x, wi_y of each further light) are ``columns``, per light, evaluated
        as the graph evaluates a group (the export's graph: the offset and the lookup once, the
        decoder once per light). A lane with a non-finite column answers 0.

        The arithmetic is traced once per number of lights and replayed after (`dr.freeze`): a traced
        material is thousands of operations, whose tracing and code generation cost several
        milliseconds a call (a multi-bounce, multi-material render makes hundreds of calls).

        Calls run one at a time (`DRJIT_LOCK`), without Python's cyclic garbage collector: drjit
        aborts the process when an array made from numpy memory (this class's tables are) is freed
        while a frozen function records, as a collection of unreachable materials did."""
        with DRJIT_LOCK:
            collecting = gc.isenabled()
            gc.disable()
            try:
                flat = self._frozen(self.graph.tables, list(columns))
            except RuntimeError as exc:  # drjit's, around what the trace raised
                if isinstance(exc.__cause__, GraphError):
                    raise ModelError(f"{self.name}: {exc.__cause__}") from exc
                raise
            finally:
                if collecting:
                    gc.enable()
        return [flat[j:j + C.RGB_DIM] for j in range(0, len(flat), C.RGB_DIM)]

    def evaluate(self, queries: np.ndarray) -> np.ndarray:
        """(N, 7) queries -> (N, 3) float32 RGB; query groups (N, 5 + 2 K) -> (N, 3 K) (checked:
        `contract.as_queries`, then `run`)."""
        return self.run(C.as_queries(queries, groups=True))

    def run(self, queries: np.ndarray) -> np.ndarray:
        """`evaluate` of queries already checked (`contract.as_queries`: a C-contiguous (N, 5 + 2 K)
        float32 array of finite values), as a server's are when they reach the engine. All of it holds
        `DRJIT_LOCK`: the upload, the gathers and the read-back are drjit work too."""
        jit = self.backend
        if not len(queries):
            return np.zeros((0, C.RGB_DIM * C.group_lights(queries.shape[1])), C.DTYPE)
        if len(queries) == 1:  # drjit holds a one-lane array as a literal: the frozen trace would record (and
            return self.run(np.repeat(queries, 2, axis=0))[:1]  # compile) again; the row is computed alone
        with DRJIT_LOCK:
            # one upload, then the columns gathered in drjit memory (columns made from numpy arrays
            # each made the frozen trace record again, call after call)
            flat, width = jit.Float(queries.reshape(-1)), queries.shape[1]
            lane = dr.arange(jit.UInt32, len(queries))
            columns = [dr.gather(jit.Float, flat, lane * width + i) for i in range(width)]
            rgb = [c for answer in self.answers(columns) for c in answer]
            out = dr.zeros(jit.Float, len(queries) * len(rgb))  # the answers scattered row-major in the kernel
            for j, c in enumerate(rgb):
                dr.scatter(out, c, lane * len(rgb) + j)
            answers = np.array(out).reshape(len(queries), len(rgb))  # one copy out of drjit memory
            del flat, lane, columns, rgb, out  # freed under the lock too
        return answers

    def _trace(self, tables: list[Float], columns: list[Float]) -> list[Float]:
        """columns of query groups -> the lights' RGB, flat (`onnx_kernel.LaneGraph.trace`). Reads
        the tables only from ``tables`` (a frozen function's inputs)."""
        return self.graph.trace(tables, columns)


class KernelMaterials:
    """The materials of a model folder (``NAME.onnx``), evaluated as drjit kernels.

    Loads each file on first use. `kernel(name)` gives the `KernelMaterial` the renderer traces into
    its bounce; `evaluate` answers numpy queries (`contract.Evaluator`). ``backend``: the drjit
    namespace of the arrays (default ``drjit.llvm.ad``; a renderer passes its variant's).
    """

    def __init__(self, folder: str | Path, backend: ModuleType | None = None) -> None:
        self.backend = backend or importlib.import_module(DEFAULT_BACKEND)
        self._models = ModelFolder(folder, lambda path, data: KernelMaterial(path, self.backend, data), lazy=True)
        self.folder = self._models.folder
        self.errors = self._models.errors
        """{name: reason} of the files that failed to load."""

    def materials(self) -> list[str]:
        return self._models.names()

    def kernel(self, name: str) -> KernelMaterial:
        """The material `name` (loaded on first use); raises UnknownMaterial or ModelError."""
        return self._models.get(name)

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        """(N, 7) queries -> (N, 3) float32 RGB; query groups (N, 5 + 2 K) -> (N, 3 K)."""
        return self.kernel(material).evaluate(queries)

    def sampling(self, material: str) -> C.SamplingLobe | None:
        """The sampling lobe the material's model declares (`contract.SamplingLobe`; None: the cosine)."""
        return self.kernel(material).sampling
