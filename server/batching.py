"""Dynamic batching: decode -> **batch** -> **predict** -> **unbatch** -> encode.

Handlers decode and validate a request, then `Batcher.evaluate` cuts its (N, 7) queries into pieces of
at most ``chunk_rows`` rows (large requests are split: one ONNX Runtime call on 10^6 rows is several
times slower than the same rows in cache-sized chunks). Each material has a collector task that takes
pieces first-in first-out and merges consecutive small ones into one call of up to ``chunk_rows``
rows, waiting at most ``max_wait_ms`` for more to arrive. Calls run in a dedicated thread pool with
one thread per ONNX Runtime worker; `predict` is the only function that touches ONNX Runtime.

Admission is bounded in rows: a request that would take the rows admitted and not yet answered above
``max_queue_rows`` is refused at once with `QueueFull` (503 + Retry-After), never queued to time out.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from neumip.client import contract as C
from neumip.client.local import Material

from .errors import ApiError, QueueFull
from .metrics import Metrics
from .settings import Settings

log = logging.getLogger(__name__)


def predict(session, queries: np.ndarray) -> np.ndarray:
    """One ONNX Runtime call: (n, 7) float32 contiguous queries -> (n, 3) float32 RGB."""
    return session.run([C.ONNX_OUTPUT], {C.ONNX_INPUT: queries})[0]


@dataclass
class _Job:
    """One request being evaluated: its answer buffer and how many pieces are still out."""

    future: asyncio.Future
    out: np.ndarray  # (N, 3) float32, filled piece by piece
    pieces_left: int


@dataclass
class _Piece:
    """At most ``chunk_rows`` consecutive rows of one job."""

    job: _Job
    queries: np.ndarray  # (n, 7) float32 view into the request's queries
    out: np.ndarray  # (n, 3) float32 view into the job's answer buffer

    @property
    def rows(self) -> int:
        return self.queries.shape[0]


@dataclass
class _MaterialQueue:
    """Pieces waiting for one material, and the event that wakes its collector."""

    material: Material
    pieces: deque = field(default_factory=deque)
    arrived: asyncio.Event = field(default_factory=asyncio.Event)
    rows: int = 0
    task: asyncio.Task | None = None


def split(queries: np.ndarray, out: np.ndarray, chunk: int, job: _Job) -> list[_Piece]:
    """Cut (N, 7) queries and their (N, 3) answer buffer into pieces of at most `chunk` rows."""
    n = queries.shape[0]
    return [_Piece(job, queries[lo : lo + chunk], out[lo : lo + chunk]) for lo in range(0, n, chunk)]


def run_batch(session, pieces: list[_Piece]) -> int:
    """Merge pieces, predict once, and copy each piece's rows of the answer back (unbatch).

    Runs in an executor thread; returns the rows evaluated.
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
        self.workers = settings.workers()
        self.executor = ThreadPoolExecutor(self.workers, thread_name_prefix="onnxruntime")
        self._materials = materials
        self._queues: dict[str, _MaterialQueue] = {}
        self._slots: asyncio.Semaphore | None = None
        self._admitted_rows = 0
        self._admitted_requests = 0
        self._running: set[asyncio.Task] = set()

    # --- life cycle -------------------------------------------------------------------------
    def start(self) -> None:
        """Start one collector per material (call inside the running event loop)."""
        self._slots = asyncio.Semaphore(self.workers)
        for name, material in self._materials.items():
            queue = _MaterialQueue(material)
            queue.task = asyncio.create_task(self._collect(queue), name=f"collect-{name}")
            self._queues[name] = queue
        log.info(
            "batcher: %d ONNX Runtime worker(s), chunks of %d rows, merge wait %.1f ms",
            self.workers, self.settings.chunk_rows, self.settings.max_wait_ms,
        )

    async def close(self) -> None:
        """Finish the calls under way, stop the collectors and the executor."""
        if self._running:
            await asyncio.gather(*self._running, return_exceptions=True)
        for queue in self._queues.values():
            if queue.task is not None:
                queue.task.cancel()
        await asyncio.gather(*(q.task for q in self._queues.values() if q.task), return_exceptions=True)
        self.executor.shutdown(wait=True)

    @property
    def admitted_rows(self) -> int:
        """Rows admitted and not yet answered."""
        return self._admitted_rows

    # --- batch ------------------------------------------------------------------------------
    async def evaluate(self, name: str, queries: np.ndarray) -> np.ndarray:
        """Validated (N, 7) float32 queries for material `name` -> (N, 3) float32 RGB.

        Raises QueueFull when admitting N more rows would pass ``max_queue_rows``.
        """
        n = queries.shape[0]
        if self._admitted_rows + n > self.settings.max_queue_rows:
            self.metrics.rejected.inc()
            raise QueueFull(
                f"server busy: {self._admitted_rows} rows queued, {n} more would pass the limit of "
                f"{self.settings.max_queue_rows}; retry after {self.settings.retry_after_s} s",
                self.settings.retry_after_s,
            )
        queue = self._queues[name]
        out = np.empty((n, C.RGB_DIM), dtype=C.DTYPE)
        job = _Job(asyncio.get_running_loop().create_future(), out, 0)
        pieces = split(queries, out, self.settings.chunk_rows, job)
        job.pieces_left = len(pieces)
        self._admit(n, +1)
        try:
            queue.pieces.extend(pieces)
            queue.rows += n
            queue.arrived.set()
            self.metrics.request_rows.observe(n)
            return await asyncio.shield(job.future)
        finally:
            if not job.future.done():  # the handler was cancelled: the pieces still run
                job.future.add_done_callback(lambda _: self._admit(n, -1))
            else:
                self._admit(n, -1)

    def _admit(self, rows: int, sign: int) -> None:
        self._admitted_rows += sign * rows
        self._admitted_requests += sign
        self.metrics.queue_rows.set(self._admitted_rows)
        self.metrics.queue_requests.set(self._admitted_requests)

    async def _collect(self, queue: _MaterialQueue) -> None:
        """Forever: wait for pieces and a free worker, merge what is waiting, launch one call."""
        chunk, wait_s = self.settings.chunk_rows, self.settings.max_wait_ms / 1000.0
        while True:
            while not queue.pieces:
                queue.arrived.clear()
                await queue.arrived.wait()
            await self._slots.acquire()
            deadline = time.perf_counter() + wait_s
            while queue.rows < chunk and (remaining := deadline - time.perf_counter()) > 0:
                queue.arrived.clear()
                try:
                    await asyncio.wait_for(queue.arrived.wait(), remaining)
                except asyncio.TimeoutError:
                    break
            batch = self._take(queue, chunk)
            task = asyncio.create_task(self._run(queue.material, batch))
            self._running.add(task)
            task.add_done_callback(self._running.discard)

    @staticmethod
    def _take(queue: _MaterialQueue, chunk: int) -> list[_Piece]:
        """Pop the first piece and the next ones while the batch stays within `chunk` rows."""
        batch = [queue.pieces.popleft()]
        rows = batch[0].rows
        while queue.pieces and rows + queue.pieces[0].rows <= chunk:
            piece = queue.pieces.popleft()
            batch.append(piece)
            rows += piece.rows
        queue.rows -= rows
        return batch

    # --- predict and unbatch ----------------------------------------------------------------
    async def _run(self, material: Material, batch: list[_Piece]) -> None:
        loop = asyncio.get_running_loop()
        start = time.perf_counter()
        try:
            rows = await loop.run_in_executor(self.executor, run_batch, material.session, batch)
        except Exception as exc:  # a model fault: every request in the batch fails with it
            log.exception("ONNX Runtime failed on material %s", material.name)
            for piece in batch:
                if not piece.job.future.done():
                    piece.job.future.set_exception(
                        ApiError(500, f"evaluating material {material.name!r} failed: {exc}")
                    )
            return
        finally:
            self._slots.release()
        self.metrics.predict_seconds.observe(time.perf_counter() - start)
        self.metrics.batch_rows.observe(rows)
        self.metrics.batch_requests.observe(len(batch))
        self.metrics.rows.labels(material.name).inc(rows)
        for piece in batch:
            job = piece.job
            job.pieces_left -= 1
            if job.pieces_left == 0 and not job.future.done():
                job.future.set_result(job.out)
