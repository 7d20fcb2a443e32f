"""The renderer fast path (``/v1``): msgpack in, msgpack out; JSON for people trying it with curl.

``POST /v1/materials/{name}/evaluate`` with ``Content-Type: application/msgpack`` takes the
`wire.encode_request` body and answers `wire.encode_response`; with ``application/json`` it
takes ``{"queries": [[u, v, sigma, wi_x, wi_y, wo_x, wo_y], ...]}`` and answers
``{"n": N, "rgb": [[r, g, b], ...]}``. Query groups (`neumip.core.contract`) go the same way: rows of
``5 + 2 K`` values in (msgpack: the width stated by ``"lights": K``, or read from the byte count,
`neumip.core.wire`), ``3 K`` out. ``GET /v1/materials`` lists the materials with their metadata.
"""

from __future__ import annotations

import asyncio

import numpy as np
from fastapi import APIRouter, Depends, Request, Response

from neumip.core import contract as C
from neumip.core import wire

from neumip.server.admission import plan, read_body
from neumip.server.answer import BufferAnswer, JsonAnswer, freed_on_failure
from neumip.server.body import JSON_TYPE, MSGPACK_TYPES, check_rows, media_type, parse_json
from neumip.server.errors import ApiError
from neumip.server.metrics import StageTimer
from neumip.server.openapi import ERROR_RESPONSES, EVALUATE_BODY, EVALUATE_RESPONSE
from neumip.server.state import ServerState, serving

router = APIRouter(tags=["v1 (renderer fast path)"])

OFFLOAD_BYTES = 1 << 20
"""JSON bodies larger than this are decoded in a thread, keeping the event loop free (answers: `answer`)."""


def decode_json(body: bytes) -> np.ndarray:
    """``{"queries": [[7 numbers], ...]}`` -> validated (N, 7) float32, or rows of 5 + 2 K numbers ->
    (N, 5 + 2 K) query groups. Raises ApiError/QueryError."""
    msg = parse_json(body)
    if not isinstance(msg, dict) or not isinstance(msg.get("queries"), list):
        raise ApiError(400, 'JSON body must be an object {"queries": [[u, v, sigma, wi_x, wi_y, wo_x, wo_y], ...]}')
    rows = msg["queries"]
    width = len(rows[0]) if rows and isinstance(rows[0], list) else C.QUERY_DIM
    if any(not isinstance(row, list) or len(row) != width for row in rows):
        raise ApiError(400, f"every entry of 'queries' must be a list of {C.QUERY_DIM} numbers "
                       f"({', '.join(C.QUERY_FIELDS)}), or of 5 + 2 K numbers for query groups of K lights, "
                       "the same in every row")
    C.group_lights(width)  # QueryError (400) for a width no group has
    if any(isinstance(x, bool) or not isinstance(x, (int, float)) for row in rows for x in row):
        raise ApiError(400, "'queries' must hold only numbers")
    if "n" in msg and msg["n"] != len(rows):
        raise ApiError(400, f"'n' is {msg['n']!r} but 'queries' holds {len(rows)} rows")
    try:
        with np.errstate(over="ignore"):  # out-of-range floats become Inf and are rejected as such
            arr = np.array(rows, dtype=np.float64).reshape(len(rows), width).astype(C.DTYPE)
    except OverflowError:  # an integer literal beyond float64
        raise ApiError(400, "'queries' holds a number outside the float range; values must be finite") from None
    return C.as_queries(arr, groups=True)


async def decode(body: bytes | bytearray, kind: str) -> np.ndarray:
    """Body -> validated (N, 7) float32 queries or (N, 5 + 2 K) groups; a large JSON body is parsed in a
    thread.

    msgpack is decoded on the event loop whatever its size: the rows are a view of the body (no
    copy), leaving only the value checks, cheaper than a hop to a thread and back.
    """
    if kind == "msgpack":
        return wire.decode_request(body)
    if len(body) > OFFLOAD_BYTES:
        return await asyncio.to_thread(decode_json, body)
    return decode_json(body)


def body_kind(request: Request) -> str:
    """'msgpack' or 'json' from the Content-Type; 415 for anything else."""
    ctype = media_type(request)
    if ctype in MSGPACK_TYPES:
        return "msgpack"
    if ctype == JSON_TYPE:
        return "json"
    got = f"got {ctype!r}" if ctype else "it is missing"
    raise ApiError(415, f"Content-Type must be {wire.MSGPACK_MEDIA_TYPE} or {JSON_TYPE}; {got}")


@router.get(wire.MATERIALS_PATH, summary="List the served materials with their metadata")
async def list_materials(state: ServerState = Depends(serving)) -> dict:
    return state.registry.listing()


@router.get(wire.MATERIALS_PATH + "/{name}", summary="Metadata of one material", responses=ERROR_RESPONSES)
async def material_info(name: str, state: ServerState = Depends(serving)) -> dict:
    return await asyncio.to_thread(state.registry.info, name)


@router.post(
    wire.EVALUATE_PATH,
    summary="Evaluate (N, 7) queries -> (N, 3) RGB, or (N, 5 + 2 K) query groups -> (N, 3 K) "
    "(msgpack or JSON)",
    openapi_extra={"requestBody": EVALUATE_BODY},
    responses={200: EVALUATE_RESPONSE, **ERROR_RESPONSES},
    response_class=Response,
)
async def evaluate(name: str, request: Request, state: ServerState = Depends(serving)) -> Response:
    timer = StageTimer()
    async with state.registry.using(name) as material:  # loaded, and kept while in flight
        kind = body_kind(request)
        body_plan = plan(request, state.settings, json=kind == "json")  # 413 / 415 from the headers alone
        with state.admission.admit(body_plan) as ticket:  # 503 at once if the budgets are spent
            body = await read_body(request, body_plan, ticket, state.admission)  # 408 if too slow
            timer.mark("read")
            with state.batcher.receiving() as arrival:  # batches not yet full wait for this request's rows
                queries = await decode(body, kind)  # (N, 5 + 2 K) float32, K = 1: (N, 7)
                answers = check_rows(queries.shape, state.settings.max_rows)
                state.admission.resize(ticket, ticket.memory, answers)
                state.admission.reserve_answer(ticket, answers)  # 503 if the answers' budget is spent
                timer.mark("decode")
                # msgpack: the workers write the answer straight into the response body (out: a view of it)
                content, out = None, None
                if kind == "msgpack":
                    content, out = wire.response_buffer(queries.shape[0], C.group_lights(queries.shape[1]))
                ticket.until = arrival.submit(name, queries, out=out, material=material)
            rgb = await asyncio.shield(ticket.until)  # (N, 3 K) float32
            timer.mark("evaluate")
            sent = state.admission.hand_answer(ticket)  # the response frees the answer once sent
        with freed_on_failure(sent):
            if kind == "msgpack":
                response = BufferAnswer([content], wire.MSGPACK_MEDIA_TYPE, sent)
            else:
                response = JsonAnswer(f'{{"n":{rgb.shape[0]},"rgb":', rgb, "}", sent)
        timer.mark("encode")  # what is encoded before the answer goes out (large JSON streams after)
        response.headers.update(timer.header())
        return response
