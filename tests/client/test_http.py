"""MaterialClient: against an in-process stand-in of the server (httpx.MockTransport, the same
httpx.Client path with another transport), a stand-in that drops connections, and real server processes."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core import wire
from neumip.client import http
from neumip.client.http import ClientConfig, MaterialClient, ServerError, ServerUnavailable
from neumip.engines.local import LocalMaterials, UnknownMaterial

from neumip.core.contract import random_queries

FAST = dict(backoff_s=0.001, max_backoff_s=0.01)
PRE_GROUPS = Path(__file__).parents[1] / "data" / "pre_groups_offset.onnx"
"""A model file of query contract version 1 (exported before query groups)."""


class FakeServer:
    """Answers the msgpack protocol from a LocalMaterials; `failures` lists statuses/exceptions to
    produce first, one per request."""

    def __init__(self, folder, failures=()):
        self.local = LocalMaterials(folder)
        self.failures = list(failures)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        if self.failures:
            failure = self.failures.pop(0)
            if isinstance(failure, Exception):
                raise failure
            return httpx.Response(failure, json={"error": f"injected {failure}"}, headers={"Retry-After": "0"})
        if request.method == "GET" and request.url.path == wire.MATERIALS_PATH:
            return httpx.Response(200, json={"materials": [{"name": n} for n in self.local.materials()]})
        try:
            queries = wire.decode_request(request.content)
            rgb = self.local.evaluate(request.url.path.split("/")[-2], queries)
        except UnknownMaterial as exc:
            return httpx.Response(404, json={"error": str(exc)})
        return httpx.Response(200, content=wire.encode_response(rgb))


def client_for(server, **config) -> MaterialClient:
    return MaterialClient("http://neumip.test", ClientConfig(**{**FAST, **config}), httpx.MockTransport(server))


def test_evaluate_matches_in_process_and_splits_large_buffers(model_dir):
    server = FakeServer(model_dir)
    queries = random_queries(2500, seed=3)
    with client_for(server, max_rows=1000) as client:
        rgb = client.evaluate("rand16", queries)
        one = client.evaluate("rand16", queries[:10])  # a single request: the answer body's rows
    np.testing.assert_array_equal(rgb, server.local.evaluate("rand16", queries))
    assert rgb.flags.writeable and one.flags.writeable
    posts = [r for r in server.requests if r.method == "POST"]
    assert posts == server.requests  # no look-up of the material
    assert [wire.decode_request(r.content).shape[0] for r in posts] == [1000, 1000, 500, 10]
    assert posts[0].headers["content-type"] == wire.MSGPACK_MEDIA_TYPE


def test_a_large_body_goes_out_in_parts_that_are_views_of_the_rows(model_dir, monkeypatch):
    """Bodies are sent in parts of at most SEND_PART_BYTES (httpcore copies the rest of a part at every send),
    each a view of the caller's buffer, and the server reads the same rows."""
    rows = np.arange(3000, dtype=np.uint8)
    parts = http._in_parts([b"head", memoryview(rows)], size=1024)
    assert [len(p) for p in parts] == [4, 1024, 1024, 952]
    assert b"".join(parts) == b"head" + rows.tobytes()
    assert all(np.shares_memory(np.frombuffer(p, np.uint8), rows) for p in parts[1:])
    monkeypatch.setattr(http, "SEND_PART_BYTES", 1000)
    server = FakeServer(model_dir)
    queries = random_queries(2500, seed=4)  # 70 kB of rows: 71 parts
    with client_for(server) as client:
        np.testing.assert_array_equal(client.evaluate("rand16", queries), server.local.evaluate("rand16", queries))


