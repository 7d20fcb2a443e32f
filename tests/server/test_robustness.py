"""Malformed HTTP at the socket level against a real server (Triton's L0_http style): each gets an
answer or a closed connection, never a hang or a crash, and the server stays live after every one."""

from __future__ import annotations

import json
import socket

import httpx
import pytest

from neumip.core import wire

PATH = wire.EVALUATE_PATH.format(name="rand16")
RAW = {
    "garbage request line": b"\x00\x01\x02 not http\r\n\r\n",
    "bad content-length": f"POST {PATH} HTTP/1.1\r\nHost: x\r\nContent-Type: application/msgpack\r\nContent-Length: abc\r\n\r\n".encode(),
    "negative content-length": f"POST {PATH} HTTP/1.1\r\nHost: x\r\nContent-Type: application/msgpack\r\nContent-Length: -5\r\n\r\n".encode(),
    "body shorter than declared, then close": f"POST {PATH} HTTP/1.1\r\nHost: x\r\nContent-Type: application/msgpack\r\nContent-Length: 1000\r\n\r\n".encode() + b"\x82" * 10,
    "huge declared body": f"POST {PATH} HTTP/1.1\r\nHost: x\r\nContent-Type: application/msgpack\r\nContent-Length: {1 << 40}\r\n\r\n".encode(),
    "oversized header": b"GET /v2 HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 200_000 + b"\r\n\r\n",
    "chunked garbage": f"POST {PATH} HTTP/1.1\r\nHost: x\r\nContent-Type: application/msgpack\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\nabc\r\n".encode(),
    "path traversal": b"GET /v1/materials/../../../etc/passwd HTTP/1.1\r\nHost: x\r\n\r\n",
    "encoded traversal": b"POST /v1/materials/..%2f..%2fetc%2fpasswd/evaluate HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n",
}


def send_raw(host_port: str, payload: bytes) -> bytes:
    host, port = host_port.split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        try:
            sock.sendall(payload)
            sock.shutdown(socket.SHUT_WR)
        except OSError:
            pass  # the server may close early (e.g. on an oversized header)
        chunks = []
        try:
            while chunk := sock.recv(65536):
                chunks.append(chunk)
        except (ConnectionResetError, TimeoutError):
            pass
    return b"".join(chunks)


@pytest.mark.parametrize("payload", list(RAW.values()), ids=list(RAW))
def test_malformed_http_never_hangs_or_kills_the_server(live_server, payload):
    reply = send_raw(live_server.host_port, payload)
    if reply:
        status = int(reply.split(b" ", 2)[1])
        if payload is RAW["oversized header"]:  # a valid GET, but 200 kB of header: NEUMIP_MAX_HEADER_BYTES
            assert status == 431, reply[:300]
        else:
            assert 400 <= status < 500, reply[:300]
        assert "error" in json.loads(reply.partition(b"\r\n\r\n")[2]), reply[:300]  # JSON, even before the app
    assert httpx.get(live_server.url + "/v2/health/live", timeout=5).status_code == 200
    assert live_server.process.poll() is None


def test_no_server_errors_were_counted(live_server):
    for payload in RAW.values():
        send_raw(live_server.host_port, payload)
    metrics = httpx.get(live_server.url + "/metrics").text
    errors = [line for line in metrics.splitlines() if line.startswith("neumip_http_requests_total") and 'status="5' in line
                     and 'route="/v2/health/ready"' not in line]  # (503 while the models load)
    assert errors == []
    assert "Traceback" not in live_server.log.read_text()
