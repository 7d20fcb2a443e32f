"""The Open Inference Protocol v2 (KServe / Triton REST) with Triton's binary tensor extension.

Each material is a model with one version, ``"1"``, one input ``queries`` FP32 [-1, -1] and one output
``rgb`` FP32 [-1, -1] (the protocol's -1: a dimension of variable size): [N, 7] queries answer [N, 3],
[N, 5 + 2 K] query groups of K lights answer [N, 3 K] (`neumip.core.contract`). Infer bodies are
read raw (tritonclient sends no Content-Type) and split by the ``Inference-Header-Content-Length``
header into the JSON header and the binary tensor bytes.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from fastapi import APIRouter, Depends, Request, Response

from neumip.core import contract as C
from neumip.core import wire

from neumip.server.admission import plan, read_body
from neumip.server.answer import Answer, BufferAnswer, JsonAnswer, freed_on_failure
from neumip.server.body import JSON_TYPE, check_rows, header_int, media_type, parse_json
from neumip.server.errors import ApiError
from neumip.server.metrics import StageTimer
from neumip.server.openapi import ERROR_RESPONSES, INFER_BODY
from neumip.server.registry import MODEL_VERSION
from neumip.server.state import ServerState, get_state, serving
from neumip.server.v1 import OFFLOAD_BYTES

router = APIRouter(prefix="/v2", tags=["v2 (Open Inference Protocol)"])

HEADER_LENGTH = wire.INFER_HEADER_LENGTH
DATATYPE = wire.INFER_DATATYPE
INFER_TYPES = (None, JSON_TYPE, "application/octet-stream")
"""Content types an infer request may carry (tritonclient sends none)."""


@dataclass
class InferRequest:
    """A parsed infer request: queries and how to send the output back."""

    id: str | None
    queries: np.ndarray  # (N, 5 + 2 K) float32, validated; K = 1: (N, 7)
    binary_output: bool


def model_metadata(name: str, platform: str) -> dict:
    """The model metadata of material `name` run by `platform` (`Engine.platform`): shapes [-1, -1] in
    and out (queries (N, 5 + 2 K) -> (N, 3 K))."""
    return {
        "name": name,
        "versions": [MODEL_VERSION],
        "platform": platform,
        "inputs": [{"name": C.ONNX_INPUT, "datatype": DATATYPE, "shape": [-1, -1]}],
        "outputs": [{"name": C.ONNX_OUTPUT, "datatype": DATATYPE, "shape": [-1, -1]}],
    }


def check_version(version: str | None) -> None:
    if version is not None and version != MODEL_VERSION:
        raise ApiError(404, f"unknown model version {version[:40]!r}: only version {MODEL_VERSION!r} exists")


# --- decode -----------------------------------------------------------------------------------
def json_length(request: Request) -> int | None:
    """The Inference-Header-Content-Length header: bytes of the JSON part (None: the body is all JSON)."""
    value = request.headers.get(HEADER_LENGTH)
    return None if value is None else header_int(value, HEADER_LENGTH)


def split_body(body: bytes, length: int | None) -> tuple[object, memoryview]:
    """Body -> (JSON header, binary tail), the header `length` bytes long (None: all of the body)."""
    if length is None:
        return parse_json(body), memoryview(b"")
    if length == 0 or length > len(body):
        raise ApiError(400, f"{HEADER_LENGTH} is {length} but the body holds {len(body)} bytes")
    view = memoryview(body)
    return parse_json(view[:length], f"JSON header (first {HEADER_LENGTH} bytes)"), view[length:]


def _parameters(obj: dict, where: str) -> dict:
    params = obj.get("parameters", {})
    if not isinstance(params, dict):
        raise ApiError(400, f"{where}'parameters' must be an object")
    return params


def _input_tensor(inputs: object, binary: memoryview) -> np.ndarray:
    """The one input tensor -> (N, 5 + 2 K) float32 (unvalidated values). Raises ApiError/QueryError."""
    if not isinstance(inputs, list) or len(inputs) != 1 or not isinstance(inputs[0], dict):
        raise ApiError(400, f"'inputs' must be a list holding exactly one tensor, '{C.ONNX_INPUT}'")
    tensor = inputs[0]
    if tensor.get("name") != C.ONNX_INPUT:
        raise ApiError(400, f"unknown input {str(tensor.get('name'))[:40]!r}: the model's input is '{C.ONNX_INPUT}'")
    if tensor.get("datatype") != DATATYPE:
        raise ApiError(400, f"input '{C.ONNX_INPUT}' must have datatype {DATATYPE}, got {str(tensor.get('datatype'))[:20]!r}")
    shape = tensor.get("shape")
    if (
        not isinstance(shape, list)
        or len(shape) != 2
        or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)
    ):
        raise ApiError(400, f"input '{C.ONNX_INPUT}' must have shape [N, {C.QUERY_DIM}] or [N, 5 + 2 K] "
                       f"for query groups, got {str(shape)[:60]}")
    n, width = shape
    try:
        C.group_lights(width)
    except C.QueryError as exc:
        raise ApiError(400, f"input '{C.ONNX_INPUT}' has shape {shape}: {exc}") from None
    size = _parameters(tensor, "input ").get("binary_data_size")
    if size is not None:
        expected = n * width * C.DTYPE.itemsize
        if not isinstance(size, int) or size != expected:
            raise ApiError(400, f"binary_data_size is {size!r} but shape {shape} of FP32 needs {expected} bytes")
        if len(binary) != size:
            raise ApiError(400, f"binary part holds {len(binary)} bytes, binary_data_size says {size}")
        return np.frombuffer(binary, dtype=C.DTYPE).reshape(n, width)
    if len(binary):
        raise ApiError(400, f"{len(binary)} bytes follow the JSON header but no input has binary_data_size")
    return _json_data(tensor.get("data"), n, width)


def _json_data(data: object, n: int, width: int) -> np.ndarray:
    if not isinstance(data, list):
        raise ApiError(400, f"input '{C.ONNX_INPUT}' needs 'data' (a list of numbers) or binary_data_size")
    try:
        arr = np.asarray(data)
    except (TypeError, ValueError):  # ragged nesting
        raise ApiError(400, f"input '{C.ONNX_INPUT}' data must be a flat or evenly nested list of numbers") from None
    if arr.size and arr.dtype.kind not in "fiu":
        kind = {"U": "strings", "b": "booleans", "O": "other values"}.get(arr.dtype.kind, f"{arr.dtype} values")
        raise ApiError(400, f"input '{C.ONNX_INPUT}' data must hold only numbers (FP32), got {kind}")
    if arr.size != n * width:
        raise ApiError(400, f"input '{C.ONNX_INPUT}' data holds {arr.size} values, shape [{n}, {width}] "
                       f"needs {n * width}")
    with np.errstate(over="ignore"):  # out-of-range values become Inf and are rejected as such
        return arr.astype(C.DTYPE).reshape(n, width)


def _binary_output(msg: dict) -> bool:
    """Whether 'rgb' goes back as binary; 400 for unknown requested outputs."""
    binary = _flag(_parameters(msg, ""), "binary_data_output", False)
    outputs = msg.get("outputs")
    if outputs is None:
        return binary
    if not isinstance(outputs, list) or not all(isinstance(o, dict) for o in outputs):
        raise ApiError(400, "'outputs' must be a list of objects")
    for out in outputs:
        if out.get("name") != C.ONNX_OUTPUT:
            raise ApiError(400, f"unknown output {str(out.get('name'))[:40]!r}: the model's output is '{C.ONNX_OUTPUT}'")
        binary = _flag(_parameters(out, "output "), "binary_data", binary)
    return binary


def _flag(params: dict, key: str, default: bool) -> bool:
    """A boolean parameter; 400 for anything but true/false (a string "false" must not mean true)."""
    value = params.get(key, default)
    if not isinstance(value, bool):
        raise ApiError(400, f"parameter '{key}' must be true or false, got {str(value)[:40]!r}")
    return value


def parse_infer(body: bytes, header_length: int | None) -> InferRequest:
    """Infer body -> InferRequest with validated queries. Raises ApiError/QueryError."""
    msg, binary = split_body(body, header_length)
    if not isinstance(msg, dict):
        raise ApiError(400, "infer request must be a JSON object with 'inputs'")
    request_id = msg.get("id")
    if request_id is not None and not isinstance(request_id, str):
        raise ApiError(400, "'id' must be a string")
    raw = _input_tensor(msg.get("inputs"), binary)
    return InferRequest(request_id, C.as_queries(raw, groups=True), _binary_output(msg))


# --- encode -----------------------------------------------------------------------------------
def infer_response(name: str, request: InferRequest, rgb: np.ndarray, on_sent: Callable[[], None]) -> Answer:
    """(N, 3 K) RGB -> the infer response, JSON (streamed when large) or JSON + binary tail."""
    head = {"model_name": name, "model_version": MODEL_VERSION}
    if request.id is not None:
        head["id"] = request.id  # before the outputs: the JSON answer's data is cut in after the last "@"
    output = {"name": C.ONNX_OUTPUT, "datatype": DATATYPE, "shape": list(rgb.shape)}
    head["outputs"] = [output]
    if not request.binary_output:
        output["data"] = "@"
        prefix, suffix = json.dumps(head, separators=(",", ":")).rsplit('"@"', 1)
        return JsonAnswer(prefix, rgb.reshape(-1), suffix, on_sent)
    output["parameters"] = {"binary_data_size": rgb.nbytes}
    header = json.dumps(head, separators=(",", ":")).encode()
    return BufferAnswer([header, rgb], "application/octet-stream", on_sent, {HEADER_LENGTH: str(len(header))})


# --- routes -----------------------------------------------------------------------------------
@router.get("", summary="Server metadata")
async def server_metadata() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    try:
        ours = version("neumip")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        ours = "0"
    return {"name": "neumip", "version": ours, "extensions": ["binary_tensor_data"]}


@router.get("/health/live", summary="Liveness (200, empty body)")
async def live() -> Response:
    return Response(status_code=200)


@router.get("/health/ready", summary="Readiness (200 once models are loaded and warm, else 400)")
async def ready(state: ServerState = Depends(get_state)) -> Response:
    return Response(status_code=200 if state.ready else 400)


@router.get("/models/{name}", summary="Model metadata", responses=ERROR_RESPONSES)
@router.get("/models/{name}/versions/{version}", include_in_schema=False)
async def metadata(name: str, version: str | None = None, state: ServerState = Depends(serving)) -> dict:
    check_version(version)
    await asyncio.to_thread(state.registry.get, name)  # 404 unless served (loads a lazily listed one)
    return model_metadata(name, state.engine.platform)


@router.get("/models/{name}/ready", summary="Model readiness (200, else 400; 404 if unknown)")
@router.get("/models/{name}/versions/{version}/ready", include_in_schema=False)
async def model_ready(name: str, version: str | None = None, state: ServerState = Depends(serving)) -> Response:
    check_version(version)
    try:
        state.registry.check(name)
    except ApiError as exc:
        if exc.status == 400 and name in state.registry.failed:
            return Response(status_code=400)
        raise
    return Response(status_code=200)


@router.post(
    "/models/{name}/infer",
    summary="Inference (JSON, or JSON + binary tensors)",
    openapi_extra={"requestBody": INFER_BODY},
    responses=ERROR_RESPONSES,
    response_class=Response,
)
@router.post("/models/{name}/versions/{version}/infer", include_in_schema=False)
async def infer(name: str, request: Request, version: str | None = None, state: ServerState = Depends(serving)) -> Response:
    timer = StageTimer()
    check_version(version)
    async with state.registry.using(name) as material:  # loaded, and kept while in flight
        if media_type(request) not in INFER_TYPES:
            raise ApiError(415, f"infer takes {JSON_TYPE}, application/octet-stream or no Content-Type; got {media_type(request)!r}")
        header_length = json_length(request)
        body_plan = plan(request, state.settings, json=True, json_length=header_length)  # 413 / 415 from the headers
        with state.admission.admit(body_plan) as ticket:  # 503 at once if the budgets are spent
            body = await read_body(request, body_plan, ticket, state.admission)  # 408 if too slow
            timer.mark("read")
            with state.batcher.receiving() as arrival:  # batches not yet full wait for this request's rows
                if len(body) > OFFLOAD_BYTES:
                    parsed = await asyncio.to_thread(parse_infer, body, header_length)
                else:
                    parsed = parse_infer(body, header_length)
                answers = check_rows(parsed.queries, state.settings.max_rows)
                state.admission.resize(ticket, ticket.memory, answers)
                state.admission.reserve_answer(ticket, answers)  # 503 if the answers' budget is spent
                timer.mark("decode")
                ticket.until = arrival.submit(name, parsed.queries, material=material)
            rgb = await asyncio.shield(ticket.until)  # (N, 3 K) float32
            timer.mark("evaluate")
            sent = state.admission.hand_answer(ticket)  # the response frees the answer once sent
        with freed_on_failure(sent):
            response = infer_response(name, parsed, rgb, sent)
        timer.mark("encode")  # what is encoded before the answer goes out (large JSON streams after)
        response.headers.update(timer.header())
        return response
