"""Running the app under uvicorn: settings from the environment plus command-line overrides."""

from __future__ import annotations

import logging
import signal
import socket

from neumip.core.errors import NeumipError

log = logging.getLogger(__name__)

BACKLOG = 2048
"""Connections the kernel queues before uvicorn accepts them (uvicorn's own default)."""


class ServeError(NeumipError):
    """`neumip serve` cannot start: bad settings, a missing model folder, a port it cannot listen on."""


def listen(host: str, port: int) -> socket.socket:
    """A TCP socket bound to (host, port) and listening, before anything slow runs: connections wait in
    its backlog until uvicorn accepts them, never refused or reset. ServeError if the port is taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn: restart at once after a stop
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise ServeError(
            f"cannot listen on {host}:{port}: {exc.strerror or exc} (is another server running there? "
            "choose another --port or NEUMIP_PORT)"
        ) from None
    sock.listen(BACKLOG)
    return sock


def run(overrides: dict) -> int:
    """Serve until SIGINT/SIGTERM (then drain for ``graceful_shutdown_s``); returns an exit status."""
    try:
        import uvicorn
        from pydantic import ValidationError

        from neumip.server.app import create_app
        from neumip.server.protocol import protocol_class
        from neumip.server.settings import Settings
    except ImportError as exc:
        raise ServeError(f"{exc}: install the server extra: pip install 'neumip[serve]'") from exc

    try:
        settings = Settings(**overrides)
    except ValidationError as exc:
        raise ServeError(f"invalid server settings: {exc}") from exc
    if not settings.model_dir.is_dir():
        raise ServeError(f"model folder {settings.model_dir} does not exist (set --model-dir or NEUMIP_MODEL_DIR)")
    # The models load after uvicorn starts: the port answers meanwhile (readiness: 503 "loading").
    app = create_app(settings, load_in_background=True)  # EngineUnavailable (one line) if it cannot run here
    sock = listen(settings.host, settings.port)
    logging.getLogger().setLevel(settings.log_level.upper())
    host = f"[{settings.host}]" if ":" in settings.host else settings.host
    log.info("listening on http://%s:%d (models load now; ready when GET /v2/health/ready answers 200)",
             host, settings.port)
    config = uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        http=protocol_class(settings),
        log_level=settings.log_level.lower(),
        timeout_keep_alive=settings.keep_alive_s,
        timeout_graceful_shutdown=settings.graceful_shutdown_s,
        access_log=False,
    )
    server = uvicorn.Server(config)
    state = app.state.neumip
    state.stop = lambda: setattr(server, "should_exit", True)  # a failed load ends the process (status 1)
    # uvicorn drains on SIGTERM, then re-raises the signal under the handler that was in place
    # before it started: make that one a no-op so a graceful stop exits with status 0.
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: log.info("stopped by SIGTERM"))
    try:
        server.run(sockets=[sock])
    finally:
        signal.signal(signal.SIGTERM, previous)
        sock.close()
    return 0 if server.started and state.load_error is None else 1
