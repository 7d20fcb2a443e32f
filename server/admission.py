"""Admission: what the requests in flight may hold, decided from their headers before the body is read.

Two budgets bound the server: the **bytes** of request bodies in memory (``body_budget_bytes``; a JSON
body counts `settings.JSON_MEMORY_FACTOR` times its length, for the Python objects it is parsed into) and the
query **rows** admitted and not yet answered (``max_queue_rows``). As soon as a request's headers are
in, `Admission.admit` reserves its declared length and an upper bound of its rows (`plan`), or refuses
it at once: 413 above the per-request limits, 503 + ``Retry-After`` when either budget is spent - never
after the client has uploaded everything. Once the body is decoded, the reservation shrinks to the
true count of queries (a query group of K lights counts K: what the work and the answer's memory
grow with; a group takes at least 8 bytes a light, so the true count can exceed the bound from the
length, and the server refuses it then); it is released when the answer is complete (or, for a handler cancelled
by a client that went away, when its queued rows have run).

When no request has been in flight for `TRIM_AFTER_S`, the server hands the C heap's free pages back to the
system (glibc's ``malloc_trim``), after the engine's own tidy-up (`Engine.idle`: the kernel engine hands drjit's
cache of freed blocks back to the heap first): large buffers can then come from the heap while requests stream
(the Docker image's ``MALLOC_MMAP_THRESHOLD_`` of 4 MiB: no page faults for each request's body and answers), and
the memory a burst took still comes back once it is over.

A third budget bounds the way out: a request's **answer** (12 bytes an answer, ``answer_budget_bytes``)
is reserved once its rows are known, before they are evaluated (503 past the budget), and freed when the
response has been handed to the connection - or, for a client that does not read it, when the connection
is dropped after ``write_timeout_s`` (`protocol.py`).

Bodies then grow with the bytes that actually arrive (`read_body`), within the body timeout: a client
that declares 128 MiB and sends one byte holds its reservation for ``body_timeout_s`` at most, and no
memory.
"""

from __future__ import annotations

import asyncio
import ctypes
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from fastapi import Request
from starlette.requests import ClientDisconnect

from neumip.core.wire import ROW_BYTES

from neumip.server.body import header_int
from neumip.server.errors import ApiError, QueueFull
from neumip.server.metrics import Metrics
from neumip.server.settings import ANSWER_BYTES, JSON_MEMORY_FACTOR, Settings

MIN_JSON_ROW_BYTES = 14
"""Fewest bytes a query row takes in JSON (``0,0,0,0,0,0,0,`` in v2's flat data): rows <= length / 14."""


TRIM_AFTER_S = 1.0
"""Seconds without a request in flight after which the heap's free pages go back to the system."""


def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim`` of this process's C library; None where there is none (musl, macOS)."""
    try:
        return ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return None


MALLOC_TRIM = _malloc_trim()


@dataclass
class BodyPlan:
    """What a request's headers say about its body."""

    declared: int | None
    """Content-Length (None for a chunked upload)."""
    all_json: bool
    """The whole body is JSON."""
    json_bytes: int
    """Bytes of the body that are JSON (the rest is raw float32 rows)."""
    rows: int
    """Upper bound of the query rows the body can hold."""

    def memory(self, factor: int = JSON_MEMORY_FACTOR) -> int:
        """Bytes of memory the body may take: its length, its JSON part `factor` times."""
        binary = (self.declared or 0) - self.json_bytes
        return binary + factor * self.json_bytes


