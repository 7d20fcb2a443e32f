"""Dynamic batching: decode -> **batch** -> **predict** -> **unbatch** -> encode.

Handlers decode and validate a request, then `Batcher.evaluate` cuts its (N, 7) queries, or (N, 5 + 2 K)
query groups, into pieces of at most the engine's ``chunk_rows`` answers (``chunk_rows // K`` groups;
large requests are split: one ONNX Runtime call on 10^6 rows is several times slower than the same rows
in cache-sized chunks) and queues them. A pool of worker threads, the engine's ``workers`` (ONNX
Runtime: one per core by default; the drjit kernel engine: one, each call using every core), is the
executor: each worker takes the oldest queued pieces of one material and width, merging
consecutive small ones into one call of up to ``chunk_rows`` answers and
waiting at most ``max_wait_ms`` (counted from the oldest piece's arrival) for a call to fill - only
while other requests are being decoded (`Batcher.receiving`), never for a body still arriving: a lone
request, or the tail of a lone large one, runs at once - then runs the call and copies each piece's
rows back. Workers pull work themselves, so consecutive chunks of a large request run back to back
without a round trip through the event loop; the loop hears back once per request. `predict` is the
only function that touches the engine (`neumip.server.engine`).

Answers are checked: a model that answers NaN or Inf for some row fails that request with a 500
naming the material (counted in ``neumip_nonfinite_answers_total``), never a silent NaN.

Only pieces of the same width share a call (one queue per material and width).

Merging and splitting keep answers bit-identical to evaluating each request on its own, in one call or
in process (`neumip.engines.local`): the exported graph answers a row with the same bits wherever it
sits in a call and however many rows the call has (`neumip.training.export.graph`), and so does the kernel
engine (each row is computed alone), so pieces go into calls in any cut.

How many rows may be queued is decided before a request gets here (`neumip.server.admission`).
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from neumip.core import contract as C
from neumip.engines.local import Material

from neumip.server.engine import Engine
from neumip.server.errors import ApiError
from neumip.server.metrics import Metrics
from neumip.server.model_stats import ModelStats
from neumip.server.settings import Settings

log = logging.getLogger(__name__)


def predict(material: Material, queries: np.ndarray) -> np.ndarray:
    """One engine call: (n, 5 + 2 K) float32 contiguous queries -> (n, 3 K) float32 RGB (`Material.run`)."""
    return material.run(queries)


@dataclass
class _Job:
    """One request being evaluated: its answer buffer and how many of its rows are not answered yet."""

    future: asyncio.Future
    out: np.ndarray  # (N, 3 K) float32, filled piece by piece
    rows_left: int  # rows not yet answered (changed under the batcher's lock)
    error: ApiError | None = None


@dataclass
class _Piece:
    """At most ``chunk_rows`` answers' worth of consecutive rows of one job."""

    job: _Job
    queries: np.ndarray  # (n, 5 + 2 K) float32 view into the request's queries
    out: np.ndarray  # (n, 3 K) float32 view into the job's answer buffer
    start: int = 0  # index of the piece's first row in the request
    arrived: float = 0.0  # time.monotonic() when queued
    order: int = 0  # global arrival order (first in, first out across materials)

    @property
    def rows(self) -> int:
        return self.queries.shape[0]


@dataclass
class _MaterialQueue:
    """Pieces of one width waiting for one material, oldest first."""

    material: Material
    chunk: int
    """Most rows of one call: ``chunk_rows // K`` groups of K lights."""
    pieces: deque = field(default_factory=deque)
    rows: int = 0


