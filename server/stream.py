"""Evaluating a large msgpack request while its body is still arriving.

A body laid out as `contract.encode_request` writes it says its row count in its first bytes
(`contract.rows_layout`), so the request is admitted to the batcher at once and every
``chunk_rows`` rows are checked and queued as soon as they are in: ONNX Runtime starts on the first
rows while the rest is still being read, instead of after the whole body has been read and decoded.
The answer is the same, bit for bit: the same rows reach the same graph.

Anything unusual - another msgpack layout, a bad row, too many rows, a full queue - gives the
streamed job up (`Batcher.abandon`) and leaves the request to the ordinary path once the body is
in, which answers it, or refuses it with the same error it always would.
"""

from __future__ import annotations

import numpy as np
from fastapi import Request

from neumip.client import contract as C

from .batching import Batcher, _Job
from .body import fill
from .errors import ApiError
from .settings import Settings

ROW_BYTES = C.QUERY_DIM * C.DTYPE.itemsize
"""Bytes of one query row on the wire."""
HEAD_BYTES = 32
"""Bytes of the body enough to read its layout (the msgpack header before the rows is at most 25)."""


def worth_streaming(declared: int | None, settings: Settings) -> bool:
    """Whether a body of `declared` bytes holds more than one chunk of rows (else nothing to overlap)."""
    return declared is not None and declared > settings.chunk_rows * ROW_BYTES


class _Stream:
    """The streamed job of one request: admitted once the layout is known, fed chunk by chunk."""

    def __init__(self, name: str, body: bytearray, batcher: Batcher, settings: Settings) -> None:
        self.name, self.body, self.batcher, self.settings = name, body, batcher, settings
        self.job: _Job | None = None
        self.response: bytearray | None = None  # the msgpack answer body the workers fill
        self.offset = 0  # where the rows start in the body
        self.given_up = False

    def advance(self, filled: int) -> None:
        """`filled` bytes of the body are in: admit the request, then queue every full chunk of rows
        (all rows left once the body is complete)."""
        if self.given_up:
            return
        if self.job is None and not self._start(filled):
            return
        job, chunk = self.job, self.settings.chunk_rows
        ready = (filled - self.offset) // ROW_BYTES  # rows wholly in
        while ready - job.queued >= chunk or (ready == job.rows and job.queued < job.rows):
            m = min(chunk, ready - job.queued)
            start = self.offset + job.queued * ROW_BYTES
            rows = np.frombuffer(self.body, dtype=C.DTYPE, count=m * C.QUERY_DIM, offset=start)
            rows = rows.reshape(m, C.QUERY_DIM)  # (m, 7) float32 view of the body
            try:
                C.check_values(rows)
            except C.QueryError:  # the ordinary path reports it, with the row's index in the request
                self.give_up()
                return
            self.batcher.queue(job, rows)

    def _start(self, filled: int) -> bool:
        """Read the layout from the body's first bytes and admit the request; False if not (yet)."""
        if filled < min(len(self.body), HEAD_BYTES):
            return False  # not enough of the header yet
        layout = C.rows_layout(memoryview(self.body)[:filled], len(self.body))
        if layout is None or layout[0] > self.settings.max_rows:
            self.give_up()
            return False
        n, self.offset = layout
        self.response, rgb = C.response_buffer(n)  # rgb: (n, 3) float32 view of the response
        try:
            self.job = self.batcher.submit(self.name, n, out=rgb)
        except ApiError:  # queue full: the ordinary path tries again once the body is in
            self.give_up()
            return False
        return True

    def give_up(self) -> None:
        """Leave the request to the ordinary path; rows already queued still run."""
        if self.job is not None and not self.given_up:
            self.batcher.abandon(self.job)
        self.given_up = True


async def read_and_queue(
    name: str, request: Request, declared: int, batcher: Batcher, settings: Settings
) -> tuple[bytearray, _Stream]:
    """Read the body (`declared` bytes), queueing its rows as they come; the body and the stream.

    ``stream.given_up`` False: every row is queued; await ``batcher.result(stream.job)`` and answer
    ``stream.response``. True: the body is for the ordinary path.
    """
    body = bytearray(declared)
    stream = _Stream(name, body, batcher, settings)
    try:
        async for filled in fill(request, body):
            stream.advance(filled)
    except BaseException:  # client gone, cancelled: nobody will collect the answer
        stream.give_up()
        raise
    if stream.job is None and not stream.given_up:
        stream.give_up()
    return body, stream