def test_query_groups_are_sent_whole_and_answer_three_values_a_light(model_dir):
    """(N, 9) groups go out as they are, split by groups (never inside one; `max_rows` counts a group
    of two lights twice), and answer (N, 6); the fallback passes them on the same way."""
    from neumip.client.http import FallbackEvaluator

    server = FakeServer(model_dir)
    groups = np.ascontiguousarray(np.hstack([random_queries(2500, seed=3), random_queries(2500, seed=4)[:, 3:5]]))
    with client_for(server, max_rows=2001) as client:  # 1000 groups of two a request
        rgb = client.evaluate("rand16", groups)
        assert client.evaluate("rand16", np.zeros((0, 9), np.float32)).shape == (0, 6)
        with pytest.raises(C.QueryError, match="5 \\+ 2 K"):
            client.evaluate("rand16", np.zeros((2, 8), np.float32))
    np.testing.assert_array_equal(rgb, server.local.evaluate("rand16", groups))
    np.testing.assert_array_equal(rgb.reshape(-1, 3), server.local.evaluate("rand16", C.ungroup(groups)))
    assert [wire.decode_request(r.content).shape for r in server.requests] == [(1000, 9), (1000, 9), (500, 9)]
    evaluator = FallbackEvaluator(client_for(server, retries=0), LocalMaterials(model_dir))
    server.failures = [httpx.ConnectError("refused")]
    np.testing.assert_array_equal(evaluator.evaluate("rand16", groups), rgb)
    assert evaluator.switched


