"""The wire formats the server and `MaterialClient` exchange: msgpack (``/v1``) and the Open Inference
Protocol's binary tensors (``/v2``).

msgpack request body:  map ``{"n": N, "lights": K, "queries": <N*W*4 bytes, little-endian float32, row-major>}``
msgpack response body: map ``{"n": N, "rgb": <N*3K*4 bytes, little-endian float32, row-major>}``

``W`` is 7 for plain queries, ``5 + 2 K`` for query groups of ``K`` lights (`contract.group_width`),
and the answer holds ``3 K`` values a row. ``"lights"`` is optional: `MaterialClient` always sends it,
and a body that has it must hold exactly ``n`` rows of ``5 + 2 K`` values (else a QueryError naming
both counts), so a wrong ``n`` cannot be read as groups of another width. A body without it (clients
before it) has its width read from the byte count: with ``n`` given, ``bytes / (4 n)`` has one value,
and a count that is no valid width (8 columns, or bytes that are not ``n`` whole rows) is a QueryError
naming the count; (N, 7) bodies read as they always did. ``N = 0`` with no bytes answers no rows (of
``3 K`` values with ``"lights"``; else of 3). Every material takes query groups (contract version 2):
on ``/v2`` its model metadata states the input ``[-1, -1]``, any width.

The rows travel as raw float32 bytes, so neither side copies them: a body laid out exactly as
`msgpack.packb` writes it is read as a view (`_fast_rows`), and the server writes its answer straight
into a response body (`response_buffer`). Any other valid msgpack layout of the same map is still
decoded, by msgpack itself. What a query *means* is `neumip.core.contract`; this module is only
how its rows travel.

The v2 binary layout (Triton's binary tensor extension) is a JSON header of
``Inference-Header-Content-Length`` bytes followed by the raw tensor bytes: `encode_infer_request`
and `decode_infer_response` are the client's half; the server reads every form the protocol allows.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from neumip.core.contract import (DTYPE, MAX_LIGHTS, ONNX_INPUT, ONNX_OUTPUT, QUERY_DIM, RGB_DIM, QueryError, as_queries,
                       group_lights, group_width)

MSGPACK_MEDIA_TYPE = "application/msgpack"
"""Content type of the request and response bodies."""
EVALUATE_PATH = "/v1/materials/{name}/evaluate"
"""POST here (msgpack or JSON) to evaluate queries on material `name`."""
MATERIALS_PATH = "/v1/materials"
"""GET here to list the served materials with their metadata."""
MATERIAL_PATH = "/v1/materials/{name}"
"""GET here for the metadata of material `name`."""
LIGHTS_KEY = "lights"
"""Optional field of a msgpack request body: the lights K of its query groups (1: plain queries)."""
ROW_BYTES = QUERY_DIM * DTYPE.itemsize
"""Bytes of one query row on the wire."""
INFER_PATH = "/v2/models/{name}/infer"
"""POST here (Open Inference Protocol) to evaluate queries on material `name`."""
MODEL_PATH = "/v2/models/{name}"
"""GET here (Open Inference Protocol) for the model metadata of material `name`."""
INFER_HEADER_LENGTH = "Inference-Header-Content-Length"
"""Header giving the length of the JSON part of a v2 body with binary tensors."""
INFER_DATATYPE = "FP32"
"""The Open Inference Protocol datatype of queries and answers."""


def _head(key: str, n: int, lights: int | None = None) -> bytes:
    """The bytes `msgpack.packb` writes for ``{"n": n, key: <rows>}`` (``{"n": n, "lights": lights, key:
    <rows>}`` with `lights`) up to the rows' bin header."""
    import msgpack

    fields = {"n": n} if lights is None else {"n": n, LIGHTS_KEY: lights}
    return msgpack.packb({**fields, key: b""})[:-2]  # [:-2]: the empty bin's header


