"""The HTTP/1.1 connection, before the app runs: header size and time limits, and JSON errors.

uvicorn's httptools protocol puts no bound on the size of a request's line and headers and none on the
time they take to arrive, and answers a request it cannot parse with a plain-text 400. `protocol_class`
gives uvicorn a subclass that:

- answers **431** once a request's line and headers pass ``max_header_bytes`` without ending (counted
  as bytes received while they are incomplete; a pipelined request may count up to one read of the
  previous body as well), then closes the connection;
- answers **408** when they take longer than ``header_timeout_s`` from the connection opening or the
  request's first byte (an idle kept-alive connection is closed after ``keep_alive_s`` by uvicorn);
- drops a connection whose client does not read its answer: when the send buffer stays above its
  high-water mark for ``write_timeout_s``, the connection is aborted (its buffered answer freed, the
  app's pending sends return at once, `answer.Answer` frees the answer's budget);
- answers every error it raises with ``{"error": "..."}``, like the app (an unparsable request line
  or header, an unknown method, a malformed Content-Length or chunk size: 400), and so does
  uvicorn's own last-resort answer: 503 for a request the shutdown cut off (a body still arriving
  when ``graceful_shutdown_s`` ran out), 500 otherwise.

Errors are written on the connection and then it is closed: the rest of such a request cannot be
trusted to mark where the next one starts. A framing error in a body the app is already reading (a bad
chunk size) is answered the same way, and the app sees the client as gone.
"""

from __future__ import annotations

import asyncio
import json
import logging

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from neumip.server.answer import PIECE_BYTES
from neumip.server.settings import Settings

STATUS_TEXT = {400: "Bad Request", 408: "Request Timeout", 431: "Request Header Fields Too Large"}

log = logging.getLogger(__name__)


def error_bytes(status: int, message: str) -> bytes:
    """A complete HTTP/1.1 error answer with a ``{"error": message}`` body that closes the connection."""
    body = json.dumps({"error": message}).encode()
    head = (
        f"HTTP/1.1 {status} {STATUS_TEXT[status]}\r\ncontent-type: application/json\r\n"
        f"content-length: {len(body)}\r\nconnection: close\r\n\r\n"
    )
    return head.encode("ascii") + body


def protocol_class(settings: Settings) -> type[asyncio.Protocol]:
    """uvicorn's httptools protocol with this server's header limits (see the module docstring)."""

    class GuardedProtocol(HttpToolsProtocol):
        max_header_bytes = settings.max_header_bytes
        header_timeout_s = settings.header_timeout_s
        write_timeout_s = settings.write_timeout_s

        def connection_made(self, transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            # answers go out in pieces of PIECE_BYTES, each written once the buffer is below the low mark:
            # the socket always has the rest of one piece queued while the next waits
            transport.set_write_buffer_limits(high=PIECE_BYTES, low=PIECE_BYTES // 4)
            self._write_timer = None
            self._shutting_down = False
            self._header_bytes = 0
            self._in_headers = True
            self._header_timer = self.loop.call_later(self.header_timeout_s, self._header_timeout)

        def connection_lost(self, exc) -> None:
            self._stop_header_timer()
            self._stop_write_timer()
            super().connection_lost(exc)

        def pause_writing(self) -> None:
            super().pause_writing()
            if self._write_timer is None:
                self._write_timer = self.loop.call_later(self.write_timeout_s, self._write_timeout)

        def resume_writing(self) -> None:
            self._stop_write_timer()
            super().resume_writing()

        def _write_timeout(self) -> None:
            self._write_timer = None
            log.warning("client %s did not read its answer for %g s: connection dropped",
                        self.client[0] if self.client else "?", self.write_timeout_s)
            self.transport.abort()  # close() would wait for the buffer to drain, which never comes

        def _stop_write_timer(self) -> None:
            if getattr(self, "_write_timer", None) is not None:
                self._write_timer.cancel()
                self._write_timer = None

        def shutdown(self) -> None:
            self._shutting_down = True
            super().shutdown()

        def data_received(self, data: bytes) -> None:
            if self._in_headers:
                self._header_bytes += len(data)
            super().data_received(data)
            if self._in_headers and self._header_bytes > self.max_header_bytes and not self.transport.is_closing():
                self._refuse(431, f"request line and headers are larger than the limit of {self.max_header_bytes} bytes")

        def on_message_begin(self) -> None:
            super().on_message_begin()
            if not self._in_headers:  # the next request on a kept-alive connection: its clock starts now
                self._in_headers, self._header_bytes = True, 0
                self._header_timer = self.loop.call_later(self.header_timeout_s, self._header_timeout)

        def on_headers_complete(self) -> None:
            self._in_headers = False
            self._stop_header_timer()
            super().on_headers_complete()
            if self.cycle is not None:  # uvicorn's last-resort answer (the app raised, or was cancelled), as JSON
                self.cycle.send_500_response = self._last_resort_response(self.cycle)

        def _last_resort_response(self, cycle):
            async def send() -> None:
                status, message = 500, "internal server error"
                if self._shutting_down:
                    status, message = 503, "the server shut down before this request was answered; retry"
                body = json.dumps({"error": message}).encode()
                await cycle.send({"type": "http.response.start", "status": status, "headers": [
                    (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close")]})
                await cycle.send({"type": "http.response.body", "body": body})

            return send

        def send_400_response(self, msg: str) -> None:
            self._stop_header_timer()
            self._refuse(400, "invalid HTTP request: the request line, a header, the method, the Content-Length or "
                         "the chunked framing could not be parsed")

        def _header_timeout(self) -> None:
            self._header_timer = None
            if not self.transport.is_closing():
                self._refuse(408, f"request line and headers not complete after {self.header_timeout_s:g} s")

        def _stop_header_timer(self) -> None:
            if getattr(self, "_header_timer", None) is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _refuse(self, status: int, message: str) -> None:
            self._stop_header_timer()
            self.logger.warning("%s %s", status, message)
            cycle = self.cycle
            if cycle is not None and not cycle.response_complete:  # the app is reading this request's body
                if cycle.response_started:  # never inside an answer the app is writing: just close
                    self.transport.close()
                    return
                cycle.disconnected = True  # the app's reads now end, its writes go nowhere
                cycle.message_event.set()
            self.transport.write(error_bytes(status, message))
            self.transport.close()

    return GuardedProtocol
