"""Dynamic batching: decode -> **batch** -> **predict** -> **unbatch** -> encode.

Handlers decode and validate a request, then `Batcher.evaluate` cuts its (N, 7) queries into pieces of
at most ``chunk_rows`` rows (large requests are split: one ONNX Runtime call on 10^6 rows is several
times slower than the same rows in cache-sized chunks) and queues them. A pool of worker threads, one
per ONNX Runtime worker (default: one per core), is the executor: each worker takes the oldest queued
pieces of one material, merging consecutive small ones into one call of up to ``chunk_rows`` rows and
waiting at most ``max_wait_ms`` (counted from the oldest piece's arrival) for a call to fill - only
while other requests are being received (`Batcher.receiving`): a lone request, or the tail of a lone
large one, runs at once - then runs the call and copies each piece's rows back. Workers pull work themselves, so consecutive chunks of a large
request run back to back without a round trip through the event loop; the loop hears back once per
request. `predict` is the only function that touches ONNX Runtime.

Merging and splitting keep answers bit-identical to evaluating each request on its own, in one call or
in process (`neumip.client.local`): the exported graph answers a row with the same bits wherever it
sits in a call and however many rows the call has (`neumip.training.export`), so pieces go into
calls in any cut.

Admission is bounded in rows: a request that would take the rows admitted and not yet answered above
``max_queue_rows`` is refused at once with `QueueFull` (503 + Retry-After), never queued to time out.
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

from neumip.client import contract as C
from neumip.client.local import Material

from .errors import ApiError, QueueFull
from .metrics import Metrics
from .model_stats import ModelStats
from .settings import Settings

log = logging.getLogger(__name__)


def predict(session, queries: np.ndarray) -> np.ndarray:
    """One ONNX Runtime call: (n, 7) float32 contiguous queries -> (n, 3) float32 RGB."""
    return session.run([C.ONNX_OUTPUT], {C.ONNX_INPUT: queries})[0]


@dataclass
class _Job:
    """One request being evaluated: its answer buffer and how many of its rows are not answered yet."""

    future: asyncio.Future
    out: np.ndarray  # (N, 3) float32, filled piece by piece
    queue: _MaterialQueue
    rows_left: int  # rows not yet answered, queued or not (changed under the batcher's lock)
    queued: int = 0  # rows queued so far (rows 0..queued of the request)
    error: ApiError | None = None

    @property
    def rows(self) -> int:
        return self.out.shape[0]


@dataclass
class _Piece:
    """At most ``chunk_rows`` consecutive rows of one job."""

    job: _Job
    queries: np.ndarray  # (n, 7) float32 view into the request's queries
    out: np.ndarray  # (n, 3) float32 view into the job's answer buffer
    arrived: float = 0.0  # time.monotonic() when queued
    order: int = 0  # global arrival order (first in, first out across materials)

    @property
    def rows(self) -> int:
        return self.queries.shape[0]


@dataclass
class _MaterialQueue:
    """Pieces waiting for one material, oldest first."""

    material: Material
    pieces: deque = field(default_factory=deque)
    rows: int = 0


def split(queries: np.ndarray, out: np.ndarray, chunk: int, job: _Job) -> list[_Piece]:
    """Cut (N, 7) queries and their (N, 3) answer buffer into pieces of at most `chunk` rows."""
    n = queries.shape[0]
    return [_Piece(job, queries[lo : lo + chunk], out[lo : lo + chunk]) for lo in range(0, n, chunk)]


def take(queue: _MaterialQueue, chunk: int) -> list[_Piece]:
    """Pieces first-in first-out while they fit in `chunk` rows; a batch holds at least one piece."""
    batch, rows = [], 0
    while queue.pieces and (not batch or rows + queue.pieces[0].rows <= chunk):
        batch.append(queue.pieces.popleft())
        rows += batch[-1].rows
    queue.rows -= rows
    return batch


def run_batch(session, pieces: list[_Piece]) -> int:
    """Merge pieces, predict once, and copy each piece's rows of the answer back (unbatch).

    Runs in a worker thread; returns the rows evaluated.
    """
    if len(pieces) == 1:
        queries = pieces[0].queries  # (n, 7): a row slice of a C-contiguous buffer, no copy
    else:
        queries = np.concatenate([p.queries for p in pieces])  # (sum n, 7)
    rgb = predict(session, queries)  # (sum n, 3)
    lo = 0
    for piece in pieces:
        piece.out[...] = rgb[lo : lo + piece.rows]
        lo += piece.rows
    return lo


class Batcher:
    """Batches evaluation requests onto ONNX Runtime sessions (see the module docstring)."""

    def __init__(self, materials: dict[str, Material], settings: Settings, metrics: Metrics) -> None:
        self.settings = settings
        self.metrics = metrics
        self.stats = ModelStats()  # per-material statistics in Triton's shape (GET /v2/models/{name}/stats)
        self.workers = settings.workers()
        self._queues = {name: _MaterialQueue(material) for name, material in materials.items()}
        self._cond = threading.Condition()
        self._order = itertools.count()
        self._closing = False
        self._threads: list[threading.Thread] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._admitted_rows = 0  # touched on the event loop only
        self._admitted_requests = 0
        self._receiving = 0  # requests being read and decoded (changed under the lock)

    # --- life cycle -------------------------------------------------------------------------
    def start(self) -> None:
        """Start the worker threads (call inside the running event loop that awaits answers)."""
        self._loop = asyncio.get_running_loop()
        self._threads = [
            threading.Thread(target=self._work, name=f"onnxruntime-{i}", daemon=True) for i in range(self.workers)
        ]
        for thread in self._threads:
            thread.start()
        log.info(
            "batcher: %d ONNX Runtime worker(s), chunks of %d rows, merge wait %.1f ms",
            self.workers, self.settings.chunk_rows, self.settings.max_wait_ms,
        )

    async def close(self) -> None:
        """Let the workers finish what is queued, then stop them."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        for thread in self._threads:
            await asyncio.to_thread(thread.join)

    @property
    def admitted_rows(self) -> int:
        """Rows admitted and not yet answered."""
        return self._admitted_rows

    # --- batch (event loop side) --------------------------------------------------------------
    @contextmanager
    def receiving(self) -> Iterator[None]:
        """Around reading and decoding a request: while any request is on its way, a batch that is
        not full waits (up to ``max_wait_ms``) for it; with none, a queued request runs at once."""
        with self._cond:
            self._receiving += 1
        try:
            yield
        finally:
            with self._cond:
                self._receiving -= 1
                if not self._receiving:  # nothing more is coming: waiting batches go now
                    self._cond.notify_all()

    async def evaluate(self, name: str, queries: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Validated (N, 7) float32 queries for material `name` -> (N, 3) float32 RGB.

        The workers write the answer into `out` ((N, 3) float32, e.g. a view into the response
        body) when given, else into a new array. Raises QueueFull when admitting N more rows would
        pass ``max_queue_rows``.
        """
        job = self.submit(name, queries.shape[0], out)
        self.queue(job, queries)
        return await self.result(job)

    def submit(self, name: str, n: int, out: np.ndarray | None = None) -> _Job:
        """Admit a request of `n` rows for material `name` before its rows are all there; they follow
        in order with `queue`, then `result` awaits the answer (or `abandon` gives the request up).

        Raises QueueFull when admitting `n` more rows would pass ``max_queue_rows``.
        """
        if self._admitted_rows + n > self.settings.max_queue_rows:
            self.metrics.rejected.inc()
            raise QueueFull(
                f"server busy: {self._admitted_rows} rows queued, {n} more would pass the limit of "
                f"{self.settings.max_queue_rows}; retry after {self.settings.retry_after_s} s",
                self.settings.retry_after_s,
            )
        if out is None:
            out = np.empty((n, C.RGB_DIM), dtype=C.DTYPE)
        elif out.shape != (n, C.RGB_DIM) or out.dtype != C.DTYPE:
            raise ValueError(f"answer buffer must be ({n}, {C.RGB_DIM}) {C.DTYPE}, got {out.shape} {out.dtype}")
        job = _Job(self._loop.create_future(), out, self._queues[name], n)
        self._admit(n, +1)
        self.stats.track(name, job.future, n)
        self.metrics.request_rows.observe(n)
        if n == 0:
            job.future.set_result(out)
        return job

    def queue(self, job: _Job, queries: np.ndarray) -> None:
        """Queue the job's next validated (m, 7) float32 rows: rows ``queued .. queued + m`` of its request."""
        lo, m = job.queued, queries.shape[0]
        if lo + m > job.rows:
            raise ValueError(f"{lo + m} rows queued for a request of {job.rows}")
        pieces = split(queries, job.out[lo : lo + m], self.settings.chunk_rows, job)
        now = time.monotonic()
        with self._cond:
            job.queued += m
            for piece in pieces:
                piece.arrived, piece.order = now, next(self._order)
                job.queue.pieces.append(piece)
            job.queue.rows += m
            self._cond.notify(len(pieces))

    async def result(self, job: _Job) -> np.ndarray:
        """The job's (N, 3) answer once its N rows are queued and evaluated."""
        try:
            return await asyncio.shield(job.future)
        finally:
            self._release(job)

    def abandon(self, job: _Job) -> None:
        """Give up a job whose remaining rows will never come (its body turned out bad): the rows
        already queued still run and count as admitted until they are done."""
        with self._cond:
            job.rows_left -= job.rows - job.queued
            job.queued = job.rows
            done = job.rows_left == 0
        if done:
            self._finish(job)
        self._release(job)

    def _release(self, job: _Job) -> None:
        """Un-admit the job's rows now if it is done, else when it is (a cancelled handler's pieces still run)."""
        if job.future.done():
            self._admit(job.rows, -1)
        else:
            job.future.add_done_callback(lambda _: self._admit(job.rows, -1))

    def _admit(self, rows: int, sign: int) -> None:
        self._admitted_rows += sign * rows
        self._admitted_requests += sign
        self.metrics.queue_rows.set(self._admitted_rows)
        self.metrics.queue_requests.set(self._admitted_requests)

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
        chunk, wait_s = self.settings.chunk_rows, self.settings.max_wait_ms / 1000.0
        while True:
            ready = [(q.pieces[0], q) for q in self._queues.values() if q.pieces]
            if not ready:
                if self._closing:
                    return None
                self._cond.wait()
                continue
            first, queue = min(ready, key=lambda pq: pq[0].order)
            remaining = first.arrived + wait_s - time.monotonic()
            if queue.rows >= chunk or remaining <= 0 or not self._receiving or self._closing:
                return queue.material, take(queue, chunk)
            self._cond.wait(remaining)  # more pieces may arrive to fill the call

    def _work(self) -> None:
        """A worker thread: take a batch, run it, report finished jobs to the event loop."""
        while True:
            with self._cond:
                work = self._next_batch()
            if work is None:
                return
            material, batch = work
            start = time.perf_counter()
            error = None
            try:
                rows = run_batch(material.session, batch)
            except Exception as exc:  # a model fault: every request in the batch fails with it
                log.exception("ONNX Runtime failed on material %s", material.name)
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
                    job.error = job.error or error
                    job.rows_left -= piece.rows
                    if job.rows_left == 0:
                        finished.append(job)
            for job in finished:
                self._loop.call_soon_threadsafe(self._finish, job)
