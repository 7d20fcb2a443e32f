"""Open Inference Protocol v2: metadata, health, JSON and binary infer, bad input, and tritonclient
against a real `neumip serve` process."""

from __future__ import annotations

import json

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core.contract import random_queries

HEADER = "Inference-Header-Content-Length"
Q = random_queries(37, seed=4)  # 37 = 2 * 16 + 5: a tail after two aligned blocks


def infer_body(queries: np.ndarray, binary_in: bool, binary_out: bool, **extra) -> tuple[bytes, dict]:
    tensor = {"name": "queries", "datatype": "FP32", "shape": list(queries.shape)}
    tail = b""
    if binary_in:
        tail = queries.tobytes()
        tensor["parameters"] = {"binary_data_size": len(tail)}
    else:
        tensor["data"] = queries.reshape(-1).tolist()
    head = json.dumps({"inputs": [tensor], "outputs": [{"name": "rgb", "parameters": {"binary_data": binary_out}}], **extra}).encode()
    return head + tail, ({HEADER: str(len(head))} if binary_in else {})


def read_output(resp) -> np.ndarray:
    if HEADER in resp.headers:
        n = int(resp.headers[HEADER])
        head = json.loads(resp.content[:n])
        out = head["outputs"][0]
        assert out["parameters"]["binary_data_size"] == len(resp.content) - n
        return np.frombuffer(resp.content[n:], dtype="<f4").reshape(out["shape"])
    out = resp.json()["outputs"][0]
    assert out["datatype"] == "FP32"
    return np.asarray(out["data"], dtype=np.float32).reshape(out["shape"])


def test_server_and_model_metadata(client):
    meta = client.get("/v2").json()
    assert meta["name"] == "neumip" and meta["extensions"] == [
        "binary_tensor_data", "model_repository", "model_configuration", "statistics"]
    model = client.get("/v2/models/rand16").json()
    assert model["platform"] == "onnxruntime_onnx"  # the default engine
    assert model["inputs"] == [{"name": "queries", "datatype": "FP32", "shape": [-1, -1]}]  # (N, 5 + 2 K)
    assert model["outputs"] == [{"name": "rgb", "datatype": "FP32", "shape": [-1, -1]}]  # (N, 3 K)
    assert client.get("/v2/models/rand16/versions/1").json() == model
    assert client.get("/v2/models/rand16/versions/2").status_code == 404


def test_health_endpoints_have_empty_bodies(client):
    for path in ("/v2/health/live", "/v2/health/ready", "/v2/models/rand16/ready", "/v2/models/rand16/versions/1/ready"):
        resp = client.get(path)
        assert resp.status_code == 200 and resp.content == b"", path
    assert client.get("/v2/models/nope/ready").status_code == 404


@pytest.mark.parametrize("binary_in, binary_out", [(False, False), (True, False), (False, True), (True, True)])
def test_infer_matches_in_process(client, reference, binary_in, binary_out):
    body, headers = infer_body(Q, binary_in, binary_out, id="req-7")
    resp = client.post("/v2/models/rand16/infer", content=body, headers=headers)
    assert resp.status_code == 200, resp.text
    np.testing.assert_array_equal(read_output(resp), reference.evaluate("rand16", Q))
    head = resp.content[: int(resp.headers[HEADER])] if binary_out else resp.content
    assert json.loads(head)["id"] == "req-7" and json.loads(head)["model_name"] == "rand16"


@pytest.mark.parametrize("binary", [False, True])
def test_query_groups_answer_like_their_single_queries(client, reference, binary):
    """[N, 9] groups of two lights -> [N, 6], light j with the bits of single query j (`contract.ungroup`)."""
    groups = np.hstack([Q, random_queries(37, seed=5)[:, C.WI_X:C.WI_Y + 1]])
    body, headers = infer_body(groups, binary, binary)
    resp = client.post("/v2/models/rand16/infer", content=body, headers=headers)
    assert resp.status_code == 200, resp.text
    rgb = read_output(resp)
    assert rgb.shape == (37, 6)
    np.testing.assert_array_equal(rgb, reference.evaluate("rand16", groups))
    np.testing.assert_array_equal(rgb.reshape(-1, 3), reference.evaluate("rand16", C.ungroup(groups)))


