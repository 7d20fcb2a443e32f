"""The HTTP floor of ``/v1`` (used by ``bench_server.py --engine kernel``): a bare ASGI app under uvicorn
that does only what every Python server of the msgpack protocol must do, and evaluates nothing.

Each ``POST /v1/materials/{name}/evaluate`` body is read through ASGI ``receive``, decoded and checked
(`wire.decode_request`: the contract's value checks), and answered with a zero-filled response body of
the right shape (`wire.response_buffer`). ``GET /v1/materials/{name}`` says it takes query groups, and
``GET /v2/health/ready`` says yes, so `MaterialClient` and the benchmark's `Server` work with it as
with `neumip serve`. No FastAPI, no batcher, no admission, no metrics: its CPU time per request is what
the product server's event loop could come down to at best on the same uvicorn (uvloop, httptools).

    .venv/bin/python -m uvicorn bare_server:app --app-dir benchmarks --loop uvloop --http httptools
"""

from __future__ import annotations

import json

from neumip.core import contract as C
from neumip.core import wire


async def _answer(send, status: int, body: bytes | memoryview, media: str) -> None:
    headers = [(b"content-type", media.encode()), (b"content-length", str(len(body)).encode())]
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


async def _lifespan(receive, send) -> None:
    while True:
        message = await receive()
        if message["type"] == "lifespan.startup":
            await send({"type": "lifespan.startup.complete"})
        elif message["type"] == "lifespan.shutdown":
            await send({"type": "lifespan.shutdown.complete"})
            return


async def app(scope, receive, send) -> None:
    if scope["type"] == "lifespan":
        await _lifespan(receive, send)
        return
    path, method = scope["path"], scope["method"]
    if method == "GET":
        metadata = {"name": path.rsplit("/", 1)[-1]}
        await _answer(send, 200, json.dumps(metadata).encode(), "application/json")
        return
    body = bytearray()
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            return
        body += message.get("body", b"")
        if not message.get("more_body", False):
            break
    queries = wire.decode_request(body)
    content, _ = wire.response_buffer(queries.shape[0], C.group_lights(queries.shape[1]))
    await _answer(send, 200, memoryview(content), wire.MSGPACK_MEDIA_TYPE)
