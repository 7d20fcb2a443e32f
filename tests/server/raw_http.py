"""Raw HTTP on loopback sockets, and a server's metrics: what the hardening tests speak to real
`neumip serve` processes with."""

from __future__ import annotations

import json
import socket

import httpx


def connect(server) -> socket.socket:
    host, port = server.host_port.split(":")
    return socket.create_connection((host, int(port)), timeout=10)


def answer(sock: socket.socket, wait_s: float) -> tuple[int, dict] | None:
    """(status, JSON body) of the answer on `sock` within `wait_s` seconds; None if none came."""
    sock.settimeout(wait_s)
    data = b""
    try:
        while b"\r\n\r\n" not in data or len(data) < _length(data):
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    except (TimeoutError, ConnectionResetError):
        pass
    if not data:
        return None
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), json.loads(body) if body else {}


def _length(data: bytes) -> int:
    head, _, _ = data.partition(b"\r\n\r\n")
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            return len(head) + 4 + int(value)
    return len(data)


def metric(server, name: str) -> float:
    text = httpx.get(server.url + "/metrics", timeout=10).text
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if line.startswith(name))