@pytest.mark.parametrize("binary_out", [False, True])
def test_the_wire_modules_infer_request_gets_its_answer_in_the_format_it_asks(client, reference, binary_out):
    """`wire.encode_infer_request(..., binary_output=False)` asks for the answer in JSON (what the Docker load test
    and `bench_docker.py` send); the default asks for binary."""
    from neumip.core import wire

    headers, parts = wire.encode_infer_request(Q, binary_output=binary_out)
    resp = client.post("/v2/models/rand16/infer", content=b"".join(bytes(p) for p in parts), headers=headers)
    assert resp.status_code == 200, resp.text
    assert (HEADER in resp.headers) == binary_out
    np.testing.assert_array_equal(read_output(resp), reference.evaluate("rand16", Q))


@pytest.mark.parametrize("binary", [False, True])
def test_zero_rows_answer_zero_rows(client, binary):
    body, headers = infer_body(np.zeros((0, 7), np.float32), binary, binary)
    resp = client.post("/v2/models/rand16/infer", content=body, headers=headers)
    assert resp.status_code == 200, resp.text
    assert read_output(resp).shape == (0, 3)


def test_request_level_binary_output_and_versioned_path(client, reference):
    body, headers = infer_body(Q, True, False)
    msg = json.loads(body[: int(headers[HEADER])])
    del msg["outputs"]
    msg["parameters"] = {"binary_data_output": True}
    head = json.dumps(msg).encode()
    resp = client.post("/v2/models/rand16/versions/1/infer", content=head + Q.tobytes(), headers={HEADER: str(len(head))})
    assert resp.status_code == 200, resp.text
    np.testing.assert_array_equal(read_output(resp), reference.evaluate("rand16", Q))


def _bad(**change) -> bytes:
    tensor = {"name": "queries", "datatype": "FP32", "shape": [1, 7], "data": [0.5, 0.5, 0.01, 0, 0, 0, 0]}
    tensor.update(change)
    return json.dumps({"inputs": [tensor]}).encode()


BINARY, BINARY_HEAD = infer_body(Q, True, True)
BAD_INFER = [
    ("wrong datatype", _bad(datatype="FP64"), {}, 400, "FP32"),
    ("binary flag as a string", json.dumps({"inputs": [json.loads(_bad())["inputs"][0]],
                                            "parameters": {"binary_data_output": "false"}}).encode(), {}, 400, "true or false"),
    ("wrong shape", _bad(shape=[7, 1]), {}, 400, "shape"),
    ("width of no group", _bad(shape=[1, 8], data=[0.0] * 8), {}, 400, "5 + 2 K"),
    ("group data length", _bad(shape=[1, 9]), {}, 400, "needs 9"),
    ("binary size of another width", json.dumps({"inputs": [{"name": "queries", "datatype": "FP32", "shape": [37, 9],
                                                  "parameters": {"binary_data_size": Q.nbytes}}]}).encode() + Q.tobytes(),
     {HEADER: str(len(json.dumps({"inputs": [{"name": "queries", "datatype": "FP32", "shape": [37, 9],
                                              "parameters": {"binary_data_size": Q.nbytes}}]})))}, 400, "binary_data_size"),
    ("3-d shape", _bad(shape=[1, 1, 7]), {}, 400, "shape"),
    ("negative shape", _bad(shape=[-1, 7]), {}, 400, "shape"),
    ("data length", _bad(data=[0.0] * 6), {}, 400, "needs 7"),
    ("data strings", _bad(data=["a"] * 7), {}, 400, "numbers"),
    ("data ragged", _bad(data=[[0.0] * 7, [0.0]]), {}, 400, "nested"),
    ("data NaN", b'{"inputs": [{"name": "queries", "datatype": "FP32", "shape": [1, 7], "data": [NaN, 0, 0, 0, 0, 0, 0]}]}', {}, 400, "finite"),
    ("nested deeply", b'{"inputs": ' + b"[" * 100_000, {}, 400, "nests too deep"),
    ("N above limit", *infer_body(random_queries(50_001), True, True), 413, "limit"),
    ("unknown input", _bad(name="x"), {}, 400, "unknown input"),
    ("two inputs", json.dumps({"inputs": [json.loads(_bad())["inputs"][0]] * 2}).encode(), {}, 400, "exactly one"),
    ("no inputs", b'{"outputs": []}', {}, 400, "inputs"),
    ("unknown output", json.dumps({**json.loads(_bad()), "outputs": [{"name": "xyz"}]}).encode(), {}, 400, "unknown output"),
    ("malformed JSON", b'{"inputs": [', {}, 400, "JSON"),
    ("JSON not an object", b"[]", {}, 400, "object"),
    ("id not a string", json.dumps({**json.loads(_bad()), "id": 5}).encode(), {}, 400, "'id'"),
    ("header length too long", BINARY, {HEADER: str(len(BINARY) + 1)}, 400, HEADER),
    ("header length zero", BINARY, {HEADER: "0"}, 400, HEADER),
    ("header length not a number", BINARY, {HEADER: "12a"}, 400, HEADER),
    ("header length cuts the JSON", BINARY, {HEADER: str(int(BINARY_HEAD[HEADER]) - 3)}, 400, "JSON"),
    ("header length eats binary", BINARY, {HEADER: str(int(BINARY_HEAD[HEADER]) + 4)}, 400, "JSON"),
    ("binary without header", BINARY, {}, 400, "JSON"),
    ("binary size wrong", BINARY[:-4], BINARY_HEAD, 400, "binary"),
    ("binary trailing bytes", BINARY + b"\0\0\0\0", BINARY_HEAD, 400, "binary"),
    ("wrong content type", _bad(), {"content-type": "text/plain"}, 415, "text/plain"),
    ("unknown model", _bad(), {}, 404, "unknown material"),
    ("oversized body", b"{" + b" " * (4 << 20), {}, 413, "limit"),
]


