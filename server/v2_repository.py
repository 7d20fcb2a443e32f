"""Triton's extensions to the Open Inference Protocol that tools call beside inference:
model configuration, statistics, the repository index and explicit model control (``tritonclient.http``'s
`get_model_config`, `get_inference_statistics`, `get_model_repository_index`, `load_model`,
`unload_model`).

The configuration is the same `ModelConfig` that `neumip export-repository` writes as
``config.pbtxt`` (`neumip.server.model_config`), filled in with this server's settings. The statistics
are what the batcher records (`neumip.server.model_stats`).

Model control is off unless configured, as in Triton's default mode: load and unload answer 403 until
``NEUMIP_MODEL_CONTROL=explicit`` (Triton's ``--model-control-mode=explicit``); with
``NEUMIP_MODEL_CONTROL_TOKEN`` set they also need ``Authorization: Bearer <token>``.
"""

from __future__ import annotations

import asyncio
import hmac

from fastapi import APIRouter, Depends, Request

from neumip.server.admission import plan, read_body
from neumip.server.body import parse_json
from neumip.server.errors import ApiError
from neumip.server.model_config import TritonOptions, model_config
from neumip.server.openapi import ERROR_RESPONSES
from neumip.server.registry import MODEL_VERSION, check_name
from neumip.server.state import ServerState, serving
from neumip.server.v2 import check_version

router = APIRouter(prefix="/v2", tags=["v2 (Open Inference Protocol)"])

INDEX_BODY_BYTES = 4096
"""Largest body of a repository-index request (it holds at most ``{"ready": true}``)."""


async def read_small_body(request: Request, state: ServerState, limit: int) -> bytes:
    """The whole body of a small control request, through the same admission, budgets and timeouts as
    every body; 413 past `limit` declared bytes."""
    body_plan = plan(request, state.settings, json=True)
    if (body_plan.declared or 0) > limit:
        raise ApiError(413, f"body is larger than the limit of {limit} bytes")
    with state.admission.admit(body_plan) as ticket:
        return bytes(await read_body(request, body_plan, ticket, state.admission))


@router.get("/models/{name}/config", summary="Model configuration (Triton's ModelConfig)", responses=ERROR_RESPONSES)
@router.get("/models/{name}/versions/{version}/config", include_in_schema=False)
async def config(name: str, version: str | None = None, state: ServerState = Depends(serving)) -> dict:
    """The config Triton would serve the file with (what `export-repository` writes), whatever engine this
    server runs (its model metadata names that: `Engine.platform`)."""
    check_version(version)
    await asyncio.to_thread(state.registry.get, name)  # 404 unless served (loads a lazily listed one)
    return model_config(name, TritonOptions.from_settings(state.settings))


@router.get("/models/stats", summary="Inference statistics of every model (Triton's shape)")
@router.get("/models/{name}/stats", summary="Inference statistics of one model", responses=ERROR_RESPONSES)
@router.get("/models/{name}/versions/{version}/stats", include_in_schema=False)
async def stats(name: str | None = None, version: str | None = None, state: ServerState = Depends(serving)) -> dict:
    check_version(version)
    names = [state.registry.check(name)] if name is not None else state.registry.names()
    return {"model_stats": [state.batcher.stats.json(n, MODEL_VERSION) for n in names]}


@router.post("/repository/index", summary="Every model of the repository and its state", responses=ERROR_RESPONSES)
async def repository_index(request: Request, state: ServerState = Depends(serving)) -> list[dict]:
    """Body (optional): ``{"ready": true}`` lists only the models ready to serve."""
    body = await read_small_body(request, state, INDEX_BODY_BYTES)
    options = parse_json(body) if body.strip() else {}
    if not isinstance(options, dict) or not isinstance(options.get("ready", False), bool):
        raise ApiError(400, 'the repository index body must be a JSON object like {"ready": true}')
    registry = state.registry
    index = [{"name": n, "version": MODEL_VERSION, "state": "READY"} for n in registry.names() if n in registry.materials]
    if not options.get("ready", False):
        waiting = {n: "not loaded: loads on its first request" for n in registry.names() if n not in registry.materials}
        waiting |= {n: "unloaded" for n in registry.unloaded} | dict(registry.failed)
        index += [{"name": n, "version": MODEL_VERSION, "state": "UNAVAILABLE", "reason": r} for n, r in waiting.items()]
    return sorted(index, key=lambda m: m["name"])


def check_control(request: Request, state: ServerState) -> None:
    """403 unless the settings allow explicit model control, and the request carries the token if one is set."""
    settings = state.settings
    if settings.model_control != "explicit":
        raise ApiError(403, "model control is off: load and unload need NEUMIP_MODEL_CONTROL=explicit")
    token = settings.model_control_token
    if token is not None:
        given = request.headers.get("authorization", "")
        if not hmac.compare_digest(given.encode(), f"Bearer {token.get_secret_value()}".encode()):
            raise ApiError(403, "model control needs the header Authorization: Bearer <NEUMIP_MODEL_CONTROL_TOKEN>")


@router.post("/repository/models/{name}/load", summary="Load (or reload) a model now", responses=ERROR_RESPONSES)
async def load(name: str, request: Request, state: ServerState = Depends(serving)) -> dict:
    """Read `name`.onnx from the model folder now and serve it (a changed file replaces the model
    atomically; a file that fails leaves a loaded older model serving): 404 without a file, 400 if it
    cannot be served. The body (tritonclient sends ``{}`` or parameters) is read and ignored. 403 without
    explicit model control (`check_control`)."""
    check_control(request, state)
    await read_small_body(request, state, INDEX_BODY_BYTES)
    await asyncio.to_thread(state.registry.load_material, check_name(name))
    return {}


@router.post("/repository/models/{name}/unload", summary="Unload a model", responses=ERROR_RESPONSES)
async def unload(name: str, request: Request, state: ServerState = Depends(serving)) -> dict:
    """Stop serving `name` and free its model; requests in flight finish on it. It is not served
    again until loaded (``.../load``). 403 without explicit model control (`check_control`)."""
    check_control(request, state)
    await read_small_body(request, state, INDEX_BODY_BYTES)
    state.registry.unload(name)
    return {}
