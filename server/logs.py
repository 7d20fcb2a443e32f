"""The request log: every answer with a 4xx or 5xx status, at INFO, with what the client was told.

One line per error answer: ``POST /v1/materials/nope/evaluate -> 404: unknown material 'nope' ...``
(method, path, status, the first line of the answer's ``error`` or ``reason``). Successful requests
are logged only with ``NEUMIP_ACCESS_LOG=true``; `/metrics` counts every request either way. Errors
that uvicorn's protocol answers before the app runs (`protocol.py`: malformed requests, header limits
and timeouts) do not pass through here.
"""

from __future__ import annotations

import json
import logging

log = logging.getLogger(__name__)

KEPT_BYTES = 1024
"""Bytes of an error answer's body kept to find its message (error bodies are small JSON)."""
MESSAGE_CHARS = 300
"""Most characters of the message put in the log line."""


def message_of(body: bytes) -> str:
    """The first line of an error body: its ``error`` (or ``reason``) if it is JSON, else its text."""
    text = body.decode("utf-8", errors="replace")
    try:
        parsed = json.loads(text)
    except ValueError:  # not JSON, or cut at KEPT_BYTES
        parsed = None
    if isinstance(parsed, dict):
        text = str(parsed.get("error", parsed.get("reason", text)))
    return first_line(text)


def first_line(text: str) -> str:
    """The first non-empty line of `text`, at most MESSAGE_CHARS long, control characters escaped."""
    lines = text.strip().splitlines()
    return printable(lines[0][:MESSAGE_CHARS]) if lines else ""


def printable(text: str) -> str:
    """`text` with control characters escaped (``\\n``, ``\\x1b``): a client's path or name cannot forge
    log lines."""
    return text if text.isprintable() else "".join(c if c.isprintable() else ascii(c)[1:-1] for c in text)


class RequestLogMiddleware:
    """Pure ASGI middleware logging each 4xx/5xx answer (and, with `access_log`, every answer) at INFO."""

    def __init__(self, app, access_log: bool = False) -> None:
        self.app = app
        self.access_log = access_log

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 0
        body = bytearray()  # the start of an error answer's body

        async def send_and_watch(message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            elif status >= 400 and len(body) < KEPT_BYTES:
                body.extend(message.get("body", b"")[:KEPT_BYTES - len(body)])
            await send(message)

        try:
            await self.app(scope, receive, send_and_watch)
        except Exception as exc:  # answered 500 by the app's last-resort handler, outside this middleware
            if status == 0:
                log.info("%s %s -> 500: %s", scope["method"], printable(scope["path"]),
                         first_line(f"{type(exc).__name__}: {exc}"))
            raise
        if status >= 400:
            log.info("%s %s -> %d: %s", scope["method"], printable(scope["path"]), status, message_of(bytes(body)))
        elif self.access_log and status:
            log.info("%s %s -> %d", scope["method"], printable(scope["path"]), status)