def group_chunk(chunk_rows: int, width: int) -> int:
    """Rows of `width` columns in a call of at most `chunk_rows` answers (at least one)."""
    return max(chunk_rows // C.group_lights(width), 1)


def split(queries: np.ndarray, out: np.ndarray, chunk: int, job: _Job) -> list[_Piece]:
    """Cut (N, 5 + 2 K) queries and their (N, 3 K) answer buffer into pieces of at most `chunk` rows."""
    n = queries.shape[0]
    return [_Piece(job, queries[lo : lo + chunk], out[lo : lo + chunk], lo) for lo in range(0, n, chunk)]


def take(queue: _MaterialQueue, chunk: int) -> list[_Piece]:
    """Pieces first-in first-out while they fit in `chunk` rows; a batch holds at least one piece."""
    batch, rows = [], 0
    while queue.pieces and (not batch or rows + queue.pieces[0].rows <= chunk):
        batch.append(queue.pieces.popleft())
        rows += batch[-1].rows
    queue.rows -= rows
    return batch


def run_batch(material: Material, pieces: list[_Piece]) -> int:
    """Merge pieces, predict once, and copy each piece's rows of the answer back (unbatch).

    Runs in a worker thread; returns the rows evaluated. Check the answers with `first_nonfinite`.
    """
    if len(pieces) == 1:
        queries = pieces[0].queries  # (n, 5 + 2 K): a row slice of a C-contiguous buffer, no copy
    else:
        queries = np.concatenate([p.queries for p in pieces])  # (sum n, 5 + 2 K): one width per queue
    rgb = predict(material, queries)  # (sum n, 3 K)
    lo = 0
    for piece in pieces:
        piece.out[...] = rgb[lo : lo + piece.rows]
        lo += piece.rows
    return lo


class _Arrival:
    """A request being decoded (`Batcher.receiving`): batches wait for it until it submits its rows."""

    def __init__(self, batcher: "Batcher") -> None:
        self.batcher = batcher
        self.open = True  # still counted as on its way (changed under the batcher's lock)

    def submit(self, name: str, queries: np.ndarray, out: np.ndarray | None = None,
               material: Material | None = None) -> asyncio.Future:
        """`Batcher.submit` of this request's rows; it stops being waited for in the same step."""
        return self.batcher.submit(name, queries, out, arrival=self, material=material)


def first_nonfinite(piece: _Piece) -> str | None:
    """Where the piece's answer holds NaN or Inf ("row i of the request is nan"), None if nowhere."""
    finite = np.isfinite(piece.out)  # (n, 3 K)
    if finite.all():
        return None
    row, col = np.argwhere(~finite)[0]
    light = f" of light {col // C.RGB_DIM + 1}" if piece.out.shape[1] > C.RGB_DIM else ""
    return (f"query row {piece.start + row} of the request answered {piece.out[row, col]} "
            f"({C.RGB_FIELDS[col % C.RGB_DIM]}{light})")


class Batcher:
    """Batches evaluation requests onto the engine's materials (see the module docstring)."""

    def __init__(self, materials: dict[str, Material], settings: Settings, metrics: Metrics, engine: Engine) -> None:
        self.settings = settings
        self.metrics = metrics
        self.engine = engine
        self.stats = ModelStats()  # per-material statistics in Triton's shape (GET /v2/models/{name}/stats)
        self.workers = self.engine.workers
        self.chunk_rows = self.engine.chunk_rows
        self._materials = materials  # name -> Material, read at submit (a registry may change it)
        # one queue per loaded model object and query width while it has pieces: a swapped model's
        # queued pieces still run on the model they were submitted to, a drained queue lets its model
        # go, and a call holds rows of one width
        self._queues: dict[tuple[int, int], _MaterialQueue] = {}
        self._cond = threading.Condition()
        self._order = itertools.count()
        self._closing = False
        self._threads: list[threading.Thread] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._receiving = 0  # requests being decoded (changed under the lock)

    # --- life cycle -------------------------------------------------------------------------
    def start(self) -> None:
        """Start the worker threads (call inside the running event loop that awaits answers)."""
        self._loop = asyncio.get_running_loop()
        self.engine.start()
        self._threads = [
            threading.Thread(target=self._work, name=f"{self.engine.name}-{i}", daemon=True)
            for i in range(self.workers)
        ]
        for thread in self._threads:
            thread.start()
        log.info(
            "batcher: %d %s worker(s), chunks of %d rows, merge wait %.1f ms",
            self.workers, self.engine.name, self.chunk_rows, self.settings.max_wait_ms,
        )

    async def close(self) -> None:
        """Let the workers finish what is queued, then stop them."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        for thread in self._threads:
            await asyncio.to_thread(thread.join)

    # --- batch (event loop side) --------------------------------------------------------------
    @contextmanager
    def receiving(self) -> Iterator[_Arrival]:
        """Around decoding a request whose body is in: while any request is being decoded, a batch that
        is not full waits (up to ``max_wait_ms``) for its rows; with none, queued rows run at once.
        A body still arriving holds nothing: a slow uploader must not slow everyone else.

        Yields the request's `_Arrival`: its ``submit`` queues the rows and ends the wait in one step,
        so a batch waiting for them takes them, and the request never waits for itself."""
        arrival = _Arrival(self)
        with self._cond:
            self._receiving += 1
        try:
            yield arrival
        finally:
            with self._cond:
                self._arrived(arrival)

    def _arrived(self, arrival: _Arrival | None) -> None:
        """Under the lock: `arrival` is no longer on its way; waiting batches go once none is."""
        if arrival is not None and arrival.open:
            arrival.open = False
            self._receiving -= 1
            if not self._receiving:
                self._cond.notify_all()

    def submit(
        self, name: str, queries: np.ndarray, out: np.ndarray | None = None, arrival: _Arrival | None = None,
        material: Material | None = None,
    ) -> asyncio.Future:
        """Queue validated (N, 7) float32 queries, or (N, 5 + 2 K) query groups, for material `name`
        (the loaded `material`, default: the one `name` maps to now); the future's result is their
        (N, 3 K) float32 RGB, written into `out` ((N, 3 K) float32, e.g. a view into the response body)
        when given, else into a new array; its exception an ApiError (500) if the model failed.
        `arrival`: the request's `receiving` (use ``arrival.submit``)."""
        n, width = queries.shape
        answers = C.RGB_DIM * C.group_lights(width)
        if out is None:
            out = np.empty((n, answers), dtype=C.DTYPE)
        elif out.shape != (n, answers) or out.dtype != C.DTYPE:
            raise ValueError(f"answer buffer must be ({n}, {answers}) {C.DTYPE}, got {out.shape} {out.dtype}")
        job = _Job(self._loop.create_future(), out, n)
        self.stats.track(name, job.future, n)
        self.metrics.request_rows.observe(n)
        if n == 0:
            job.future.set_result(out)
        material = material or self._materials[name]
        chunk = group_chunk(self.chunk_rows, width)
        pieces = split(queries, out, chunk, job)
        now = time.monotonic()
        with self._cond:
            queue = self._queues.setdefault((id(material), width), _MaterialQueue(material, chunk))
            for piece in pieces:
                piece.arrived, piece.order = now, next(self._order)
                queue.pieces.append(piece)
            queue.rows += n
            self._cond.notify(len(pieces))
            self._arrived(arrival)
        return job.future

    async def evaluate(self, name: str, queries: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """`submit`, then await the answer."""
        return await asyncio.shield(self.submit(name, queries, out))

    @staticmethod
    def _finish(job: _Job) -> None:
        """On the event loop: hand the finished job's answer (or error) to its handler."""
        if job.future.done():
            return
        if job.error is not None:
            job.future.set_exception(job.error)
        else:
            job.future.set_result(job.out)

    # --- predict and unbatch (worker threads) --------------------------------------------------
    def _next_batch(self) -> tuple[Material, list[_Piece]] | None:
        """Under the lock: wait for work, then the batch to run; None once closing and drained."""
        wait_s = self.settings.max_wait_ms / 1000.0
        while True:
            ready = [(q.pieces[0], key, q) for key, q in self._queues.items() if q.pieces]
            if not ready:
                if self._closing:
                    return None
                self._cond.wait()
                continue
            first, key, queue = min(ready, key=lambda pkq: pkq[0].order)
            remaining = first.arrived + wait_s - time.monotonic()
            if queue.rows >= queue.chunk or remaining <= 0 or not self._receiving or self._closing:
                batch = take(queue, queue.chunk)
                if not queue.pieces:
                    del self._queues[key]
                return queue.material, batch
            self._cond.wait(remaining)  # more pieces may arrive to fill the call

    def _nonfinite(self, name: str, piece: _Piece) -> ApiError | None:
        """The error of a piece whose answer holds NaN or Inf (counted and logged), else None."""
        where = first_nonfinite(piece)
        if where is None:
            return None
        self.metrics.nonfinite.labels(name).inc()
        log.error("material %s answered NaN/Inf: %s", name, where)
        return ApiError(
            500,
            f"material {name!r} answered a non-finite value ({where}): the model is broken for these "
            "inputs, so no answer is given",
        )

    def _work(self) -> None:
        """A worker thread: take a batch, run it, report finished jobs to the event loop."""
        while True:
            with self._cond:
                work = self._next_batch()
            if work is None:
                return
            self._run(*work)
            del work  # nothing of the batch (a request's body, its answers) is kept while the worker waits

    def _run(self, material: Material, batch: list[_Piece]) -> None:
        """Run one batch and hand its finished jobs to the event loop."""
        start = time.perf_counter()
        error = None
        try:
            rows = run_batch(material, batch)
        except Exception as exc:  # a model fault: every request in the batch fails with it
            log.exception("%s failed on material %s", self.engine.name, material.name)
            error = ApiError(500, f"evaluating material {material.name!r} failed: {exc}")
        else:
            self.metrics.predict_seconds.observe(time.perf_counter() - start)
            self.metrics.batch_rows.observe(rows)
            self.metrics.batch_requests.observe(len(batch))
            self.metrics.rows.labels(material.name).inc(rows)
            self.stats.executed(material.name, rows, time.perf_counter() - start, [p.arrived for p in batch])
        finished = []
        with self._cond:
            for piece in batch:
                job = piece.job
                job.error = job.error or error or self._nonfinite(material.name, piece)
                job.rows_left -= piece.rows
                if job.rows_left == 0:
                    finished.append(job)
        for job in finished:
            self._loop.call_soon_threadsafe(self._finish, job)
