"""Answers on the way out: sent in pieces the client must take, freed once sent, JSON encoded off the loop.

Every evaluation answer is an `Answer`, a Starlette response that ends by calling ``on_sent`` (which
frees the answer's reservation in the admission budget, `Admission.hand_answer`) once the connection
has taken all of it - or once the client is gone:

- `BufferAnswer` (msgpack, binary tensors) sends the buffers the workers wrote, without a copy, in
  pieces of `PIECE_BYTES`. Each piece waits until the connection's send buffer has room (uvicorn's
  flow control), so a client that does not read holds the response there, not more memory; after
  ``NEUMIP_WRITE_TIMEOUT_S`` without room its connection is dropped (`protocol.py`).
- `JsonAnswer` encodes a large answer in a worker thread, `JSON_PIECE_VALUES` numbers at a time, and
  streams it (chunked transfer encoding): the event loop, health checks included, never waits for the
  encoding of a large answer (each piece holds the GIL for a few ms), and the text of only one piece
  exists at a time. Small answers (up to `JSON_INLINE_VALUES` numbers) are encoded at once and sent
  with a Content-Length. The numbers are those of ``json.dumps(rgb.tolist())``, as before.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import contextmanager

import numpy as np
from starlette.responses import Response

PIECE_BYTES = 1 << 20
"""Most bytes one send hands to the connection."""
JSON_INLINE_VALUES = 1 << 14
"""JSON answers of at most this many numbers are encoded on the event loop (about 3 ms), in one piece."""
JSON_PIECE_VALUES = 1 << 14
"""Numbers a worker thread encodes in one go (about 3-5 ms holding the GIL, which ``json`` never lets go of
within one call: the event loop waits that long at most)."""


@contextmanager
def freed_on_failure(sent: Callable[[], None]) -> Iterator[None]:
    """Around building the response that will send an answer: if building fails, no response will
    ever free the answer's reservation (`Admission.hand_answer`), so it is given back at once."""
    try:
        yield
    except BaseException:
        sent()
        raise


class Answer(Response):
    """A response whose body `pieces` yields; `on_sent` runs when it is sent or the client is gone."""

    def __init__(self, media_type: str, on_sent: Callable[[], None], length: int | None = None,
                 headers: dict[str, str] | None = None) -> None:
        self.status_code = 200
        self.media_type = media_type
        self.background = None
        self.on_sent = on_sent
        headers = dict(headers or {})
        if length is not None:  # else uvicorn sends the body chunked
            headers["content-length"] = str(length)
        self.init_headers(headers)

    def pieces(self, receive) -> AsyncIterator[bytes | memoryview]:
        """The body, piece by piece (`receive`: the ASGI receive, to learn that the client went away)."""
        raise NotImplementedError

    async def __call__(self, scope, receive, send) -> None:
        try:
            await send({"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers})
            async for piece in self.pieces(receive):  # once the client is gone, uvicorn's send returns at once
                await send({"type": "http.response.body", "body": piece, "more_body": True})
            await send({"type": "http.response.body", "body": b"", "more_body": False})
        finally:
            self.on_sent()


async def _disconnect(receive) -> None:
    """Returns when the ASGI server says the client disconnected (the request body is already read)."""
    while (await receive())["type"] != "http.disconnect":
        pass


class BufferAnswer(Answer):
    """Bytes-like buffers (msgpack bodies, a JSON header, float32 arrays) sent as they are, one after another."""

    def __init__(self, buffers: list, media_type: str, on_sent: Callable[[], None],
                 headers: dict[str, str] | None = None) -> None:
        self.buffers = [memoryview(np.ascontiguousarray(b).reshape(-1).view(np.uint8) if isinstance(b, np.ndarray)
                                   else b) for b in buffers]
        super().__init__(media_type, on_sent, sum(b.nbytes for b in self.buffers), headers)

    async def pieces(self, receive) -> AsyncIterator[memoryview]:
        for buffer in self.buffers:
            for start in range(0, buffer.nbytes, PIECE_BYTES):
                yield buffer[start:start + PIECE_BYTES]


def json_items(values: np.ndarray) -> str:
    """The items of ``values.tolist()`` as JSON, comma-separated, without the brackets."""
    return json.dumps(values.tolist(), separators=(",", ":"))[1:-1]


class JsonAnswer(Answer):
    """``prefix + "[" + items + "]" + suffix``: the list `values` (rows of a 2-D array, or numbers of a
    1-D one) inside a JSON document whose text around it is `prefix` and `suffix`."""

    def __init__(self, prefix: str, values: np.ndarray, suffix: str, on_sent: Callable[[], None]) -> None:
        self.prefix, self.values, self.suffix = prefix, values, suffix
        self.text = None
        if values.size <= JSON_INLINE_VALUES:
            self.text = f"{prefix}[{json_items(values)}]{suffix}".encode()
        super().__init__("application/json", on_sent, None if self.text is None else len(self.text))

    async def pieces(self, receive) -> AsyncIterator[bytes]:
        if self.text is not None:
            yield self.text
            return
        step = max(JSON_PIECE_VALUES * len(self.values) // self.values.size, 1)  # items a piece
        gone = asyncio.ensure_future(_disconnect(receive))  # no more encoding once the client is gone
        try:
            yield (self.prefix + "[").encode()
            for start in range(0, len(self.values), step):
                if gone.done():
                    return
                text = await asyncio.to_thread(json_items, self.values[start:start + step])
                yield (text if start == 0 else "," + text).encode()
            yield ("]" + self.suffix).encode()
        finally:
            gone.cancel()