def _prefix(key: str, n: int, width: int, lights: int | None = None) -> bytes:
    """The bytes `msgpack.packb` writes before the raw rows of ``{"n": n, ["lights": lights,] key:
    <rows>}``, `n` rows of `width` float32."""
    nbytes = n * width * DTYPE.itemsize
    if nbytes < 1 << 8:
        bin_header = b"\xc4" + nbytes.to_bytes(1, "big")
    elif nbytes < 1 << 16:
        bin_header = b"\xc5" + nbytes.to_bytes(2, "big")
    else:
        bin_header = b"\xc6" + nbytes.to_bytes(4, "big")
    return _head(key, n, lights) + bin_header


def _uint(view: memoryview, pos: int) -> tuple[int, int] | None:
    """A non-negative int as msgpack writes it (fixint or uint 8..64) at `pos` -> (value, position
    after it); None if there is none."""
    if len(view) <= pos:
        return None
    tag = view[pos]
    size = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}.get(tag, 0 if tag < 0x80 else -1)
    if size < 0 or len(view) < pos + 1 + size:
        return None
    return (tag if size == 0 else int.from_bytes(view[pos + 1 : pos + 1 + size], "big")), pos + 1 + size


_LIGHTS_TAG = b"\xa6" + LIGHTS_KEY.encode()  # "lights" as msgpack writes the key


def _fast_rows(body, key: str) -> tuple[int, int | None, memoryview] | None:
    """(n, lights or None, the raw row bytes) of a body laid out exactly as `msgpack.packb` writes
    ``{"n": n, key: <rows>}`` or ``{"n": n, "lights": lights, key: <rows>}``, a view without copying;
    None for any other layout (the msgpack decoder takes those)."""
    view = memoryview(body)
    # 0x82 / 0x83: map of 2 / 3; 0xa1 'n'; then n (and lights) as msgpack writes a non-negative int
    if len(view) < 3 or view[0] not in (0x82, 0x83) or view[1:3] != b"\xa1n":
        return None
    parsed = _uint(view, 3)
    if parsed is None:
        return None
    n, pos = parsed
    lights = None
    if view[0] == 0x83:  # {"n", "lights", key}
        parsed = _uint(view, pos + len(_LIGHTS_TAG))
        if view[pos : pos + len(_LIGHTS_TAG)] != _LIGHTS_TAG or parsed is None:
            return None
        lights = parsed[0]
    head = _head(key, n, lights)  # up to the rows' bin header
    lengths = {0xC4: 1, 0xC5: 2, 0xC6: 4}  # bin 8, 16, 32: bytes of the length that follows
    if view[: len(head)] != head or len(view) < len(head) + 1 or view[len(head)] not in lengths:
        return None
    start = len(head) + 1 + lengths[view[len(head)]]
    if len(view) < start or int.from_bytes(view[len(head) + 1 : start], "big") != len(view) - start:
        return None
    return n, lights, view[start:]


def _unpack(body, key: str) -> tuple[int, object, memoryview | bytes]:
    """(n, the ``"lights"`` value or None if absent, the raw bytes under `key`) of a msgpack body (a view
    of `body` where its layout allows). Raises QueryError."""
    import msgpack

    fast = _fast_rows(body, key)  # the layout this module writes: a view, no copy
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
    if LIGHTS_KEY in msg and msg[LIGHTS_KEY] is None:
        raise QueryError(f"'{LIGHTS_KEY}' must be an integer from 1 to {MAX_LIGHTS}, got nil")
    return n, msg.get(LIGHTS_KEY), raw