@pytest.mark.parametrize("body, headers, status, words", [b[1:] for b in BAD_INFER], ids=[b[0] for b in BAD_INFER])
def test_bad_infer_gets_4xx_with_message_and_server_stays_live(client, body, headers, status, words):
    model = "nope" if words == "unknown material" else "rand16"
    resp = client.post(f"/v2/models/{model}/infer", content=body, headers=headers)
    assert resp.status_code == status, resp.text
    assert words.lower() in resp.json()["error"].lower(), resp.json()
    assert client.get("/v2/health/live").status_code == 200
    assert client.post("/v2/models/rand16/infer", content=_bad()).status_code == 200


def test_tritonclient_against_a_real_server(live_server, reference):
    import tritonclient.http as triton
    from tritonclient.utils import InferenceServerException

    client = triton.InferenceServerClient(live_server.host_port)
    assert client.is_server_live() and client.is_server_ready() and client.is_model_ready("rand16")
    assert client.get_model_metadata("rand16")["inputs"][0]["shape"] == [-1, -1]
    q = random_queries(100_003, seed=9)
    expected = reference.evaluate("rand16", q)
    for binary in (True, False):
        tensor = triton.InferInput("queries", list(q.shape), "FP32")
        tensor.set_data_from_numpy(q, binary_data=binary)
        result = client.infer("rand16", [tensor], outputs=[triton.InferRequestedOutput("rgb", binary_data=binary)])
        np.testing.assert_array_equal(result.as_numpy("rgb"), expected)
    groups = np.hstack([q[:5000], q[5000:10000, C.WI_X:C.WI_Y + 1]])  # [N, 9]: two lights -> [N, 6]
    tensor = triton.InferInput("queries", list(groups.shape), "FP32")
    tensor.set_data_from_numpy(groups)
    rgb = client.infer("rand16", [tensor]).as_numpy("rgb")
    np.testing.assert_array_equal(rgb.reshape(-1, 3), reference.evaluate("rand16", C.ungroup(groups)))
    bad = triton.InferInput("queries", [2, 8], "FP32")
    bad.set_data_from_numpy(np.zeros((2, 8), np.float32))
    with pytest.raises(InferenceServerException, match="5 \\+ 2 K"):
        client.infer("rand16", [bad])
    bad = triton.InferInput("queries", [2, 7], "FP32")
    bad.set_data_from_numpy(np.full((2, 7), np.nan, np.float32))
    with pytest.raises(InferenceServerException, match="finite"):
        client.infer("rand16", [bad])
    with pytest.raises(InferenceServerException, match="unknown material"):
        client.infer("nope", [tensor])
    assert client.is_server_live()
