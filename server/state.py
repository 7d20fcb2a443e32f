"""What the request handlers share: settings, metrics, and (after start-up) the registry and batcher.

One `ServerState` lives in ``app.state.neumip``; handlers get it through the `get_state` dependency.
"""

from __future__ import annotations

from dataclasses import dataclass

from fastapi import Request

from .admission import Admission
from .batching import Batcher
from .engine import Engine
from .errors import ApiError
from .metrics import Metrics
from .registry import Registry
from .settings import Settings


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
    registry: Registry | None = None
    """Loaded materials; None until start-up has loaded them."""
    batcher: Batcher | None = None
    """The batching queue in front of the engine; None until start-up."""
    started: bool = False
    """Start-up (load and warm-up) finished and shutdown has not begun."""

    @property
    def ready(self) -> bool:
        """Ready to answer: started and serving at least one material (loaded, or loadable on request)."""
        return self.started and self.registry is not None and bool(self.registry.names())


async def get_state(request: Request) -> ServerState:
    """FastAPI dependency: the shared state (async: a sync dependency costs a thread-pool hop per request)."""
    return request.app.state.neumip


async def serving(request: Request) -> ServerState:
    """FastAPI dependency: the shared state once models are loaded (503 before that); async, as above."""
    state: ServerState = request.app.state.neumip
    if not state.started:
        raise ApiError(503, "server is starting or shutting down: models are not loaded")
    return state