def _width(key: str, n: int, nbytes: int, unit: int, empty: int) -> int:
    """Float32 values per row of `n` rows held in `nbytes` bytes (`empty` for no rows); QueryError
    unless the bytes are `n` whole rows whose width is a multiple of `unit`."""
    if n == 0:
        if nbytes:
            raise QueryError(f"'{key}' holds {nbytes} bytes; n=0 rows need 0")
        return empty
    width, rest = divmod(nbytes, n * DTYPE.itemsize)
    if rest or not width or width % unit:
        need = (f"a multiple of n x {unit * DTYPE.itemsize} bytes" if key != "queries"
                else f"n x {ROW_BYTES} bytes for (N, 7) queries, or n x (5 + 2 K) x 4 for groups of K lights")
        raise QueryError(f"'{key}' holds {nbytes} bytes, which is not n={n} rows of float32: it needs {need}")
    return width


def _stated_width(n: int, lights: object, nbytes: int) -> int:
    """The query width of a body that states its ``"lights"``; QueryError unless `lights` is a light
    count and the bytes are exactly `n` rows of its groups."""
    if isinstance(lights, bool) or not isinstance(lights, int) or not 1 <= lights <= MAX_LIGHTS:
        raise QueryError(f"'{LIGHTS_KEY}' must be an integer from 1 to {MAX_LIGHTS}, got {str(lights)[:40]}")
    width = group_width(lights)
    if nbytes != n * width * DTYPE.itemsize:
        raise QueryError(f"'queries' holds {nbytes} bytes, but n={n} rows of {lights} light(s) ({width} float32 "
                         f"each) need {n * width * DTYPE.itemsize}")
    return width


def encode_request(queries: np.ndarray) -> bytes:
    """(N, 7) queries, or query groups (N, 5 + 2 K) -> msgpack request body."""
    header, rows = encode_request_parts(queries)
    return header + bytes(rows)


def encode_request_parts(queries: np.ndarray) -> tuple[bytes, memoryview]:
    """(N, 7) queries or (N, 5 + 2 K) groups -> the msgpack request body as (header, rows): ``header +
    rows`` is `encode_request`'s body, for sending the rows without copying them."""
    q = np.ascontiguousarray(queries, dtype=DTYPE)
    n, width = int(q.shape[0]), int(q.shape[1])
    return _prefix("queries", n, width, group_lights(width)), memoryview(q.reshape(-1)).cast("B")


def decode_request(body) -> np.ndarray:
    """msgpack request body -> validated (N, 7) float32 queries, or (N, 5 + 2 K) query groups (a view
    of `body`): the width from ``"lights"`` if the body states it, else from the byte count. Raises
    QueryError."""
    n, lights, raw = _unpack(body, "queries")
    if lights is not None:
        width = _stated_width(n, lights, len(raw))
    else:
        width = _width("queries", n, len(raw), 1, QUERY_DIM)
        try:
            group_lights(width)
        except QueryError as exc:
            raise QueryError(f"'queries' holds {len(raw)} bytes, {width} float32 per row for n={n}: {exc}") from None
    return as_queries(np.frombuffer(raw, dtype=DTYPE).reshape(n, width), groups=True)


def response_buffer(rows: int, lights: int = 1) -> tuple[bytearray, np.ndarray]:
    """An msgpack response body to fill in place: (body, its (rows, 3 lights) float32 RGB view).

    Once the view holds the answer, ``body`` equals `encode_response` of it.
    """
    width = RGB_DIM * lights
    prefix = _prefix("rgb", rows, width)
    body = bytearray(len(prefix) + rows * width * DTYPE.itemsize)
    body[: len(prefix)] = prefix
    rgb = np.frombuffer(body, dtype=DTYPE, offset=len(prefix)).reshape(rows, width)  # (rows, 3 lights)
    return body, rgb


