"""Running the app under uvicorn: settings from the environment plus command-line overrides."""

from __future__ import annotations

import logging
import signal

from neumip.client.cli import CommandError

log = logging.getLogger(__name__)


def run(overrides: dict) -> int:
    """Serve until SIGINT/SIGTERM (then drain for ``graceful_shutdown_s``); returns an exit status."""
    try:
        import uvicorn
        from pydantic import ValidationError

        from .app import create_app
        from .settings import Settings
    except ImportError as exc:
        raise CommandError(f"{exc}: install the server extra: pip install 'neumip[serve]'") from exc

    try:
        settings = Settings(**overrides)
    except ValidationError as exc:
        raise CommandError(f"invalid server settings: {exc}") from exc
    if not settings.model_dir.is_dir():
        raise CommandError(f"model folder {settings.model_dir} does not exist (set --model-dir or NEUMIP_MODEL_DIR)")
    logging.getLogger().setLevel(settings.log_level.upper())
    config = uvicorn.Config(
        create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level.lower(),
        timeout_graceful_shutdown=settings.graceful_shutdown_s,
        access_log=False,
    )
    server = uvicorn.Server(config)
    # uvicorn drains on SIGTERM, then re-raises the signal under the handler that was in place
    # before it started: make that one a no-op so a graceful stop exits with status 0.
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: log.info("stopped by SIGTERM"))
    try:
        server.run()
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0 if server.started else 1
