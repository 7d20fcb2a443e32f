"""The FastAPI application: lifespan (load, warm up, batch), routes, errors and metrics.

``create_app(settings)`` builds an app; `neumip serve` serves it with uvicorn and neumip's protocol
class (`uvicorn_run.py`), which enforces the write timeout and the header limits: plain ``uvicorn
--factory neumip.server.app:create_app`` would serve without them. Models load and warm up in the lifespan, before
uvicorn accepts connections; ``/v2/health/ready`` says yes only after that and until shutdown begins.
OpenAPI docs: ``/docs`` and ``/openapi.json``.
"""

from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI, Response

from .admission import Admission
from .batching import Batcher
from .engine import Engine
from .errors import install_error_handlers
from .metrics import Metrics, MetricsMiddleware
from .registry import Registry
from .settings import Settings
from .state import ServerState, get_state
from . import v1, v2, v2_repository

log = logging.getLogger(__name__)


@asynccontextmanager
async def lifespan(app: FastAPI):
    """Load and warm up every material, start the batcher; on shutdown, drain and stop it."""
    state: ServerState = app.state.neumip
    settings = state.settings
    registry = await asyncio.to_thread(
        Registry.load, settings.model_dir, state.engine, settings.warmup_rows, settings.load == "lazy",
        int(settings.memory_budget_mb * 2**20), state.metrics,
    )
    batcher = Batcher(registry.materials, settings, state.metrics, state.engine)
    batcher.start()
    state.registry, state.batcher, state.started = registry, batcher, True
    if not registry.names():
        log.warning("no material can be served from %s (yet): the server will not report ready", settings.model_dir)
    poller = asyncio.create_task(follow_folder(registry, settings.poll_s)) if settings.poll_s else None
    try:
        yield
    finally:
        state.started = False
        if poller is not None:
            poller.cancel()
        await batcher.close()
        log.info("batcher stopped")


async def follow_folder(registry: Registry, interval_s: float) -> None:
    """List the model folder every `interval_s` seconds (`Registry.poll`, in a thread)."""
    while True:
        await asyncio.sleep(interval_s)
        try:
            await asyncio.to_thread(registry.poll)
        except Exception:  # a folder gone for a moment must not end the polling
            log.exception("polling the model folder failed")


def create_app(settings: Settings | None = None) -> FastAPI:
    """A new server app; `settings` default to the ``NEUMIP_*`` environment. Raises EngineUnavailable
    if ``NEUMIP_ENGINE`` cannot run here."""
    settings = settings or Settings()
    engine = Engine.from_settings(settings)
    metrics = Metrics()
    app = FastAPI(
        title="neumip inference server",
        summary="NeuMIP neural materials: (N, 7) shading queries -> (N, 3) RGB, or query groups "
                "(N, 5 + 2K) -> (N, 3K)",
        lifespan=lifespan,
        redirect_slashes=False,  # a trailing slash is 404, not a 307 to the path without it
    )
    app.state.neumip = ServerState(settings, metrics, Admission(settings, metrics), engine)
    install_error_handlers(app)
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.include_router(v1.router)
    app.include_router(v2_repository.router)  # before v2: /v2/models/stats is not a model named "stats"
    app.include_router(v2.router)

    @app.get("/metrics", summary="Prometheus metrics", tags=["operations"])
    async def prometheus(state: ServerState = Depends(get_state)) -> Response:
        content, media = state.metrics.render()
        return Response(content, media_type=media)

    return app
