"""Admission: body memory and queued rows reserved from the headers, refused at once, released when answered."""

from __future__ import annotations

import asyncio

import pytest
from starlette.requests import Request

from neumip.server.admission import Admission, plan
from neumip.server.errors import ApiError, QueueFull
from neumip.server.metrics import Metrics
from neumip.server.settings import Settings


def request(**headers: str) -> Request:
    raw = [(k.replace("_", "-").encode(), v.encode()) for k, v in headers.items()]
    return Request({"type": "http", "method": "POST", "path": "/", "headers": raw})


def test_plan_bounds_rows_and_memory_from_the_headers():
    settings = Settings(max_rows=1000, max_queue_rows=1000, max_body_bytes=1 << 20,
                        max_json_body_bytes=1 << 16, body_budget_bytes=2 << 20)
    msgpack = plan(request(content_length=str(6 + 28 * 300)), settings, json=False)
    assert (msgpack.rows, msgpack.memory()) == (300, 6 + 28 * 300)
    assert plan(request(content_length=str(28 * 5000)), settings, json=False).rows == 1000  # at most max_rows
    json_body = plan(request(content_length="1400"), settings, json=True)
    assert json_body.rows == 100 and json_body.memory() == 16 * 1400
    v2 = plan(request(content_length=str(200 + 28 * 10)), settings, json=True, json_length=200)
    assert v2.rows == 10 + 200 // 14 and v2.memory() == 28 * 10 + 16 * 200
    chunked = plan(request(), settings, json=False)
    assert chunked.declared is None and chunked.rows == 0
    for headers, status in (({"content_length": "abc"}, 400), ({"content_length": str(2 << 20)}, 413),
                            ({"content_length": "10", "content_encoding": "gzip"}, 415)):
        with pytest.raises(ApiError) as info:
            plan(request(**headers), settings, json=False)
        assert info.value.status == status
    with pytest.raises(ApiError, match="JSON limit") as info:
        plan(request(content_length=str(1 << 17)), settings, json=True)
    assert info.value.status == 413


def test_budgets_refuse_at_once_and_release_when_the_answer_is_done():
    settings = Settings(max_rows=3000, max_queue_rows=3000, max_body_bytes=1 << 20, max_json_body_bytes=1 << 16,
                        body_budget_bytes=2 << 20)
    metrics = Metrics()
    admission = Admission(settings, metrics)

    async def scenario():
        first = plan(request(content_length=str(28 * 2000)), settings, json=False)
        with admission.admit(first) as ticket:
            assert (admission.rows, admission.memory) == (2000, 28 * 2000)
            with pytest.raises(QueueFull, match="rows queued") as info:
                with admission.admit(first):
                    pass
            assert info.value.status == 503 and info.value.headers["Retry-After"] == "1"
            admission.resize(ticket, ticket.memory, 10)  # decoded: 10 rows after all
            with admission.admit(first):
                assert admission.rows == 2010
                gauge = metrics.registry.get_sample_value  # what /metrics shows now
                assert (gauge("neumip_queue_rows"), gauge("neumip_queue_requests")) == (2010, 2)
                assert gauge("neumip_body_bytes") == 2 * 28 * 2000
            ticket.until = asyncio.get_running_loop().create_future()  # still running when the handler leaves
        assert admission.rows == 10 and admission.requests == 1
        ticket.until.set_result(None)
        await asyncio.sleep(0)  # done callbacks run on the loop
        assert (admission.rows, admission.memory, admission.requests) == (0, 0, 0)
        assert metrics.registry.get_sample_value("neumip_queue_requests") == 0
        roomy = settings.model_copy(update={"max_queue_rows": 100_000})  # rows to spare: memory binds
        memory = Admission(roomy, metrics)
        big = plan(request(content_length=str(900_000)), roomy, json=False)
        with memory.admit(big), memory.admit(big):
            with pytest.raises(QueueFull, match="bytes of request bodies"):
                with memory.admit(big):
                    pass

    asyncio.run(scenario())
    assert metrics.registry.get_sample_value("neumip_queue_rejected_total") == 2
    assert metrics.registry.get_sample_value("neumip_body_bytes") == 0


def test_the_heap_is_trimmed_once_the_server_is_idle(monkeypatch):
    """glibc's malloc_trim runs once no request has been in flight for TRIM_AFTER_S, not while requests keep
    arriving; and the real one is found on this (glibc) system."""
    from neumip.server import admission as A

    assert A._malloc_trim() is not None  # Debian's glibc
    calls = []
    monkeypatch.setattr(A, "MALLOC_TRIM", lambda pad: calls.append(pad) or 1)
    monkeypatch.setattr(A, "TRIM_AFTER_S", 0.05)
    settings = Settings()
    admission = Admission(settings, Metrics())
    one = plan(request(content_length=str(28 * 10)), settings, json=False)

    async def scenario():
        for _ in range(6):  # a stream of requests 0.02 s apart: never idle for 0.05 s
            with admission.admit(one):
                pass
            await asyncio.sleep(0.02)
        assert calls == []
        await asyncio.sleep(0.1)
        assert calls == [0] and admission.trims == 1
        await asyncio.sleep(0.1)  # idle on: no second trim until a request comes and goes
        assert calls == [0]
        with admission.admit(one):
            await asyncio.sleep(0.1)  # in flight: no trim
        assert calls == [0]
        await asyncio.sleep(0.1)
        assert calls == [0, 0]

    asyncio.run(scenario())
