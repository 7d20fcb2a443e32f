"""The msgpack wire format of the ``/v1`` endpoints: the bodies the server and `MaterialClient` exchange.

Request body:  msgpack map ``{"n": N, "queries": <N*7*4 bytes, little-endian float32, row-major>}``
Response body: msgpack map ``{"n": N, "rgb": <N*3*4 bytes, little-endian float32, row-major>}``

The rows travel as raw float32 bytes, so neither side copies them: a body laid out exactly as
`msgpack.packb` writes it is read as a view (`_fast_rows`), and the server writes its answer straight
into a response body (`response_buffer`). Any other valid msgpack layout of the same map is still
decoded, by msgpack itself. What a query *means* is `neumip.client.contract`; this module is only
how its rows travel.
"""

from __future__ import annotations

import numpy as np

from .contract import DTYPE, QUERY_DIM, RGB_DIM, QueryError, as_queries

MSGPACK_MEDIA_TYPE = "application/msgpack"
"""Content type of the request and response bodies."""
EVALUATE_PATH = "/v1/materials/{name}/evaluate"
"""POST here (msgpack or JSON) to evaluate queries on material `name`."""
MATERIALS_PATH = "/v1/materials"
"""GET here to list the served materials with their metadata."""
ROW_BYTES = QUERY_DIM * DTYPE.itemsize
"""Bytes of one query row on the wire."""


def _prefix(key: str, n: int) -> bytes:
    """The bytes `msgpack.packb` writes before the raw rows of ``{"n": n, key: <rows>}``."""
    import msgpack

    nbytes = n * (QUERY_DIM if key == "queries" else RGB_DIM) * DTYPE.itemsize
    if nbytes < 1 << 8:
        bin_header = b"\xc4" + nbytes.to_bytes(1, "big")
    elif nbytes < 1 << 16:
        bin_header = b"\xc5" + nbytes.to_bytes(2, "big")
    else:
        bin_header = b"\xc6" + nbytes.to_bytes(4, "big")
    return msgpack.packb({"n": n, key: b""})[:-2] + bin_header  # [:-2]: the empty bin's header


def _fast_rows(body, key: str, width: int) -> np.ndarray | None:
    """The (n, width) rows of a body laid out exactly as `msgpack.packb` writes ``{"n": n, key: <rows>}``,
    as a view without copying; None for any other layout (the msgpack decoder takes those)."""
    view = memoryview(body)
    # 0x82: map of 2; 0xa1 'n'; then n as msgpack writes a non-negative int (fixint or uint 8..64)
    if len(view) < 4 or view[:3] != b"\x82\xa1n":
        return None
    tag = view[3]
    size = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}.get(tag, 0 if tag < 0x80 else -1)
    if size < 0 or len(view) < 4 + size:
        return None
    n = tag if size == 0 else int.from_bytes(view[4 : 4 + size], "big")
    if n > len(view):  # cannot be right
        return None
    prefix = _prefix(key, n)
    if view[: len(prefix)] != prefix or len(view) != len(prefix) + n * width * DTYPE.itemsize:
        return None
    return np.frombuffer(body, dtype=DTYPE, offset=len(prefix), count=n * width).reshape(n, width)


def _unpack_rows(body, key: str, width: int) -> np.ndarray:
    import msgpack

    fast = _fast_rows(body, key, width)  # the layout this module writes: a view, no copy
    if fast is not None:
        return fast
    try:
        msg = msgpack.unpackb(body, raw=False)
    except Exception as exc:  # msgpack raises several types for malformed input
        raise QueryError(f"body is not valid msgpack: {exc}") from None
    if not isinstance(msg, dict) or key not in msg or "n" not in msg:
        raise QueryError(f"msgpack body must be a map with keys 'n' and '{key}'")
    n, raw = msg["n"], msg[key]
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise QueryError(f"'n' must be a non-negative integer, got {n!r}")
    if not isinstance(raw, (bytes, bytearray)):
        raise QueryError(f"'{key}' must be binary (raw little-endian float32 bytes)")
    if len(raw) != n * width * DTYPE.itemsize:
        raise QueryError(
            f"'{key}' holds {len(raw)} bytes; n={n} rows of {width} float32 need {n * width * 4}"
        )
    return np.frombuffer(raw, dtype=DTYPE).reshape(n, width)


def encode_request(queries: np.ndarray) -> bytes:
    """(N, 7) queries -> msgpack request body."""
    header, rows = encode_request_parts(queries)
    return header + bytes(rows)


def encode_request_parts(queries: np.ndarray) -> tuple[bytes, memoryview]:
    """(N, 7) queries -> the msgpack request body as (header, rows): ``header + rows`` is
    `encode_request`'s body, for sending the rows without copying them."""
    q = np.ascontiguousarray(queries, dtype=DTYPE)
    return _prefix("queries", int(q.shape[0])), memoryview(q.reshape(-1)).cast("B")


def decode_request(body) -> np.ndarray:
    """msgpack request body -> validated (N, 7) float32 queries (a view of `body`). Raises QueryError."""
    return as_queries(_unpack_rows(body, "queries", QUERY_DIM))


def response_buffer(rows: int) -> tuple[bytearray, np.ndarray]:
    """An msgpack response body to fill in place: (body, its (rows, 3) float32 RGB view).

    Once the view holds the answer, ``body`` equals `encode_response` of it.
    """
    prefix = _prefix("rgb", rows)
    body = bytearray(len(prefix) + rows * RGB_DIM * DTYPE.itemsize)
    body[: len(prefix)] = prefix
    rgb = np.frombuffer(body, dtype=DTYPE, offset=len(prefix)).reshape(rows, RGB_DIM)  # (rows, 3)
    return body, rgb


def encode_response(rgb: np.ndarray) -> bytes:
    """(N, 3) RGB -> msgpack response body."""
    body, view = response_buffer(int(np.shape(rgb)[0]))
    view[...] = rgb
    return bytes(body)


def decode_response(body) -> np.ndarray:
    """msgpack response body -> (N, 3) float32 RGB (a view of `body`). Raises QueryError."""
    return _unpack_rows(body, "rgb", RGB_DIM)
