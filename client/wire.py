"""The wire formats the server and `MaterialClient` exchange: msgpack (``/v1``) and the Open Inference
Protocol's binary tensors (``/v2``).

msgpack request body:  map ``{"n": N, "queries": <N*7*4 bytes, little-endian float32, row-major>}``
msgpack response body: map ``{"n": N, "rgb": <N*3*4 bytes, little-endian float32, row-major>}``

The rows travel as raw float32 bytes, so neither side copies them: a body laid out exactly as
`msgpack.packb` writes it is read as a view (`_fast_rows`), and the server writes its answer straight
into a response body (`response_buffer`). Any other valid msgpack layout of the same map is still
decoded, by msgpack itself. What a query *means* is `neumip.client.contract`; this module is only
how its rows travel.

The v2 binary layout (Triton's binary tensor extension) is a JSON header of
``Inference-Header-Content-Length`` bytes followed by the raw tensor bytes: `encode_infer_request`
and `decode_infer_response` are the client's half; the server reads every form the protocol allows.
"""

from __future__ import annotations

import json

import numpy as np

from .contract import DTYPE, ONNX_INPUT, ONNX_OUTPUT, QUERY_DIM, RGB_DIM, QueryError, as_queries

MSGPACK_MEDIA_TYPE = "application/msgpack"
"""Content type of the request and response bodies."""
EVALUATE_PATH = "/v1/materials/{name}/evaluate"
"""POST here (msgpack or JSON) to evaluate queries on material `name`."""
MATERIALS_PATH = "/v1/materials"
"""GET here to list the served materials with their metadata."""
ROW_BYTES = QUERY_DIM * DTYPE.itemsize
"""Bytes of one query row on the wire."""
INFER_PATH = "/v2/models/{name}/infer"
"""POST here (Open Inference Protocol) to evaluate queries on material `name`."""
INFER_HEADER_LENGTH = "Inference-Header-Content-Length"
"""Header giving the length of the JSON part of a v2 body with binary tensors."""
INFER_DATATYPE = "FP32"
"""The Open Inference Protocol datatype of queries and answers."""


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


def encode_infer_request(queries: np.ndarray) -> tuple[dict[str, str], list]:
    """(N, 7) queries -> (headers, body parts) of a v2 infer request with a binary input and output:
    the JSON header, then the rows without a copy."""
    q = np.ascontiguousarray(queries, dtype=DTYPE)
    tensor = {"name": ONNX_INPUT, "datatype": INFER_DATATYPE, "shape": list(q.shape),
              "parameters": {"binary_data_size": q.nbytes}}
    head = {"inputs": [tensor], "outputs": [{"name": ONNX_OUTPUT, "parameters": {"binary_data": True}}]}
    header = json.dumps(head, separators=(",", ":")).encode()
    headers = {
        "Content-Type": "application/octet-stream",
        INFER_HEADER_LENGTH: str(len(header)),
        "Content-Length": str(len(header) + q.nbytes),
    }
    return headers, [header, memoryview(q.reshape(-1)).cast("B")]


def decode_infer_response(body, header_length: str | None) -> np.ndarray:
    """A v2 infer answer with a binary ``rgb`` output (and `header_length`, its
    Inference-Header-Content-Length) -> (N, 3) float32 RGB, a view of `body`. Raises QueryError."""
    if header_length is None or not header_length.isdigit() or int(header_length) > len(body):
        raise QueryError(f"v2 answer has no valid {INFER_HEADER_LENGTH} ({header_length!r}): no binary output")
    length = int(header_length)
    try:
        head = json.loads(bytes(memoryview(body)[:length]))
        [output] = [o for o in head["outputs"] if o["name"] == ONNX_OUTPUT]
        shape, size = output["shape"], output["parameters"]["binary_data_size"]
    except (ValueError, KeyError, TypeError) as exc:
        raise QueryError(f"v2 answer header is not an infer response with a binary '{ONNX_OUTPUT}': {exc}") from None
    if output.get("datatype") != INFER_DATATYPE or len(shape) != 2 or shape[1] != RGB_DIM:
        raise QueryError(f"v2 answer '{ONNX_OUTPUT}' is {output.get('datatype')} {shape}, not {INFER_DATATYPE} [N, 3]")
    if size != shape[0] * RGB_DIM * DTYPE.itemsize or len(body) - length != size:
        raise QueryError(f"v2 answer holds {len(body) - length} bytes of '{ONNX_OUTPUT}', shape {shape} needs "
                         f"{shape[0] * RGB_DIM * DTYPE.itemsize}")
    return np.frombuffer(body, dtype=DTYPE, offset=length).reshape(shape[0], RGB_DIM)
