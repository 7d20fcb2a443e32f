"""What the request handlers share: settings, metrics, and (after start-up) the registry and batcher.

One `ServerState` lives in ``app.state.neumip``; handlers get it through the `get_state` dependency.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from fastapi import Request, Response
from fastapi.responses import JSONResponse

from neumip.server.admission import Admission
from neumip.server.batching import Batcher
from neumip.server.engine import Engine
from neumip.server.errors import ApiError
from neumip.server.metrics import Metrics
from neumip.server.registry import Registry
from neumip.server.settings import Settings
from neumip.server.shared_memory import SharedMemory


@dataclass
class ServerState:
    """The server's shared state, filled in by the app's lifespan."""

    settings: Settings
    """Settings read once at start-up."""
    metrics: Metrics
    """Prometheus collectors of this app."""
    admission: Admission
    """The budgets of body memory and queued rows that requests reserve from."""
    engine: Engine
    """What loads and evaluates the materials (``NEUMIP_ENGINE``)."""
    shared_memory: SharedMemory = field(default_factory=lambda: SharedMemory(False))
    """The registered shared-memory regions (`Settings.allow_shared_memory`)."""
    registry: Registry | None = None
    """Loaded materials; None until start-up has loaded them."""
    batcher: Batcher | None = None
    """The batching queue in front of the engine; None until start-up."""
    started: bool = False
    """Start-up (load and warm-up) finished and shutdown has not begun."""
    load_in_background: bool = False
    """Load the models after start-up instead of during it, so the port answers while they load
    (`neumip serve`); in-process apps (tests) load them in the lifespan, before their first request."""
    loading: bool = False
    """The models are loading in the background."""
    load_error: str | None = None
    """Why loading the models failed (the server never becomes ready); None if it did not fail."""
    stop: Callable[[], None] | None = None
    """Asks the server running the app to exit (set by `neumip serve`); a failed background load calls it."""

    @property
    def ready(self) -> bool:
        """Ready to answer: started and serving at least one material (loaded, or loadable on request)."""
        return self.started and self.registry is not None and bool(self.registry.names())

    def not_serving(self) -> tuple[str, str]:
        """Why the models cannot be used now: (status, reason), e.g. ``("loading", "models are loading ...")``."""
        if self.loading:
            return "loading", "models are loading and warming up: retry when GET /v2/health/ready answers 200"
        if self.load_error is not None:
            return "failed", f"loading the models failed: {self.load_error}"
        if self.registry is not None:  # it was serving: shutdown has begun
            return "stopping", "the server is shutting down"
        return "starting", "the server is starting: models are not loaded yet"

    def readiness(self) -> Response:
        """``/v2/health/ready``: 200 with an empty body (as Triton) when ready; while the models load, or
        after a failed load or during shutdown, 503 ``{"status": ..., "reason": ...}``; started with no
        material to serve, 400 with the reason (Triton's not-ready status)."""
        if self.ready:
            return Response(status_code=200)
        if self.started:
            reason = "no material can be served from the model folder (yet): see GET /v1/materials"
            return JSONResponse({"status": "no materials", "reason": reason}, status_code=400)
        status, reason = self.not_serving()
        return JSONResponse({"status": status, "reason": reason}, status_code=503)


async def get_state(request: Request) -> ServerState:
    """FastAPI dependency: the shared state (async: a sync dependency costs a thread-pool hop per request)."""
    return request.app.state.neumip


async def serving(request: Request) -> ServerState:
    """FastAPI dependency: the shared state once models are loaded (503 before that); async, as above."""
    state: ServerState = request.app.state.neumip
    if not state.started:
        status, reason = state.not_serving()
        retry = {"Retry-After": str(state.settings.retry_after_s)} if status in ("loading", "starting") else None
        raise ApiError(503, reason, retry)
    return state