def encode_response(rgb: np.ndarray) -> bytes:
    """(N, 3) RGB, or (N, 3 K) answers of query groups -> msgpack response body."""
    rows, width = np.shape(rgb)
    body, view = response_buffer(int(rows), width // RGB_DIM)
    view[...] = rgb
    return bytes(body)


def decode_response(body) -> np.ndarray:
    """msgpack response body -> (N, 3) float32 RGB, or (N, 3 K) for query groups (a view of `body`).
    Raises QueryError."""
    n, _, raw = _unpack(body, "rgb")
    return np.frombuffer(raw, dtype=DTYPE).reshape(n, _width("rgb", n, len(raw), RGB_DIM, RGB_DIM))


def encode_infer_request(queries: np.ndarray, binary_output: bool = True) -> tuple[dict[str, str], list]:
    """(N, 7) queries or (N, 5 + 2 K) groups -> (headers, body parts) of a v2 infer request with a
    binary input and a binary output (`binary_output` False: the answer in JSON): the JSON header, then the rows
    without a copy."""
    q = np.ascontiguousarray(queries, dtype=DTYPE)
    tensor = {"name": ONNX_INPUT, "datatype": INFER_DATATYPE, "shape": list(q.shape),
              "parameters": {"binary_data_size": q.nbytes}}
    head = {"inputs": [tensor], "outputs": [{"name": ONNX_OUTPUT, "parameters": {"binary_data": binary_output}}]}
    header = json.dumps(head, separators=(",", ":")).encode()
    headers = {
        "Content-Type": "application/octet-stream",
        INFER_HEADER_LENGTH: str(len(header)),
        "Content-Length": str(len(header) + q.nbytes),
    }
    return headers, [header, memoryview(q.reshape(-1)).cast("B")]


def encode_shared_infer_request(shape: tuple[int, int], queries_at: SharedMemoryRef,
                                answers_at: SharedMemoryRef) -> tuple[dict[str, str], list]:
    """A v2 infer request of (N, 5 + 2 K) queries already in shared memory at `queries_at`, asking for the
    answers at `answers_at` -> (headers, body parts): a JSON body of a few hundred bytes."""
    tensor = {"name": ONNX_INPUT, "datatype": INFER_DATATYPE, "shape": list(shape), "parameters": queries_at.parameters()}
    head = {"inputs": [tensor], "outputs": [{"name": ONNX_OUTPUT, "parameters": answers_at.parameters()}]}
    body = json.dumps(head, separators=(",", ":")).encode()
    return {"Content-Type": "application/json", "Content-Length": str(len(body))}, [body]


def decode_shared_infer_response(body) -> tuple[tuple[int, int], SharedMemoryRef]:
    """A v2 infer answer whose ``rgb`` went to shared memory -> (its shape (N, 3 K), where it lies). Raises
    QueryError."""
    try:
        head = json.loads(bytes(body))
        [output] = [o for o in head["outputs"] if o["name"] == ONNX_OUTPUT]
        shape, where = output["shape"], _shared_memory_ref(output["parameters"], "output ")
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise QueryError(f"v2 answer is not an infer response with '{ONNX_OUTPUT}' in shared memory: {exc}") from None
    if (where is None or output.get("datatype") != INFER_DATATYPE or not isinstance(shape, list) or len(shape) != 2
            or not all(isinstance(d, int) and d >= 0 for d in shape) or not shape[1] or shape[1] % RGB_DIM):
        raise QueryError(f"v2 answer '{ONNX_OUTPUT}' is {output.get('datatype')} {shape}, not {INFER_DATATYPE} "
                         "[N, 3 K] in shared memory")
    if where.byte_size != shape[0] * shape[1] * DTYPE.itemsize:
        raise QueryError(f"v2 answer '{ONNX_OUTPUT}' of shape {shape} says it takes {where.byte_size} bytes")
    return (shape[0], shape[1]), where


def decode_infer_response(body, header_length: str | None) -> np.ndarray:
    """A v2 infer answer with a binary ``rgb`` output (and `header_length`, its
    Inference-Header-Content-Length) -> (N, 3) float32 RGB, or (N, 3 K) answers of query groups, a view
    of `body`. Raises QueryError."""
    if header_length is None or not (header_length.isascii() and header_length.isdigit()) or int(header_length) > len(body):
        raise QueryError(f"v2 answer has no valid {INFER_HEADER_LENGTH} ({header_length!r}): no binary output")
    length = int(header_length)
    try:
        head = json.loads(bytes(memoryview(body)[:length]))
        [output] = [o for o in head["outputs"] if o["name"] == ONNX_OUTPUT]
        shape, size = output["shape"], output["parameters"]["binary_data_size"]
    except (ValueError, KeyError, TypeError) as exc:
        raise QueryError(f"v2 answer header is not an infer response with a binary '{ONNX_OUTPUT}': {exc}") from None
    if (output.get("datatype") != INFER_DATATYPE or len(shape) != 2
            or not all(isinstance(d, int) and d >= 0 for d in shape) or not shape[1] or shape[1] % RGB_DIM):
        raise QueryError(f"v2 answer '{ONNX_OUTPUT}' is {output.get('datatype')} {shape}, "
                         f"not {INFER_DATATYPE} [N, 3 K]")
    if size != shape[0] * shape[1] * DTYPE.itemsize or len(body) - length != size:
        raise QueryError(f"v2 answer holds {len(body) - length} bytes of '{ONNX_OUTPUT}', shape {shape} needs "
                         f"{shape[0] * shape[1] * DTYPE.itemsize}")
    return np.frombuffer(body, dtype=DTYPE, offset=length).reshape(shape)

# --- the Open Inference Protocol's infer request and response, server side ---------------------

@dataclass(frozen=True)
class SharedMemoryRef:
    """Where a tensor lies in shared memory (Triton's system shared-memory extension): `byte_size` bytes
    from `offset` of the registered region `region` (`neumip.server.shared_memory`)."""

    region: str
    byte_size: int
    offset: int = 0

    def parameters(self) -> dict:
        """The tensor's ``parameters`` that point here."""
        return {"shared_memory_region": self.region, "shared_memory_byte_size": self.byte_size,
                "shared_memory_offset": self.offset}


@dataclass
class InferRequest:
    """A decoded v2 infer request: its id, its queries and how the output goes back."""

    id: str | None
    queries: np.ndarray | None  # (N, 5 + 2 K) float32, validated; K = 1: (N, 7); None: in `input_region`
    binary_output: bool
    shape: tuple[int, int] = (0, QUERY_DIM)
    """The queries' shape, (N, 5 + 2 K)."""
    input_region: SharedMemoryRef | None = None
    """Where the queries lie in shared memory (then `queries` is None until the server reads them)."""
    output_region: SharedMemoryRef | None = None
    """Where the answers go in shared memory (None: in the response)."""


def _parse_json(raw: bytes | memoryview, what: str = "body") -> object:
    """JSON text -> Python value; QueryError saying where the JSON is broken (or that it nests too deep)."""
    try:
        return json.loads(bytes(raw))
    except (UnicodeDecodeError, ValueError) as exc:
        raise QueryError(f"{what} is not valid JSON: {exc}") from None
    except RecursionError:
        raise QueryError(f"{what} nests too deep to be a query request") from None


def _split_body(body: bytes, length: int | None) -> tuple[object, memoryview]:
    """Body -> (JSON header, binary tail), the header `length` bytes long (None: all of the body)."""
    if length is None:
        return _parse_json(body), memoryview(b"")
    if length == 0 or length > len(body):
        raise QueryError(f"{INFER_HEADER_LENGTH} is {length} but the body holds {len(body)} bytes")
    view = memoryview(body)
    return _parse_json(view[:length], f"JSON header (first {INFER_HEADER_LENGTH} bytes)"), view[length:]


def _parameters(obj: dict, where: str) -> dict:
    params = obj.get("parameters", {})
    if not isinstance(params, dict):
        raise QueryError(f"{where}'parameters' must be an object")
    return params


def _shared_memory_ref(params: dict, where: str) -> SharedMemoryRef | None:
    """A tensor's shared-memory parameters -> where it lies (None: not in shared memory). Raises QueryError
    if only one of the region and its byte size is given, as Triton does."""
    region, size = params.get("shared_memory_region"), params.get("shared_memory_byte_size")
    offset = params.get("shared_memory_offset", 0)
    if region is None and size is None:
        if "shared_memory_offset" in params:
            raise QueryError(f"{where}'shared_memory_offset' needs 'shared_memory_region' and 'shared_memory_byte_size'")
        return None
    if not isinstance(region, str) or not region:
        raise QueryError(f"{where}'shared_memory_region' must name a registered region, got {str(region)[:40]!r}")
    for key, value in (("shared_memory_byte_size", size), ("shared_memory_offset", offset)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise QueryError(f"{where}'{key}' must be a non-negative integer, got {str(value)[:40]!r}")
    return SharedMemoryRef(region, size, offset)


def _input_tensor(inputs: object, binary: memoryview) -> tuple[np.ndarray | SharedMemoryRef, tuple[int, int]]:
    """The one input tensor -> ((N, 5 + 2 K) float32 (unvalidated values), or where it lies in shared
    memory; its shape). Raises QueryError."""
    if not isinstance(inputs, list) or len(inputs) != 1 or not isinstance(inputs[0], dict):
        raise QueryError(f"'inputs' must be a list holding exactly one tensor, '{ONNX_INPUT}'")
    tensor = inputs[0]
    if tensor.get("name") != ONNX_INPUT:
        raise QueryError(f"unknown input {str(tensor.get('name'))[:40]!r}: the model's input is '{ONNX_INPUT}'")
    if tensor.get("datatype") != INFER_DATATYPE:
        raise QueryError(f"input '{ONNX_INPUT}' must have datatype {INFER_DATATYPE}, got {str(tensor.get('datatype'))[:20]!r}")
    shape = tensor.get("shape")
    if (
        not isinstance(shape, list)
        or len(shape) != 2
        or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)
    ):
        raise QueryError(f"input '{ONNX_INPUT}' must have shape [N, {QUERY_DIM}] or [N, 5 + 2 K] "
                       f"for query groups, got {str(shape)[:60]}")
    n, width = shape
    try:
        group_lights(width)
    except QueryError as exc:
        raise QueryError(f"input '{ONNX_INPUT}' has shape {shape}: {exc}") from None
    params = _parameters(tensor, "input ")
    shared = _shared_memory_ref(params, "input ")
    if shared is not None:
        if "data" in tensor or "binary_data_size" in params:
            raise QueryError(f"input '{ONNX_INPUT}' in shared memory can have neither 'data' nor binary_data_size")
        if shared.byte_size != n * width * DTYPE.itemsize:
            raise QueryError(f"shared_memory_byte_size is {shared.byte_size} but shape {shape} of FP32 needs "
                             f"{n * width * DTYPE.itemsize} bytes")
        if len(binary):
            raise QueryError(f"{len(binary)} bytes follow the JSON header but the input is in shared memory")
        return shared, (n, width)
    size = params.get("binary_data_size")
    if size is not None:
        expected = n * width * DTYPE.itemsize
        if not isinstance(size, int) or size != expected:
            raise QueryError(f"binary_data_size is {size!r} but shape {shape} of FP32 needs {expected} bytes")
        if len(binary) != size:
            raise QueryError(f"binary part holds {len(binary)} bytes, binary_data_size says {size}")
        return np.frombuffer(binary, dtype=DTYPE).reshape(n, width), (n, width)
    if len(binary):
        raise QueryError(f"{len(binary)} bytes follow the JSON header but no input has binary_data_size")
    return _json_data(tensor.get("data"), n, width), (n, width)


def _json_data(data: object, n: int, width: int) -> np.ndarray:
    if not isinstance(data, list):
        raise QueryError(f"input '{ONNX_INPUT}' needs 'data' (a list of numbers) or binary_data_size")
    try:
        arr = np.asarray(data)
    except (TypeError, ValueError):  # ragged nesting
        raise QueryError(f"input '{ONNX_INPUT}' data must be a flat or evenly nested list of numbers") from None
    if arr.size and arr.dtype.kind not in "fiu":
        kind = {"U": "strings", "b": "booleans", "O": "other values"}.get(arr.dtype.kind, f"{arr.dtype} values")
        raise QueryError(f"input '{ONNX_INPUT}' data must hold only numbers (FP32), got {kind}")
    if arr.size != n * width:
        raise QueryError(f"input '{ONNX_INPUT}' data holds {arr.size} values, shape [{n}, {width}] "
                       f"needs {n * width}")
    with np.errstate(over="ignore"):  # out-of-range values become Inf and are rejected as such
        return arr.astype(DTYPE).reshape(n, width)


def _output(msg: dict) -> tuple[bool, SharedMemoryRef | None]:
    """Whether 'rgb' goes back as binary, and where in shared memory it goes instead (None: in the
    response); 400 for unknown requested outputs."""
    binary, shared = _flag(_parameters(msg, ""), "binary_data_output", False), None
    outputs = msg.get("outputs")
    if outputs is None:
        return binary, shared
    if not isinstance(outputs, list) or not all(isinstance(o, dict) for o in outputs):
        raise QueryError("'outputs' must be a list of objects")
    for out in outputs:
        if out.get("name") != ONNX_OUTPUT:
            raise QueryError(f"unknown output {str(out.get('name'))[:40]!r}: the model's output is '{ONNX_OUTPUT}'")
        params = _parameters(out, "output ")
        binary = _flag(params, "binary_data", binary)
        shared = _shared_memory_ref(params, "output ") or shared
    return binary, shared


def _flag(params: dict, key: str, default: bool) -> bool:
    """A boolean parameter; 400 for anything but true/false (a string "false" must not mean true)."""
    value = params.get(key, default)
    if not isinstance(value, bool):
        raise QueryError(f"parameter '{key}' must be true or false, got {str(value)[:40]!r}")
    return value


def decode_infer_request(body: bytes, header_length: int | None) -> InferRequest:
    """A v2 infer request's body (and its Inference-Header-Content-Length, None: all JSON) -> InferRequest with
    validated queries (a view of `body` where binary). Raises QueryError. The inverse of `encode_infer_request`."""
    msg, binary = _split_body(body, header_length)
    if not isinstance(msg, dict):
        raise QueryError("infer request must be a JSON object with 'inputs'")
    request_id = msg.get("id")
    if request_id is not None and not isinstance(request_id, str):
        raise QueryError("'id' must be a string")
    raw, shape = _input_tensor(msg.get("inputs"), binary)
    binary_output, output_region = _output(msg)
    if isinstance(raw, SharedMemoryRef):
        return InferRequest(request_id, None, binary_output, shape, raw, output_region)
    return InferRequest(request_id, as_queries(raw, groups=True), binary_output, shape, None, output_region)


def infer_response_head(model: str, version: str, request: InferRequest, rgb: np.ndarray) -> dict:
    """The JSON head of the v2 answer to `request`: (N, 3 K) `rgb` as binary data (``binary_data_size``, the
    bytes following the head) or, for a JSON answer, ``"data": "@"`` where the caller cuts in the numbers.
    The inverse of `decode_infer_response`."""
    head = {"model_name": model, "model_version": version}
    if request.id is not None:
        head["id"] = request.id  # before the outputs: a JSON answer's data is cut in after the last "@"
    output = {"name": ONNX_OUTPUT, "datatype": INFER_DATATYPE, "shape": list(rgb.shape)}
    head["outputs"] = [output]
    if request.output_region is not None:  # the answers are in shared memory: no data here
        output["parameters"] = SharedMemoryRef(request.output_region.region, rgb.nbytes,
                                               request.output_region.offset).parameters()
    elif request.binary_output:
        output["parameters"] = {"binary_data_size": rgb.nbytes}
    else:
        output["data"] = "@"
    return head
