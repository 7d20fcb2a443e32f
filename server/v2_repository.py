"""Triton's extensions to the Open Inference Protocol that tools call beside inference:
model configuration, statistics and the repository index (``tritonclient.http``'s
`get_model_config`, `get_inference_statistics`, `get_model_repository_index`).

The configuration is the same `ModelConfig` that `neumip export-repository` writes as
``config.pbtxt`` (`neumip.server.model_config`), filled in with this server's settings; the statistics
are what the batcher records (`neumip.server.model_stats`).
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request
from starlette.requests import ClientDisconnect

from .body import parse_json
from .errors import ApiError
from .model_config import TritonOptions, model_config
from .openapi import ERROR_RESPONSES
from .registry import MODEL_VERSION
from .state import ServerState, serving
from .v2 import check_version

router = APIRouter(prefix="/v2", tags=["v2 (Open Inference Protocol)"])

INDEX_BODY_BYTES = 4096
"""Largest body of a repository-index request (it holds at most ``{"ready": true}``)."""


async def read_small_body(request: Request, limit: int) -> bytes:
    """The whole body of a small control request; 413 past `limit` bytes (declared or arrived)."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise ApiError(413, f"body is larger than the limit of {limit} bytes")
    chunks, size = [], 0
    try:
        async for chunk in request.stream():
            size += len(chunk)
            if size > limit:
                raise ApiError(413, f"body is larger than the limit of {limit} bytes")
            chunks.append(chunk)
    except ClientDisconnect:
        raise ApiError(400, f"client disconnected after {size} bytes of the body") from None
    return b"".join(chunks)


@router.get("/models/{name}/config", summary="Model configuration (Triton's ModelConfig)", responses=ERROR_RESPONSES)
@router.get("/models/{name}/versions/{version}/config", include_in_schema=False)
async def config(name: str, version: str | None = None, state: ServerState = Depends(serving)) -> dict:
    check_version(version)
    state.registry.get(name)
    return model_config(name, TritonOptions.from_settings(state.settings))


@router.get("/models/stats", summary="Inference statistics of every model (Triton's shape)")
@router.get("/models/{name}/stats", summary="Inference statistics of one model", responses=ERROR_RESPONSES)
@router.get("/models/{name}/versions/{version}/stats", include_in_schema=False)
async def stats(name: str | None = None, version: str | None = None, state: ServerState = Depends(serving)) -> dict:
    check_version(version)
    names = [state.registry.get(name).name] if name is not None else state.registry.names()
    return {"model_stats": [state.batcher.stats.json(n, MODEL_VERSION) for n in names]}


@router.post("/repository/index", summary="Every model of the repository and its state", responses=ERROR_RESPONSES)
async def repository_index(request: Request, state: ServerState = Depends(serving)) -> list[dict]:
    """Body (optional): ``{"ready": true}`` lists only the models ready to serve."""
    body = await read_small_body(request, INDEX_BODY_BYTES)
    options = parse_json(body) if body.strip() else {}
    if not isinstance(options, dict) or not isinstance(options.get("ready", False), bool):
        raise ApiError(400, 'the repository index body must be a JSON object like {"ready": true}')
    index = [{"name": n, "version": MODEL_VERSION, "state": "READY"} for n in state.registry.names()]
    if not options.get("ready", False):
        index += [
            {"name": n, "version": MODEL_VERSION, "state": "UNAVAILABLE", "reason": reason}
            for n, reason in state.registry.failed.items()
        ]
    return sorted(index, key=lambda m: m["name"])
