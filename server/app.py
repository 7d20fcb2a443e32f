"""The FastAPI application: lifespan (load, warm up, batch), routes, errors and metrics.

``create_app(settings)`` builds an app; `neumip serve` serves it with uvicorn and neumip's protocol
class (`uvicorn_run.py`), which enforces the write timeout and the header limits: plain ``uvicorn
--factory neumip.server.app:create_app`` would serve without them. Models load and warm up in the lifespan,
before the first request; under `neumip serve` (``load_in_background``) in a task the lifespan starts, so
the port answers while they load: liveness 200, readiness and the model endpoints 503 saying so.
``/v2/health/ready`` says yes only after that and until shutdown begins. OpenAPI docs: ``/docs`` and
``/redoc`` (their scripts served by the app itself, no CDN) and ``/openapi.json``.
"""

from __future__ import annotations

import asyncio
import logging
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI, Response
from fastapi_offline import FastAPIOffline

from neumip.server.admission import Admission
from neumip.server.batching import Batcher
from neumip.server.engine import Engine
from neumip.server.errors import install_error_handlers
from neumip.server.logs import RequestLogMiddleware
from neumip.server.metrics import Metrics, MetricsMiddleware
from neumip.server.registry import Registry
from neumip.server.settings import Settings
from neumip.server.shared_memory import SharedMemory
from neumip.server.state import ServerState, get_state
from neumip.server import v1, v2, v2_repository

log = logging.getLogger(__name__)

READY_PATH = "/v2/health/ready"
"""The readiness endpoint (Open Inference Protocol), answered by `ServerState.readiness`."""


@asynccontextmanager
async def lifespan(app: FastAPI):
    """Load and warm up every material and start the batcher (in a background task with
    ``load_in_background``); on shutdown, drain and stop it."""
    state: ServerState = app.state.neumip
    tasks: list[asyncio.Task] = []  # the background load, the folder poller
    if state.load_in_background:
        state.loading = True
        tasks.append(asyncio.create_task(load_in_background(state, tasks)))
    else:
        await start_serving(state, tasks)
    try:
        yield
    finally:
        state.started = False
        for task in tasks:
            task.cancel()  # a load in progress finishes in its thread, unused
        if state.batcher is not None:
            await state.batcher.close()
            log.info("batcher stopped")
        state.shared_memory.close()


async def start_serving(state: ServerState, tasks: list[asyncio.Task]) -> None:
    """Load and warm up every material (in a thread), start the batcher and the folder poller (added to
    `tasks`)."""
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
    if settings.poll_s:
        tasks.append(asyncio.create_task(follow_folder(registry, settings.poll_s)))


async def load_in_background(state: ServerState, tasks: list[asyncio.Task]) -> None:
    """`start_serving` while the server answers; a failure is logged, kept for the readiness answer, and
    stops the server (`ServerState.stop`)."""
    try:
        await start_serving(state, tasks)
    except Exception as exc:
        state.load_error = f"{type(exc).__name__}: {exc}"
        log.exception("loading the models failed: the server will not become ready")
        if state.stop is not None:
            state.stop()
    finally:
        state.loading = False
    if state.started:
        log.info("models loaded: ready (GET %s)", READY_PATH)


async def follow_folder(registry: Registry, interval_s: float) -> None:
    """List the model folder every `interval_s` seconds (`Registry.poll`, in a thread)."""
    while True:
        await asyncio.sleep(interval_s)
        try:
            await asyncio.to_thread(registry.poll)
        except Exception:  # a folder gone for a moment must not end the polling
            log.exception("polling the model folder failed")


def create_app(settings: Settings | None = None, load_in_background: bool = False) -> FastAPI:
    """A new server app; `settings` default to the ``NEUMIP_*`` environment. `load_in_background`: the
    lifespan returns at once and the models load while the app answers (``ServerState.load_in_background``).
    Raises EngineUnavailable if ``NEUMIP_ENGINE`` cannot run here."""
    settings = settings or Settings()
    engine = Engine.from_settings(settings)
    metrics = Metrics()
    app = FastAPIOffline(  # FastAPI with /docs and /redoc served from files of its own package, no CDN
        title="neumip inference server",
        summary="NeuMIP neural materials: (N, 7) shading queries -> (N, 3) RGB, or query groups "
                "(N, 5 + 2K) -> (N, 3K)",
        lifespan=lifespan,
        redirect_slashes=False,  # a trailing slash is 404, not a 307 to the path without it
    )
    app.state.neumip = ServerState(settings, metrics, Admission(settings, metrics, engine.idle), engine,
                                   SharedMemory(settings.allow_shared_memory), load_in_background=load_in_background)
    install_error_handlers(app)
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(RequestLogMiddleware, access_log=settings.access_log)

    # Readiness says why it is not ready (503 + JSON while the models load). Routes match in order, so
    # this one answers before v2.py's (which answers only 200/400, and still documents the path).
    @app.get(READY_PATH, include_in_schema=False)
    async def readiness(state: ServerState = Depends(get_state)) -> Response:
        return state.readiness()

    app.include_router(v1.router)
    app.include_router(v2_repository.router)  # before v2: /v2/models/stats is not a model named "stats"
    app.include_router(v2.router)

    @app.get("/metrics", summary="Prometheus metrics", tags=["operations"])
    async def prometheus(state: ServerState = Depends(get_state)) -> Response:
        content, media = state.metrics.render()
        return Response(content, media_type=media)

    return app
