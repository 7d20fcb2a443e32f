"""Large msgpack requests evaluated while their body arrives: same bits, same errors, nothing leaks."""

from __future__ import annotations

import http.client
import time

import msgpack
import numpy as np
import pytest

from neumip.client import contract as C
from neumip.server import v1
from neumip.client.contract import random_queries

MSGPACK = {"content-type": C.MSGPACK_MEDIA_TYPE}
PATH = C.EVALUATE_PATH.format(name="rand16")


@pytest.fixture
def streams(monkeypatch) -> list:
    """The streams the in-process app's /v1 handler used (given_up says whether it fell back)."""
    seen = []

    async def recording(*args, **kwargs):
        body, stream = await original(*args, **kwargs)
        seen.append(stream)
        return body, stream

    original = v1.read_and_queue
    monkeypatch.setattr(v1, "read_and_queue", recording)
    return seen


def admitted_rows_settle_to_zero(client) -> bool:
    batcher = client.app.state.neumip.batcher
    deadline = time.monotonic() + 10
    while batcher.admitted_rows and time.monotonic() < deadline:
        time.sleep(0.01)
    return batcher.admitted_rows == 0


def test_streamed_answer_is_bit_identical(client, reference, streams):
    q = random_queries(30_000, seed=21)  # several chunks of 8192 rows and a tail
    resp = client.post(PATH, content=C.encode_request(q), headers=MSGPACK)
    assert resp.status_code == 200, resp.text
    np.testing.assert_array_equal(C.decode_response(resp.content), reference.evaluate("rand16", q))
    assert len(streams) == 1 and not streams[0].given_up


def test_small_body_is_not_streamed(client, streams):
    resp = client.post(PATH, content=C.encode_request(random_queries(100)), headers=MSGPACK)
    assert resp.status_code == 200 and streams == []


def test_bad_row_gives_the_same_error_as_unstreamed(client, streams):
    q = random_queries(30_000, seed=22)
    q[20_001, C.SIGMA] = np.nan
    expected = pytest.raises(C.QueryError, C.decode_request, C.encode_request(q)).value
    resp = client.post(PATH, content=C.encode_request(q), headers=MSGPACK)
    assert resp.status_code == 400 and str(expected) in resp.json()["error"]
    assert "row 20001 column sigma" in resp.json()["error"]
    assert streams[0].given_up
    assert admitted_rows_settle_to_zero(client)  # the chunks queued before the bad one were let go


def test_too_many_rows_is_413_and_other_layouts_still_work(client, reference, streams):
    resp = client.post(PATH, content=C.encode_request(random_queries(60_000)), headers=MSGPACK)  # limit 50k
    assert resp.status_code == 413 and "60000 query rows is more than the limit" in resp.json()["error"]
    q = random_queries(20_000, seed=23)
    swapped = msgpack.packb({"queries": q.tobytes(), "n": q.shape[0]})  # valid msgpack, another layout
    resp = client.post(PATH, content=swapped, headers=MSGPACK)
    assert resp.status_code == 200
    np.testing.assert_array_equal(C.decode_response(resp.content), reference.evaluate("rand16", q))
    assert [s.given_up for s in streams] == [True, True]
    assert admitted_rows_settle_to_zero(client)


def send_in_parts(url: str, body: bytes, parts: int) -> tuple[int, bytes]:
    """POST `body` to a real server in `parts` sends with pauses between: the server sees it arrive."""
    host, port = url.split("://", 1)[1].split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=60)
    conn.putrequest("POST", PATH)
    conn.putheader("Content-Type", C.MSGPACK_MEDIA_TYPE)
    conn.putheader("Content-Length", str(len(body)))
    conn.endheaders()
    step = -(-len(body) // parts)
    for lo in range(0, len(body), step):
        conn.send(body[lo : lo + step])
        time.sleep(0.05)
    resp = conn.getresponse()
    answer = resp.read()
    conn.close()
    return resp.status, answer


def test_real_server_evaluates_a_body_arriving_in_parts(live_server, reference):
    q = random_queries(40_000, seed=24)
    status, answer = send_in_parts(live_server.url, C.encode_request(q), parts=5)
    assert status == 200
    np.testing.assert_array_equal(C.decode_response(answer), reference.evaluate("rand16", q))
    q[39_000, C.WO_X] = 3.0  # a bad row in the last part, after four parts' rows were queued
    status, answer = send_in_parts(live_server.url, C.encode_request(q), parts=5)
    assert status == 400 and b"row 39000" in answer
