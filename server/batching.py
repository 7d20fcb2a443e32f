"""Dynamic batching: decode -> **batch** -> **predict** -> **unbatch** -> encode.

Handlers decode and validate a request, then `Batcher.evaluate` cuts its (N, 7) queries into pieces of
at most ``chunk_rows`` rows (large requests are split: one ONNX Runtime call on 10^6 rows is several
times slower than the same rows in cache-sized chunks). Each material has a collector task that takes
pieces first-in first-out and merges consecutive small ones into one call of up to ``chunk_rows``
rows, waiting at most ``max_wait_ms`` for more to arrive. Calls run in a dedicated thread pool with
one thread per ONNX Runtime worker; `predict` is the only function that touches ONNX Runtime.

Merging keeps answers bit-identical to evaluating each request on its own: some ONNX Runtime CPU
kernels (``Log``, used for the level of detail) compute vector-sized blocks and the last few elements
of a call differently, so a row's bits depend on its position modulo the vector width. Every body
piece is a multiple of `ALIGN_ROWS` rows, so it starts aligned in a merged call, and a request's last
``N % ALIGN_ROWS`` rows (its tail) only ever go at the end of a call, exactly where they sit when the
request is evaluated alone.

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

ALIGN_ROWS = 16
"""Rows per alignment block: a multiple of every CPU vector width in floats (SSE 4, AVX 8, AVX-512 16)."""


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
    tail: bool = False  # the request's last N % ALIGN_ROWS rows: must end an ONNX Runtime call

    @property
    def rows(self) -> int:
        return self.queries.shape[0]


@dataclass
class _MaterialQueue:
    """Pieces waiting for one material, and the event that wakes its collector."""

    material: Material
    bodies: deque = field(default_factory=deque)  # pieces of a multiple of ALIGN_ROWS rows
    tails: deque = field(default_factory=deque)  # pieces of fewer than ALIGN_ROWS rows
    arrived: asyncio.Event = field(default_factory=asyncio.Event)
    rows: int = 0
    task: asyncio.Task | None = None


def split(queries: np.ndarray, out: np.ndarray, chunk: int, job: _Job) -> list[_Piece]:
    """Cut (N, 7) queries and their (N, 3) answer buffer into body pieces of at most `chunk` rows
    (a multiple of ALIGN_ROWS) and, if N is not a multiple of ALIGN_ROWS, one tail piece."""
    n = queries.shape[0]
    body = n - n % ALIGN_ROWS
    pieces = [
        _Piece(job, queries[lo : min(lo + chunk, body)], out[lo : min(lo + chunk, body)])
        for lo in range(0, body, chunk)
    ]
    if body < n:
        pieces.append(_Piece(job, queries[body:], out[body:], tail=True))
    return pieces


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
            for piece in pieces:
                (queue.tails if piece.tail else queue.bodies).append(piece)
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
            while not (queue.bodies or queue.tails):
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
        """Body pieces first-in first-out while they fit in `chunk` rows, then the oldest tail if it
        fits (a tail must end the call). A batch holds at least one piece."""
        batch, rows = [], 0
        while queue.bodies and (not batch or rows + queue.bodies[0].rows <= chunk):
            batch.append(queue.bodies.popleft())
            rows += batch[-1].rows
        if queue.tails and (not batch or rows + queue.tails[0].rows <= chunk):
            batch.append(queue.tails.popleft())
            rows += batch[-1].rows
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
