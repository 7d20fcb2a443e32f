"""The /v1 fast path: msgpack and JSON answers, listing, and every kind of bad input (4xx, still live)."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core import wire
from neumip.core.contract import random_queries

MSGPACK = {"content-type": wire.MSGPACK_MEDIA_TYPE}


def evaluate_path(name: str = "rand16") -> str:
    return wire.EVALUATE_PATH.format(name=name)


def test_msgpack_answer_is_bit_identical_to_in_process(client, reference):
    q = random_queries(40_000, seed=11)  # > chunk_rows: split into several ONNX Runtime calls
    resp = client.post(evaluate_path(), content=wire.encode_request(q), headers=MSGPACK)
    assert resp.status_code == 200, resp.text
    assert resp.headers["content-type"] == wire.MSGPACK_MEDIA_TYPE
    np.testing.assert_array_equal(wire.decode_response(resp.content), reference.evaluate("rand16", q))


def test_json_answer_matches_msgpack(client):
    q = random_queries(5, seed=2)
    resp = client.post(evaluate_path(), json={"queries": q.tolist()})
    assert resp.status_code == 200, resp.text
    body = resp.json()
    assert body["n"] == 5
    packed = client.post(evaluate_path(), content=wire.encode_request(q), headers=MSGPACK)
    np.testing.assert_array_equal(np.asarray(body["rgb"], dtype=np.float32), wire.decode_response(packed.content))


def test_query_groups_answer_like_their_single_queries(client, reference):
    """(N, 9) groups of two lights, msgpack and JSON -> (N, 6): light j with the bits of single query j."""
    groups = np.ascontiguousarray(np.hstack([random_queries(300, seed=6), random_queries(300, seed=7)[:, 3:5]]))
    resp = client.post(evaluate_path(), content=wire.encode_request(groups), headers=MSGPACK)
    assert resp.status_code == 200, resp.text
    rgb = wire.decode_response(resp.content)
    assert rgb.shape == (300, 6)
    np.testing.assert_array_equal(rgb, reference.evaluate("rand16", groups))
    np.testing.assert_array_equal(rgb.reshape(-1, 3), reference.evaluate("rand16", C.ungroup(groups)))
    resp = client.post(evaluate_path(), json={"queries": groups[:5].tolist()})
    assert resp.status_code == 200 and resp.json()["n"] == 5, resp.text
    np.testing.assert_array_equal(np.asarray(resp.json()["rgb"], np.float32), rgb[:5])


def test_zero_rows_answer_zero_rows(client):
    """N = 0 is valid (the contract): msgpack and JSON both answer an empty (0, 3)."""
    resp = client.post(evaluate_path(), content=wire.encode_request(np.zeros((0, 7), np.float32)), headers=MSGPACK)
    assert resp.status_code == 200, resp.text
    assert wire.decode_response(resp.content).shape == (0, 3)
    resp = client.post(evaluate_path(), json={"queries": []})
    assert resp.status_code == 200 and resp.json() == {"n": 0, "rgb": []}


def test_lambert_answers_albedo_over_pi(client):
    resp = client.post(evaluate_path("lambert"), json={"queries": random_queries(3).tolist()})
    np.testing.assert_allclose(resp.json()["rgb"], 0.5 / np.pi, rtol=1e-6)


def test_listing_carries_metadata(client):
    listing = client.get(wire.MATERIALS_PATH).json()
    names = [m["name"] for m in listing["materials"]]
    assert names == ["flat16", "lambert", "rand16"]
    rand = listing["materials"][names.index("rand16")]
    assert rand["contract_version"] == C.CONTRACT_VERSION
    assert rand["config"]["resolution"] == 16
    assert rand["description"] == "random test material"
    assert listing["failed"] == []
    assert client.get(wire.MATERIALS_PATH + "/lambert").json()["name"] == "lambert"


def _msgpack(**fields) -> bytes:
    return msgpack.packb(fields)


GOOD = random_queries(4, seed=5)
NAN = GOOD.copy()
NAN[1, C.SIGMA] = np.nan
INF = GOOD.copy()
INF[2, C.U] = np.inf
OUTSIDE = GOOD.copy()
OUTSIDE[0, C.WI_X] = 1.5

# (name, path, body, headers, status, words the error message must contain)
BAD_REQUESTS = [
    ("wrong byte length", evaluate_path(), _msgpack(n=4, queries=GOOD.tobytes()[:-4]), MSGPACK, 400, "bytes"),
    ("n disagrees", evaluate_path(), _msgpack(n=5, queries=GOOD.tobytes()), MSGPACK, 400, "n=5"),
    ("queries not binary", evaluate_path(), _msgpack(n=1, queries=[1.0] * 7), MSGPACK, 400, "binary"),
    ("n not an integer", evaluate_path(), _msgpack(n="4", queries=GOOD.tobytes()), MSGPACK, 400, "'n'"),
    ("missing key", evaluate_path(), _msgpack(queries=GOOD.tobytes()), MSGPACK, 400, "keys"),
    ("not a map", evaluate_path(), msgpack.packb([1, 2, 3]), MSGPACK, 400, "map"),
    ("malformed msgpack", evaluate_path(), b"\xc1\xff\x00garbage", MSGPACK, 400, "msgpack"),
    ("truncated msgpack", evaluate_path(), wire.encode_request(GOOD)[:-10], MSGPACK, 400, "msgpack"),
    ("NaN", evaluate_path(), wire.encode_request(NAN), MSGPACK, 400, "finite"),
    ("Inf", evaluate_path(), wire.encode_request(INF), MSGPACK, 400, "finite"),
    ("direction outside disk", evaluate_path(), wire.encode_request(OUTSIDE), MSGPACK, 400, "unit vector"),
    ("N above limit", evaluate_path(), wire.encode_request(random_queries(50_001)), MSGPACK, 413, "limit"),
    ("unknown material", evaluate_path("nope"), wire.encode_request(GOOD), MSGPACK, 404, "unknown material"),
    ("path trick", "/v1/materials/..%2F..%2Fetc%2Fpasswd/evaluate", wire.encode_request(GOOD), MSGPACK, 404, "no such"),
    ("dot name", evaluate_path(".."), wire.encode_request(GOOD), MSGPACK, 404, "no such"),
    ("hidden name", evaluate_path(".rand16"), wire.encode_request(GOOD), MSGPACK, 400, "invalid material name"),
    ("long name", evaluate_path("a" * 300), wire.encode_request(GOOD), MSGPACK, 400, "invalid material name"),
    ("missing content type", evaluate_path(), wire.encode_request(GOOD), {}, 415, "missing"),
    ("wrong content type", evaluate_path(), wire.encode_request(GOOD), {"content-type": "text/plain"}, 415, "text/plain"),
    ("gzip body", evaluate_path(), wire.encode_request(GOOD), {**MSGPACK, "content-encoding": "gzip"}, 415, "gzip"),
    ("oversized body", evaluate_path(), b"\x00" * (4 << 20 | 1), MSGPACK, 413, "limit"),
    ("malformed JSON", evaluate_path(), b'{"queries": [[1,2', {"content-type": "application/json"}, 400, "JSON"),
    ("JSON not an object", evaluate_path(), b"[1, 2]", {"content-type": "application/json"}, 400, "queries"),
    ("JSON short row", evaluate_path(), b'{"queries": [[0, 0, 0, 0, 0, 0]]}', {"content-type": "application/json"}, 400, "(N, 7)"),
    ("JSON rows of 8", evaluate_path(), b'{"queries": [[0, 0, 0, 0, 0, 0, 0, 0]]}', {"content-type": "application/json"}, 400, "5 + 2 K"),
    ("JSON ragged groups", evaluate_path(), b'{"queries": [[0, 0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0, 0, 0]]}',
     {"content-type": "application/json"}, 400, "same in every row"),
    ("8 columns", evaluate_path(), _msgpack(n=4, queries=np.zeros((4, 8), np.float32).tobytes()), MSGPACK, 400, "8 float32 per row"),
    ("bytes of no width", evaluate_path(), _msgpack(n=4, queries=b"\0" * 4 * 4 * 9 + b"\0" * 8), MSGPACK, 400, "not n=4 rows"),
    ("group light outside disk", evaluate_path(), wire.encode_request(np.hstack([GOOD, [[1.5, 0]] * 4]).astype(np.float32)),
     MSGPACK, 400, "wi of light 2"),
    ("group of 65 lights", evaluate_path(), _msgpack(n=1, queries=np.zeros((1, 5 + 2 * 65), np.float32).tobytes()),
     MSGPACK, 400, "K <= 64"),
    ("65 lights stated", evaluate_path(), _msgpack(n=1, lights=65, queries=np.zeros((1, 5 + 2 * 65), np.float32).tobytes()),
     MSGPACK, 400, "'lights' must be an integer from 1 to 64"),
    ("JSON strings", evaluate_path(), b'{"queries": [["a", 0, 0, 0, 0, 0, 0]]}', {"content-type": "application/json"}, 400, "numbers"),
    ("JSON booleans", evaluate_path(), b'{"queries": [[true, 0, 0, 0, 0, 0, 0]]}', {"content-type": "application/json"}, 400, "numbers"),
    ("JSON NaN", evaluate_path(), b'{"queries": [[NaN, 0, 0, 0, 0, 0, 0]]}', {"content-type": "application/json"}, 400, "finite"),
    ("JSON huge value", evaluate_path(), b'{"queries": [[1e300, 0, 0, 0, 0, 0, 0]]}', {"content-type": "application/json"}, 400, "finite"),
    ("JSON integer beyond float", evaluate_path(), b'{"queries": [[1' + b"0" * 400 + b', 0, 0, 0, 0, 0, 0]]}', {"content-type": "application/json"}, 400, "finite"),
    ("JSON nested deeply", evaluate_path(), b'{"queries": ' + b"[" * 100_000, {"content-type": "application/json"}, 400, "nests too deep"),
    ("JSON n disagrees", evaluate_path(), b'{"n": 2, "queries": [[0, 0, 0, 0, 0, 0, 0]]}', {"content-type": "application/json"}, 400, "'n'"),
    ("bad Content-Length", evaluate_path(), None, {**MSGPACK, "content-length": "abc"}, 400, "content-length"),
]


@pytest.mark.parametrize(
    "path, body, headers, status, words", [r[1:] for r in BAD_REQUESTS], ids=[r[0] for r in BAD_REQUESTS]
)
def test_bad_request_gets_4xx_with_message_and_server_stays_live(client, path, body, headers, status, words):
    resp = client.post(path, content=body, headers=headers)
    assert resp.status_code == status, resp.text
    message = resp.json()["error"]
    assert words.lower() in message.lower(), message
    assert client.get("/v2/health/live").status_code == 200
    ok = client.post(evaluate_path(), content=wire.encode_request(GOOD), headers=MSGPACK)
    assert ok.status_code == 200


def test_framework_errors_use_the_error_body(client):
    for resp, status in (
        (client.get("/no/such/thing"), 404),
        (client.get(evaluate_path()), 405),
        (client.delete(wire.MATERIALS_PATH), 405),
    ):
        assert resp.status_code == status
        assert set(resp.json()) == {"error"}


def test_chunked_uploads_are_read_and_bounded(client, reference):
    """A body without Content-Length (chunked) reserves memory as it grows: answered, or 413 past the limit."""
    q = random_queries(1000, seed=5)
    body = wire.encode_request(q)
    resp = client.post(evaluate_path(), content=iter([body[:100], body[100:]]), headers=MSGPACK)
    assert resp.status_code == 200, resp.text
    np.testing.assert_array_equal(wire.decode_response(resp.content), reference.evaluate("rand16", q))
    too_big = iter([b"\x00" * (1 << 20)] * 5)  # 5 MiB against the 4 MiB limit of this app
    resp = client.post(evaluate_path(), content=too_big, headers=MSGPACK)
    assert resp.status_code == 413 and "limit of 4194304 bytes" in resp.json()["error"]
    assert client.app.state.neumip.admission.memory == 0