def plan(request: Request, settings: Settings, json: bool, json_length: int | None = None) -> BodyPlan:
    """The body's plan from the headers: 415 if compressed, 400 if the length is malformed, 413 if
    the body or its JSON part is over its limit. `json`: the body is JSON, all of it or, when the
    headers say how long its JSON part is, its first `json_length` bytes (v2's
    ``Inference-Header-Content-Length``); the rest is raw float32 rows."""
    encoding = request.headers.get("content-encoding", "identity").strip().lower()
    if encoding not in ("", "identity"):
        raise ApiError(415, f"Content-Encoding {encoding!r} is not supported; send the body uncompressed")
    value = request.headers.get("content-length")
    declared = None if value is None else header_int(value, "Content-Length")
    if declared is not None and declared > settings.max_body_bytes:
        raise ApiError(413, f"body of {declared} bytes is larger than the limit of {settings.max_body_bytes} bytes")
    all_json = json and json_length is None
    json_bytes = (declared or 0) if all_json else (json_length or 0)
    if json_bytes > settings.max_json_body_bytes:
        raise ApiError(
            413,
            f"JSON of {json_bytes} bytes is larger than the JSON limit of {settings.max_json_body_bytes} bytes;"
            " send large requests as msgpack (/v1) or binary tensors (/v2)",
        )
    binary = max((declared or 0) - json_bytes, 0)
    rows = binary // ROW_BYTES + json_bytes // MIN_JSON_ROW_BYTES
    return BodyPlan(declared, all_json, json_bytes, min(rows, settings.max_rows))


@dataclass
class Ticket:
    """What one request holds of the budgets."""

    memory: int
    """Bytes of body memory reserved."""
    rows: int
    """Query rows reserved."""
    until: asyncio.Future | None = None
    """The request's answer: the reservation lasts until it is done (set once its rows are queued)."""
    answer: int = 0
    """Bytes of answer memory reserved."""
    answer_handed: bool = False
    """A response frees the answer's reservation once sent (`Admission.hand_answer`), not the ticket."""
    released: bool = False


class Admission:
    """The server's two budgets, body bytes and queued rows (see the module docstring)."""

    def __init__(self, settings: Settings, metrics: Metrics, idle: Callable[[], object] = lambda: None) -> None:
        self.settings = settings
        self.metrics = metrics
        self.idle = idle  # the engine's tidy-up before the trim (`Engine.idle`)
        self.memory = 0  # touched on the event loop only, like everything here
        self.rows = 0
        self.requests = 0
        self.answers = 0
        # the gauges read the books when /metrics is scraped, not on every change
        metrics.body_bytes.set_function(lambda: self.memory)
        metrics.queue_rows.set_function(lambda: self.rows)
        metrics.queue_requests.set_function(lambda: self.requests)
        metrics.answer_bytes.set_function(lambda: self.answers)
        self.last_busy = time.monotonic()  # when a request last arrived or finished
        self.trims = 0
        self._trim: asyncio.TimerHandle | None = None

    @contextmanager
    def admit(self, plan: BodyPlan) -> Iterator[Ticket]:
        """Reserve the planned body memory and rows for the ``with`` block (and until ``ticket.until``
        is done); QueueFull (503) if either budget cannot take them."""
        ticket = Ticket(0, 0)
        self.resize(ticket, plan.memory(), plan.rows)
        self.requests += 1
        self.last_busy = time.monotonic()
        try:
            yield ticket
        finally:
            if ticket.until is None or ticket.until.done():
                self._release(ticket)
            else:  # a cancelled handler: its queued rows still run and still hold the body
                ticket.until.add_done_callback(lambda _: self._release(ticket))

    def resize(self, ticket: Ticket, memory: int, rows: int) -> None:
        """Change the ticket's reservation; QueueFull if it grows past a budget (nothing changes then)."""
        s = self.settings
        if memory > ticket.memory and self.memory - ticket.memory + memory > s.body_budget_bytes:
            self._refuse(f"{self.memory} bytes of request bodies in memory, {memory} more would pass the "
                         f"budget of {s.body_budget_bytes}")
        if rows > ticket.rows and self.rows - ticket.rows + rows > s.max_queue_rows:
            self._refuse(f"{self.rows} rows queued, {rows} more would pass the limit of {s.max_queue_rows}")
        self.memory += memory - ticket.memory
        self.rows += rows - ticket.rows
        ticket.memory, ticket.rows = memory, rows

    def reserve_answer(self, ticket: Ticket, answers: int) -> None:
        """Reserve the memory of `answers` answers (a query group of K lights counting K) before they are
        evaluated; QueueFull (503) if the answer budget cannot take them."""
        size, budget = answers * ANSWER_BYTES, self.settings.answer_budget_bytes
        if size > ticket.answer and self.answers - ticket.answer + size > budget:
            self._refuse(f"{self.answers} bytes of answers in memory, {size} more would pass the budget of {budget}")
        self.answers += size - ticket.answer
        ticket.answer = size

    def hand_answer(self, ticket: Ticket) -> Callable[[], None]:
        """The answer leaves in a response: returns what frees its reservation once the response is sent
        (from then on the ticket's release keeps it)."""
        ticket.answer_handed = True
        return lambda: self._free_answer(ticket)

    def _free_answer(self, ticket: Ticket) -> None:
        self.answers -= ticket.answer
        ticket.answer = 0

    def _refuse(self, why: str) -> None:
        self.metrics.rejected.inc()
        retry = self.settings.retry_after_s
        raise QueueFull(f"server busy: {why}; retry after {retry} s", retry)

    def _release(self, ticket: Ticket) -> None:
        if not ticket.released:
            ticket.released = True
            self.memory -= ticket.memory
            self.rows -= ticket.rows
            self.requests -= 1
            if not ticket.answer_handed:
                self._free_answer(ticket)
            self.last_busy = time.monotonic()
            if not self.requests:
                self._trim_when_idle()

    def _trim_when_idle(self) -> None:
        """Trim the heap once no request has been in flight for `TRIM_AFTER_S` (checked again when the timer
        fires: a stream of requests keeps putting it off)."""
        if MALLOC_TRIM is None or self._trim is not None:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # not on an event loop (a unit test's books): nothing to trim for
            return

        def fire() -> None:
            self._trim = None
            if self.requests:
                return  # busy again: the last release schedules the next
            idle = time.monotonic() - self.last_busy
            if idle < TRIM_AFTER_S:
                self._trim = loop.call_later(TRIM_AFTER_S - idle, fire)
                return
            self.idle()
            MALLOC_TRIM(0)
            self.trims += 1

        self._trim = loop.call_later(TRIM_AFTER_S, fire)


