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
REGISTER_BYTES = 4096
"""Largest shared-memory register request body."""
EXTENSIONS = ("binary_tensor_data", "model_repository", "model_configuration", "statistics")
"""Triton's protocol extensions the server speaks, as ``GET /v2`` lists them (by Triton's names): binary tensors
(here), the model repository, configuration and statistics (`v2_repository`); and ``system_shared_memory`` where
allowed (`shared_memory`)."""
INFER_TYPES = (None, JSON_TYPE, "application/octet-stream")
"""Content types an infer request may carry (tritonclient sends none)."""


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


# --- encode -----------------------------------------------------------------------------------
def infer_response(name: str, request: wire.InferRequest, rgb: np.ndarray, on_sent: Callable[[], None]) -> Answer:
    """(N, 3 K) RGB -> the infer response, JSON (streamed when large) or JSON + binary tail."""
    head = wire.infer_response_head(name, MODEL_VERSION, request, rgb)
    if request.output_region is not None:  # the answers went to shared memory
        return BufferAnswer([json.dumps(head, separators=(",", ":")).encode()], JSON_TYPE, on_sent)
    if not request.binary_output:
        prefix, suffix = json.dumps(head, separators=(",", ":")).rsplit('"@"', 1)
        return JsonAnswer(prefix, rgb.reshape(-1), suffix, on_sent)
    header = json.dumps(head, separators=(",", ":")).encode()
    return BufferAnswer([header, rgb], "application/octet-stream", on_sent, {HEADER_LENGTH: str(len(header))})


# --- routes -----------------------------------------------------------------------------------
@router.get("", summary="Server metadata")
async def server_metadata(state: ServerState = Depends(get_state)) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    try:
        ours = version("neumip")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        ours = "0"
    extensions = list(EXTENSIONS) + ["system_shared_memory"] * state.shared_memory.allowed
    return {"name": "neumip", "version": ours, "extensions": extensions}


# --- Triton's system shared-memory extension (`shared_memory`) --------------------------------
@router.get("/systemsharedmemory/status", summary="Shared memory: every registered region")
@router.get("/systemsharedmemory/region/{region}/status", summary="Shared memory: one registered region")
async def shared_memory_status(region: str | None = None, state: ServerState = Depends(get_state)) -> list[dict]:
    return state.shared_memory.status(region)


@router.post("/systemsharedmemory/region/{region}/register", summary="Shared memory: register a region",
             responses=ERROR_RESPONSES)
async def shared_memory_register(region: str, request: Request, state: ServerState = Depends(get_state)) -> Response:
    state.shared_memory.check_allowed()
    body_plan = plan(request, state.settings, json=True)  # read as any body is: its timeout, a client gone
    if (body_plan.declared or 0) > REGISTER_BYTES:
        raise ApiError(413, f"a register request is a JSON object of at most {REGISTER_BYTES} bytes")
    with state.admission.admit(body_plan) as ticket:  # a chunked one: 413 past REGISTER_BYTES as it arrives
        body = await read_body(request, body_plan, ticket, state.admission, limit=REGISTER_BYTES)
    state.shared_memory.register(region, parse_json(body))
    return Response(status_code=200)


@router.post("/systemsharedmemory/unregister", summary="Shared memory: unregister every region")
@router.post("/systemsharedmemory/region/{region}/unregister", summary="Shared memory: unregister a region")
async def shared_memory_unregister(region: str | None = None, state: ServerState = Depends(get_state)) -> Response:
    state.shared_memory.unregister(region)
    return Response(status_code=200)


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
                    parsed = await asyncio.to_thread(wire.decode_infer_request, body, header_length)
                else:
                    parsed = wire.decode_infer_request(body, header_length)
                answers = check_rows(parsed.shape, state.settings.max_rows)
                if parsed.output_region is not None:
                    state.shared_memory.check_answer(parsed.output_region, answers * C.RGB_DIM * C.DTYPE.itemsize)
                if parsed.input_region is None:
                    state.admission.resize(ticket, ticket.memory, answers)
                else:  # the queries, read from shared memory, take memory as a body does
                    state.admission.resize(ticket, ticket.memory + parsed.input_region.byte_size, answers)
                    parsed.queries = await state.shared_memory.read_queries(parsed.input_region, parsed.shape)
                state.admission.reserve_answer(ticket, answers)  # 503 if the answers' budget is spent
                timer.mark("decode")
                ticket.until = arrival.submit(name, parsed.queries, material=material)
            rgb = await asyncio.shield(ticket.until)  # (N, 3 K) float32
            timer.mark("evaluate")
            if parsed.output_region is not None:
                await state.shared_memory.write_answer(parsed.output_region, rgb)
            sent = state.admission.hand_answer(ticket)  # the response frees the answer once sent
        with freed_on_failure(sent):
            response = infer_response(name, parsed, rgb, sent)
        timer.mark("encode")  # what is encoded before the answer goes out (large JSON streams after)
        response.headers.update(timer.header())
        return response
