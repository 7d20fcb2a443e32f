"""Reading request bodies safely: size limit, content type, and the 4xx errors for each mistake.

uvicorn puts no bound on a body by itself: `read_body` refuses a declared ``Content-Length`` above the
limit before reading anything, and stops a chunked upload as soon as it passes the limit.
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator

from fastapi import Request
from starlette.requests import ClientDisconnect

from .errors import ApiError

MSGPACK_TYPES = ("application/msgpack", "application/x-msgpack", "application/vnd.msgpack")
"""Content types taken as msgpack (the first is `contract.MSGPACK_MEDIA_TYPE`)."""
JSON_TYPE = "application/json"


def media_type(request: Request) -> str | None:
    """The request's Content-Type without parameters, lower case; None if absent."""
    value = request.headers.get("content-type")
    if value is None:
        return None
    return value.split(";", 1)[0].strip().lower() or None


def check_encoding(request: Request) -> None:
    """Refuse compressed bodies (415): the server reads raw bytes only."""
    encoding = request.headers.get("content-encoding", "identity").strip().lower()
    if encoding not in ("", "identity"):
        raise ApiError(415, f"Content-Encoding {encoding!r} is not supported; send the body uncompressed")


def declared_length(request: Request, limit: int) -> int | None:
    """The body's Content-Length (None for a chunked upload): 415 if compressed, 400 if malformed,
    413 above `limit` bytes - all before anything is read."""
    check_encoding(request)
    declared = request.headers.get("content-length")
    if declared is None:
        return None
    if not declared.strip().isdigit():
        raise ApiError(400, f"Content-Length must be a non-negative integer, got {declared[:40]!r}")
    if int(declared) > limit:
        raise ApiError(413, f"body of {int(declared)} bytes is larger than the limit of {limit} bytes")
    return int(declared)


async def read_body(request: Request, limit: int) -> bytes | bytearray:
    """The whole request body; 413 if it is (or declares to be) longer than `limit` bytes.

    With a ``Content-Length``, the chunks land in one buffer of that size as they arrive (no
    joining copy at the end); a chunked upload is joined once it ends.
    """
    declared = declared_length(request, limit)
    if declared is not None:
        body = bytearray(declared)
        async for _ in fill(request, body):
            pass
        return body
    chunks, size = [], 0
    try:
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise ApiError(413, f"body is larger than the limit of {limit} bytes")
            chunks.append(chunk)
    except ClientDisconnect:  # nobody is left to read the answer; a 4xx keeps the books straight
        raise ApiError(400, f"client disconnected after {size} bytes of the body") from None
    return b"".join(chunks)


async def fill(request: Request, body: bytearray) -> AsyncIterator[int]:
    """Read a body of ``len(body)`` bytes (its Content-Length) into `body`, yielding how many bytes
    are in after each chunk; 400 if the client goes away or the sizes disagree."""
    declared, size = len(body), 0
    try:
        async for chunk in request.stream():
            end = size + len(chunk)
            if end > declared:  # the HTTP parser enforces Content-Length; never write past the buffer
                raise ApiError(400, f"body is longer than its Content-Length of {declared} bytes")
            body[size:end] = chunk
            size = end
            if chunk:
                yield size
    except ClientDisconnect:  # nobody is left to read the answer; a 4xx keeps the books straight
        raise ApiError(400, f"client disconnected after {size} bytes of the body") from None
    if size != declared:
        raise ApiError(400, f"body has {size} bytes but its Content-Length says {declared}")


def parse_json(raw: bytes | memoryview, what: str = "body") -> object:
    """JSON text -> Python value; 400 saying where the JSON is broken."""
    try:
        return json.loads(bytes(raw))
    except (UnicodeDecodeError, ValueError) as exc:
        raise ApiError(400, f"{what} is not valid JSON: {exc}") from None


def check_rows(n: int, limit: int) -> None:
    """400 for an empty request, 413 for one over the row limit."""
    if n == 0:
        raise ApiError(400, "no queries: a request must carry at least one query row")
    if n > limit:
        raise ApiError(413, f"{n} query rows is more than the limit of {limit} rows per request")