async def read_body(request: Request, plan: BodyPlan, ticket: Ticket, admission: Admission,
                    limit: int | None = None) -> bytearray:
    """The whole body, grown with the bytes that arrive (nothing is reserved in memory up front).

    408 (and the connection closed) if it takes longer than ``body_timeout_s``; 400 if the client goes
    away; a chunked upload grows its reservation as it comes (413 past the limits, 503 past the budget).
    `limit`: the body's most bytes where a route allows fewer than the settings (a shared-memory register
    request's 4 kB), so that a chunked upload is refused there, not reserved up to the settings' limit.
    """
    settings, body = admission.settings, bytearray()
    most = settings.max_json_body_bytes if plan.all_json else settings.max_body_bytes
    limit = most if limit is None else min(limit, most)
    factor = JSON_MEMORY_FACTOR if plan.all_json else 1
    try:
        async with asyncio.timeout(settings.body_timeout_s):
            async for chunk in request.stream():
                body += chunk
                if plan.declared is None:  # chunked: reserve as it grows
                    if len(body) > limit:
                        raise ApiError(413, f"body is larger than the limit of {limit} bytes")
                    admission.resize(ticket, max(ticket.memory, factor * len(body)), ticket.rows)
    except TimeoutError:
        expected = f"of {plan.declared} " if plan.declared is not None else ""
        raise ApiError(
            408,
            f"request body not complete after {settings.body_timeout_s:g} s ({len(body)} bytes {expected}arrived)",
            {"Connection": "close"},
        ) from None
    except ClientDisconnect:  # nobody is left to read the answer; a 4xx keeps the books straight
        raise ApiError(400, f"client disconnected after {len(body)} bytes of the body") from None
    return body