def triton_stand_in(folder):
    """A stand-in (MockTransport handler) of Triton serving `folder`'s files over /v2 (config dims [-1]).
    Returns (handler, the requests it got)."""
    local, seen = LocalMaterials(folder), []

    def handler(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        name = request.url.path.split("/")[3]
        length = int(request.headers[wire.INFER_HEADER_LENGTH])
        shape = json.loads(request.content[:length])["inputs"][0]["shape"]
        rgb = local.evaluate(name, np.frombuffer(request.content[length:], np.float32).reshape(shape))
        out = {"name": "rgb", "datatype": "FP32", "shape": list(rgb.shape), "parameters": {"binary_data_size": rgb.nbytes}}
        head = json.dumps({"model_name": name, "outputs": [out]}).encode()
        return httpx.Response(200, content=head + rgb.tobytes(), headers={wire.INFER_HEADER_LENGTH: str(len(head))})

    return handler, seen


def sent_widths(requests: list[httpx.Request]) -> list[int]:
    """Query widths of the evaluations among `requests` (msgpack or v2 binary)."""
    widths = []
    for r in requests:
        if r.method == "POST" and wire.INFER_HEADER_LENGTH in r.headers:
            widths.append(json.loads(r.content[:int(r.headers[wire.INFER_HEADER_LENGTH])])["inputs"][0]["shape"][1])
        elif r.method == "POST":
            widths.append(wire.decode_request(r.content).shape[1])
    return widths


@pytest.mark.parametrize("protocol", ["msgpack", "v2"])
def test_groups_go_whole_in_either_protocol(model_dir, protocol):
    """Stand-ins (MockTransport) of neumip's server (msgpack) and of Triton (v2): groups of three
    lights go whole, split between groups by `max_rows` counted in answers, with no look-up of the
    material first, and answer with the bits of their single queries."""
    if protocol == "msgpack":
        server = FakeServer(model_dir)
        handler, seen, local = server, server.requests, server.local
    else:
        (handler, seen), local = triton_stand_in(model_dir), LocalMaterials(model_dir)
    groups = np.ascontiguousarray(np.hstack([random_queries(2500, seed=3), random_queries(2500, seed=4)[:, 3:5],
                                             random_queries(2500, seed=5)[:, 3:5]]))  # (2500, 11): 3 lights
    client = MaterialClient("http://neumip.test", ClientConfig(max_rows=3000, **FAST), httpx.MockTransport(handler),
                            protocol=protocol)
    rgb = client.evaluate("rand16", groups)
    assert rgb.shape == (2500, 9) and rgb.flags.writeable
    np.testing.assert_array_equal(rgb, local.evaluate("rand16", groups))
    np.testing.assert_array_equal(rgb.reshape(-1, 3), local.evaluate("rand16", C.ungroup(groups)))
    assert sent_widths(seen) == [11, 11, 11] and len(seen) == 3  # 1000 groups of three a request


def test_an_unknown_material_is_the_server_error_each_time(model_dir):
    """...and an `UnknownMaterial`, as `LocalMaterials` raises for it, so that a renderer takes either."""
    server = FakeServer(model_dir)
    groups = np.hstack([random_queries(4), random_queries(4, seed=1)[:, 3:5]])
    client = client_for(server)
    for _ in range(2):
        with pytest.raises(ServerError, match="evaluate 4 queries on 'nope': server answered 404: unknown material") as info:
            client.evaluate("nope", groups)
        assert info.value.status == 404 and isinstance(info.value, UnknownMaterial)
    assert len(server.requests) == 2


def test_materials_lists_the_server(model_dir):
    client = client_for(FakeServer(model_dir))
    assert client.materials() == ["flat16", "lambert", "rand16"]


def test_empty_buffer_sends_nothing(model_dir):
    server = FakeServer(model_dir)
    assert client_for(server).evaluate("lambert", np.zeros((0, 7), np.float32)).shape == (0, 3)
    assert server.requests == []


def test_retries_503_then_succeeds(model_dir):
    server = FakeServer(model_dir, failures=[503, 503])
    rgb = client_for(server, retries=2).evaluate("lambert", random_queries(10))
    np.testing.assert_allclose(rgb, 0.5 / np.pi, rtol=1e-6)
    assert len(server.requests) == 3


def test_503_past_the_retries_is_unavailable(model_dir):
    server = FakeServer(model_dir, failures=[503] * 10)
    with pytest.raises(ServerUnavailable, match=r"busy \(503\) after 3 attempt\(s\): injected 503"):
        client_for(server, retries=2).evaluate("lambert", random_queries(10))
    assert len(server.requests) == 3


def test_connection_errors_are_retried_then_reported(model_dir):
    server = FakeServer(model_dir, failures=[httpx.ConnectError("refused")])
    assert client_for(server, retries=1).evaluate("lambert", random_queries(4)).shape == (4, 3)
    server = FakeServer(model_dir, failures=[httpx.ConnectError("refused")] * 5)
    with pytest.raises(ServerUnavailable, match=r"http://neumip.test unreachable after 2 attempt\(s\).*refused"):
        client_for(server, retries=1).evaluate("lambert", random_queries(4))


def test_client_errors_fail_at_once_with_the_server_message(model_dir):
    server = FakeServer(model_dir)
    with pytest.raises(ServerError, match="answered 404: unknown material 'nope'") as info:
        client_for(server).evaluate("nope", random_queries(4))
    assert info.value.status == 404 and len(server.requests) == 1


def test_bad_answer_size_is_an_error():
    def short(request):
        return httpx.Response(200, content=wire.encode_response(np.zeros((3, 3), np.float32)))

    client = MaterialClient("http://x", ClientConfig(**FAST), httpx.MockTransport(short))
    with pytest.raises(C.QueryError, match=r"answer must have shape \(4, 3\)"):
        client.evaluate("m", random_queries(4))


def test_bad_queries_are_rejected_before_sending(model_dir):
    server = FakeServer(model_dir)
    with pytest.raises(C.QueryError):
        client_for(server).evaluate("lambert", np.full((2, 7), np.nan, np.float32))
    assert server.requests == []


@pytest.mark.parametrize("name", ["../admin", "a/b", "rock?x=1", "rock#", "", "x" * 129, "-rock", "r o"])
def test_names_that_are_not_material_names_never_reach_the_url(model_dir, name):
    """A name goes into the URL path: one with '/', '?', '#', spaces... is refused before sending."""
    server = FakeServer(model_dir)
    with pytest.raises(UnknownMaterial, match="is not a material name"):
        client_for(server).evaluate(name, random_queries(4))
    assert server.requests == []


def test_bad_url_and_config():
    with pytest.raises(ValueError, match="http://"):
        MaterialClient("localhost:8000")
    with pytest.raises(ValueError, match="max_rows"):
        MaterialClient("http://x", ClientConfig(max_rows=0))


def test_unreachable_real_port_is_unavailable():
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    client = MaterialClient(f"http://127.0.0.1:{port}", ClientConfig(retries=1, **FAST))
    with pytest.raises(ServerUnavailable, match="unreachable after 2 attempt"):
        client.materials()


def test_fallback_takes_over_when_the_server_goes_away(model_dir, caplog):
    from neumip.client.http import FallbackEvaluator

    server = FakeServer(model_dir)
    evaluator = FallbackEvaluator(client_for(server, retries=0), LocalMaterials(model_dir))
    queries = random_queries(50, seed=9)
    expected = server.local.evaluate("rand16", queries)
    np.testing.assert_array_equal(evaluator.evaluate("rand16", queries), expected)
    assert evaluator.switched is None
    server.failures = [httpx.ConnectError("refused")] * 10
    np.testing.assert_array_equal(evaluator.evaluate("rand16", queries), expected)
    assert "unreachable" in evaluator.switched and "falling back to LocalMaterials" in caplog.text
    seen = len(server.requests)
    evaluator.evaluate("rand16", queries)
    assert len(server.requests) == seen  # stays on the fallback


def test_fallback_does_not_hide_client_errors(model_dir):
    from neumip.client.http import FallbackEvaluator

    evaluator = FallbackEvaluator(client_for(FakeServer(model_dir)), LocalMaterials(model_dir))
    with pytest.raises(ServerError, match="404"):
        evaluator.evaluate("nope", random_queries(3))
    assert evaluator.switched is None


class _HandlerLog:
    connections = 0


def _closing_server(model_dir):
    """A stand-in HTTP/1.1 server (standard library) that answers evaluations and then closes each
    connection without saying so: the client's kept-alive connection goes stale between requests."""
    import http.server
    import threading

    local = LocalMaterials(model_dir)
    log = _HandlerLog()

    class Handler(http.server.BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def setup(self):
            log.connections += 1
            super().setup()

        def do_POST(self):
            body = self.rfile.read(int(self.headers["Content-Length"]))
            name = self.path.split("/")[-2]
            answer = wire.encode_response(local.evaluate(name, wire.decode_request(body)))
            self.send_response(200)
            self.send_header("Content-Length", str(len(answer)))
            self.end_headers()
            self.wfile.write(answer)
            self.close_connection = True  # no "Connection: close" header: the client finds out later

        def log_message(self, *args):
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, log, local


def test_stale_kept_alive_connection_is_reopened_without_a_retry(model_dir, caplog):
    server, log, local = _closing_server(model_dir)
    try:
        client = MaterialClient(f"http://127.0.0.1:{server.server_address[1]}", ClientConfig(retries=0))
        for seed in range(3):
            queries = random_queries(100, seed=seed)
            np.testing.assert_array_equal(client.evaluate("rand16", queries), local.evaluate("rand16", queries))
        client.close()
    finally:
        server.shutdown()
        server.server_close()
    assert log.connections == 3  # one per request, each reopened by the client
    assert "retrying" not in caplog.text  # retries=0: a stale connection is not a failed attempt


def client_port(client: MaterialClient) -> int:
    """The local port of the client's kept-alive connection (a new one means a new connection)."""
    reply = client._http.get("/v2/health/live")
    return reply.extensions["network_stream"].get_extra_info("client_addr")[1]


@pytest.mark.parametrize("protocol", ["msgpack", "v2"])
def test_real_server_answers_bit_identical_on_one_kept_alive_connection(serve, model_dir, protocol):
    """MaterialClient, as it runs in a render, against a real `neumip serve` process, in both protocols."""
    server = serve(max_rows=5000)
    reference = LocalMaterials(model_dir)
    with MaterialClient(server.url, ClientConfig(max_rows=3000), protocol=protocol) as client:
        assert client.materials() == ["flat16", "lambert", "rand16"]
        port = client_port(client)
        for n, seed in ((1, 0), (7000, 1), (20000, 2)):  # 7000 and 20000: several requests each
            queries = random_queries(n, seed=seed)
            rgb = client.evaluate("rand16", queries)
            np.testing.assert_array_equal(rgb, reference.evaluate("rand16", queries))
            assert rgb.flags.writeable
        assert set(client.server_timing) == {"read", "decode", "evaluate", "encode"}
        assert client_port(client) == port  # every request on the one kept-alive connection
        with pytest.raises(ServerError, match="answered 404: unknown material 'nope'") as info:
            client.evaluate("nope", random_queries(4))
        assert info.value.status == 404
        with pytest.raises(ServerError, match="answered 400: queries must be finite"):
            client._evaluate_once("rand16", np.full((2, 7), np.nan, np.float32))  # past the client's own check
        assert client.evaluate("lambert", np.zeros((0, 7), np.float32)).shape == (0, 3)
    with MaterialClient(server.url, ClientConfig(max_rows=6000), protocol=protocol) as client:
        with pytest.raises(ServerError, match="answered 413: 6000 queries .* is more than the limit of 5000"):
            client.evaluate("rand16", random_queries(6000))


def test_unknown_protocol_is_refused():
    with pytest.raises(ValueError, match="msgpack, v2"):
        MaterialClient("http://x", protocol="grpc")


def test_real_server_gone_and_back(serve, model_dir):
    """A server that has stopped: the client reports it unavailable after its retries."""
    server = serve()
    client = MaterialClient(server.url, ClientConfig(retries=1, **FAST))
    q = random_queries(100, seed=5)
    assert client.evaluate("rand16", q).shape == (100, 3)
    assert server.stop() == 0
    with pytest.raises(ServerUnavailable, match="unreachable after 2 attempt"):
        client.evaluate("rand16", q)
    client.close()


class Recording(httpx.HTTPTransport):
    """The network transport, keeping each request it sends (body read) to look at after."""

    def __init__(self) -> None:
        super().__init__()
        self.requests: list[httpx.Request] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        request.read()
        self.requests.append(request)
        return super().handle_request(request)


def test_real_server_refuses_a_version_1_file_naming_its_upgrade_and_takes_groups(serve, model_dir, tmp_path):
    """A real `neumip serve` with a model file of contract version 1 (a test fixture) beside a current
    one: in both protocols the client's error for the old one names the command that upgrades it, and
    groups for the current one go whole and answer with the bits of in-process evaluation."""
    shutil.copy(PRE_GROUPS, tmp_path / "old.onnx")
    shutil.copy(model_dir / "rand16.onnx", tmp_path / "rand16.onnx")
    server = serve(tmp_path)
    local = LocalMaterials(tmp_path)
    groups = np.ascontiguousarray(np.hstack([random_queries(3000, seed=1), random_queries(3000, seed=2)[:, 3:5]]))
    for protocol in ("msgpack", "v2"):
        transport = Recording()
        with MaterialClient(server.url, ClientConfig(max_rows=4000), transport, protocol) as client:
            with pytest.raises(ServerError, match="neumip export old.onnx -o NEW.onnx") as info:
                client.evaluate("old", groups)
            assert info.value.status in (400, 404)
            rgb = client.evaluate("rand16", groups)
            np.testing.assert_array_equal(rgb, local.evaluate("rand16", groups))
        # old: refused once; rand16: 3000 groups of two (6000 answers) in two requests
        assert sent_widths(transport.requests) == [9, 9, 9], protocol


def test_sampling_lobe_comes_from_the_listing(model_dir):
    """The server's listing carries each loaded model's sampling lobe (`Material.info`); a malformed
    one is ignored (it only moves noise), a material without one has None."""
    lobe = {"alpha": 0.2, "weight": 0.5}

    def handler(request: httpx.Request) -> httpx.Response:
        if request.url.path == wire.MATERIALS_PATH + "/lazy":  # describing it loads it
            return httpx.Response(200, json={"name": "lazy", "sampling": {"alpha": 0.3, "weight": 0.25}})
        return httpx.Response(200, json={"materials": [
            {"name": "glossy", "sampling": lobe}, {"name": "odd", "sampling": {"alpha": "x"}},
            {"name": "huge", "sampling": {"alpha": 10**400, "weight": 0.5}},
            {"name": "matte", "sampling": None}, {"name": "lazy"}]})

    client = client_for(handler)
    assert client.sampling("glossy") == C.SamplingLobe(0.2, 0.5)
    assert client.sampling("odd") is None and client.sampling("huge") is None and client.sampling("matte") is None
    assert client.sampling("lazy") == C.SamplingLobe(0.3, 0.25)
    assert client.sampling("unknown") is None
