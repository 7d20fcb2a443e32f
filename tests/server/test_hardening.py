"""Memory and time per connection, and protocol edges, against real `neumip serve` processes.

Each test reproduces an attack or a fault seen against the server (hostile declared lengths, a full
queue, huge JSON, a slow uploader, huge or slow headers, unparsable requests, a model answering NaN)
with raw sockets on 127.0.0.1, in bounded loops: every socket has a timeout and every wait a deadline.
"""

from __future__ import annotations

import shutil
import socket
import statistics
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core import wire
from neumip.core.contract import random_queries
from neumip.client.http import ClientConfig, MaterialClient, ServerUnavailable

from .raw_http import answer, connect, metric

PATH = wire.EVALUATE_PATH.format(name="rand16")
MiB = 1 << 20
SMALL = dict(
    max_body_bytes=16 * MiB, max_json_body_bytes=MiB, body_budget_bytes=64 * MiB, max_rows=200_000,
    max_queue_rows=1_000_000, body_timeout_s=3, header_timeout_s=2, max_header_bytes=16 * 1024, max_wait_ms=1000,
)
"""Small budgets and short timeouts, so that each attack runs in seconds; a long merge wait, so that a
request held back by a batch would show."""


def post_head(length: int, path: str = PATH, content_type: str = wire.MSGPACK_MEDIA_TYPE) -> bytes:
    return (f"POST {path} HTTP/1.1\r\nHost: x\r\nContent-Type: {content_type}\r\n"
            f"Content-Length: {length}\r\n\r\n").encode()


def live_in(server, bound_s: float = 1.0) -> float:
    """Seconds the server takes to answer /v2/health/live (asserted below `bound_s`)."""
    start = time.perf_counter()
    assert httpx.get(server.url + "/v2/health/live", timeout=10).status_code == 200
    took = time.perf_counter() - start
    assert took < bound_s, f"health check took {took:.2f} s"
    return took


@pytest.fixture(scope="module")
def hardened(serve_module, model_dir, tmp_path_factory):
    """A server with small budgets (`SMALL`) serving the test materials plus `nanny`, a model that
    answers NaN for u > 100 (which warm-up never asks)."""
    folder = tmp_path_factory.mktemp("hardened")
    for onnx_file in model_dir.glob("*.onnx"):
        shutil.copy(onnx_file, folder / onnx_file.name)
    write_nan_model(folder / "nanny.onnx")
    return serve_module(folder, **SMALL)


def write_nan_model(path) -> None:
    """rgb = 0.1 + 0 * log(100 - u): 0.1 for u < 100, NaN beyond (a model broken for some inputs); like
    every model of the contract, it takes query groups (N, 5 + 2 K) and answers (N, 3 K)."""
    import onnx
    from onnx import TensorProto, helper

    def const(name, values, dtype=TensorProto.FLOAT, dims=None):
        return helper.make_tensor(name, dtype, dims or [len(values)], values)

    nodes = [
        helper.make_node("Slice", [C.ONNX_INPUT, "zero", "one", "one"], ["u"]),  # (N, 1)
        helper.make_node("Sub", ["hundred", "u"], ["d"]),
        helper.make_node("Log", ["d"], ["log"]),
        helper.make_node("Mul", ["log", "nought"], ["z"]),
        helper.make_node("Add", ["z", "grey"], ["rgb1"]),  # (N, 1)
        helper.make_node("Shape", [C.ONNX_INPUT], ["shape"]),  # [N, 5 + 2 K]
        helper.make_node("Mul", ["shape", "three"], ["thrice"]),  # [3 N, 15 + 6 K]
        helper.make_node("Sub", ["thrice", "fifteen"], ["minus"]),
        helper.make_node("Div", ["minus", "two"], ["answers"]),  # [_, 3 K]
        helper.make_node("Slice", ["shape", "zero", "one"], ["n"]),
        helper.make_node("Slice", ["answers", "one", "two"], ["k3"]),
        helper.make_node("Concat", ["n", "k3"], ["out_shape"], axis=0),
        helper.make_node("Expand", ["rgb1", "out_shape"], [C.ONNX_OUTPUT]),  # (N, 3 K)
    ]
    graph = helper.make_graph(
        nodes, "nan_for_large_u",
        [helper.make_tensor_value_info(C.ONNX_INPUT, TensorProto.FLOAT, ["N", "width"])],
        [helper.make_tensor_value_info(C.ONNX_OUTPUT, TensorProto.FLOAT, ["N", "answers"])],
        [const("zero", [0], TensorProto.INT64), const("one", [1], TensorProto.INT64), const("hundred", [100.0]),
         const("nought", [0.0]), const("grey", [0.1], dims=[1, 1]), const("two", [2], TensorProto.INT64),
         const("three", [3], TensorProto.INT64), const("fifteen", [15], TensorProto.INT64)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    helper.set_model_props(model, {C.META_CONTRACT: C.CONTRACT_VERSION, C.META_DESCRIPTION: "NaN for u > 100"})
    onnx.save(model, path)


# --- memory -----------------------------------------------------------------------------------------
def test_declared_lengths_reserve_no_memory_and_the_rest_is_refused_at_once(live_server):
    """The reproduction: 16 sockets each declaring 128 MiB and sending 1 byte (default settings). Four
    fit the 512 MiB body budget and hold no memory; twelve get 503 + Retry-After at once."""
    before = live_server.rss_bytes()
    socks = [connect(live_server) for _ in range(16)]
    try:
        for sock in socks:
            sock.sendall(post_head(128 * MiB) + b"\x82")
        replies = [answer(sock, wait_s=1.0) for sock in socks]
        refused = [r for r in replies if r is not None]
        time.sleep(0.5)
        growth = live_server.rss_bytes() - before
        health_s = live_in(live_server)
        print(f"16 x 128 MiB declared, 1 byte sent: {len(refused)} refused at once, RSS {before / MiB:.0f} -> "
              f"{(before + growth) / MiB:.0f} MiB, health check {health_s * 1e3:.1f} ms")
        assert len(refused) == 12 and {r[0] for r in refused} == {503}, replies
        assert all("budget" in r[1]["error"] for r in refused)
        assert growth < 32 * MiB, f"RSS grew by {growth / MiB:.0f} MiB"
        assert metric(live_server, "neumip_body_bytes ") == 4 * 128 * MiB
    finally:
        for sock in socks:
            sock.close()
    deadline = time.monotonic() + 10  # closed sockets give their reservations back
    while metric(live_server, "neumip_body_bytes ") and time.monotonic() < deadline:
        time.sleep(0.1)
    assert metric(live_server, "neumip_body_bytes ") == 0


def test_bodies_that_do_arrive_stay_within_the_budget(hardened):
    """16 clients each upload a 16 MiB body but its last byte: RSS grows by at most 1.5x the 64 MiB
    budget, the admitted uploads time out with 408 and their memory goes back."""
    before = hardened.rss_bytes()
    size, socks, refused = 16 * MiB, [], 0
    try:
        for _ in range(16):
            sock = connect(hardened)
            socks.append(sock)
            sock.sendall(post_head(size))
            early = answer(sock, wait_s=0.2)
            if early is not None:  # refused from the headers: nothing more to send
                assert early[0] == 503, early
                refused += 1
                continue
            piece = b"\x00" * MiB
            for lo in range(0, size - 1, MiB):
                sock.sendall(piece[: min(MiB, size - 1 - lo)])
        time.sleep(0.5)
        peak = hardened.rss_bytes() - before
        replies = [answer(sock, wait_s=SMALL["body_timeout_s"] + 5) for sock in socks]
    finally:
        for sock in socks:
            sock.close()
    print(f"16 x 16 MiB uploads against a 64 MiB budget: {refused} refused at once, RSS growth {peak / MiB:.0f} MiB")
    assert refused == 12
    assert peak <= 1.5 * SMALL["body_budget_bytes"], f"RSS grew by {peak / MiB:.0f} MiB"
    timed_out = [r for r in replies if r is not None and r[0] == 408]
    assert len(timed_out) == 4 and "not complete after 3 s" in timed_out[0][1]["error"]
    assert metric(hardened, "neumip_body_bytes ") == 0


def test_a_full_queue_refuses_from_the_headers(hardened):
    """With the queue taken, a 7 MiB body is refused 1 KiB in, without waiting for the rest."""
    holders = [connect(hardened) for _ in range(5)]
    try:
        for holder in holders:  # 5 x 200 000 rows declared: every row of the queue reserved
            holder.sendall(post_head(SMALL["max_rows"] * wire.ROW_BYTES) + b"\x82")
        time.sleep(0.2)
        sock = connect(hardened)
        start = time.perf_counter()
        sock.sendall(post_head(7 * MiB) + b"\x00" * 1024)
        reply = answer(sock, wait_s=5)
        took = time.perf_counter() - start
        sock.close()
        # a client that uploads everything before it reads still gets the 503, not a broken connection
        with MaterialClient(hardened.url, ClientConfig(retries=0)) as client:
            with pytest.raises(ServerUnavailable, match=r"busy \(503\).*rows queued"):
                client.evaluate("rand16", random_queries(SMALL["max_rows"]))
    finally:
        for holder in holders:
            holder.close()
    print(f"queue full: 503 for a 7 MiB body 1 KiB in after {took * 1e3:.1f} ms")
    assert reply is not None and reply[0] == 503 and "rows queued" in reply[1]["error"]
    assert took < 2


def test_json_over_its_limit_is_refused_before_it_is_read(hardened):
    sock = connect(hardened)
    start = time.perf_counter()
    sock.sendall(post_head(12 * MiB, content_type="application/json") + b'{"queries": [')
    reply = answer(sock, wait_s=5)
    sock.close()
    assert reply is not None and reply[0] == 413 and "JSON limit" in reply[1]["error"]
    assert time.perf_counter() - start < 2
    v2 = httpx.post(hardened.url + "/v2/models/rand16/infer", content=b"{" + b" " * (2 * MiB) + b"}", timeout=10)
    assert v2.status_code == 413 and "JSON limit" in v2.json()["error"]
    live_in(hardened)


# --- time ---------------------------------------------------------------------------------------------
def test_a_slow_uploader_does_not_hold_batches_open(hardened):
    """While clients upload bodies byte by byte, 16-row requests answer without the 1 s merge wait."""
    body = wire.encode_request(random_queries(16, seed=1))
    stop = threading.Event()

    def slow_upload(delay: float) -> None:  # one upload after the other (each ends with a 408), until stopped
        stop.wait(delay)
        while not stop.is_set():
            with connect(hardened) as sock:
                try:
                    sock.sendall(post_head(len(body)))
                    for i in range(len(body) - 1):
                        if stop.wait(0.05):
                            return
                        sock.sendall(body[i : i + 1])
                except OSError:  # timed out by the server: start the next one
                    pass

    half = SMALL["body_timeout_s"] / 2  # two staggered: one is always in flight, also while the other restarts
    uploaders = [threading.Thread(target=slow_upload, args=(delay,)) for delay in (0, half)]
    for uploader in uploaders:
        uploader.start()
    try:
        time.sleep(0.2)
        assert metric(hardened, "neumip_body_bytes ") > 0  # the upload is in flight
        latencies = []
        with MaterialClient(hardened.url, ClientConfig(timeout_s=30)) as client:
            for seed in range(10):
                q = random_queries(16, seed=seed)
                start = time.perf_counter()
                client.evaluate("rand16", q)
                latencies.append(time.perf_counter() - start)
    finally:
        stop.set()
        for uploader in uploaders:
            uploader.join(timeout=10)
    p50 = statistics.median(latencies)
    print(f"16-row p50 with a slow uploader and a 1 s merge wait: {p50 * 1e3:.1f} ms")
    assert p50 < 0.5, f"16-row p50 {p50 * 1e3:.0f} ms: a batch waited for the upload"


def test_header_over_the_limit_is_431_and_stalls_nobody(hardened):
    sock = connect(hardened)
    sock.sendall(b"GET /v2 HTTP/1.1\r\nHost: x\r\nX-Big: ")
    reply = None
    try:
        for _ in range(64):  # up to 4 MiB of header, until the server answers
            sock.sendall(b"a" * 65536)
    except (BrokenPipeError, ConnectionResetError):
        pass
    reply = answer(sock, wait_s=5)
    sock.close()
    assert reply is not None and reply[0] == 431 and "16384 bytes" in reply[1]["error"], reply
    live_in(hardened)


def test_slow_or_missing_headers_time_out_with_408(hardened):
    idle, slow = connect(hardened), connect(hardened)
    slow.sendall(b"GET /v2 HTTP/1.1\r\nHost: x\r\n")  # and never the blank line
    start = time.perf_counter()
    replies = [answer(sock, wait_s=SMALL["header_timeout_s"] + 5) for sock in (idle, slow)]
    took = time.perf_counter() - start
    for sock in (idle, slow):
        sock.close()
    for reply in replies:
        assert reply is not None and reply[0] == 408 and "not complete after 2 s" in reply[1]["error"], reply
    assert took < SMALL["header_timeout_s"] + 3


@pytest.mark.parametrize("payload", [
    b"\x00\x01\x02 not http\r\n\r\n",
    b"BREW /v2 HTTP/1.1\r\nHost: x\r\n\r\n",
    post_head(0).replace(b"Content-Length: 0", b"Content-Length: abc"),
    post_head(0).replace(b"Content-Length: 0", b"Content-Length: -5"),
    f"POST {PATH} HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\nabc\r\n".encode(),
], ids=["garbage", "unknown method", "letters length", "negative length", "bad chunk size"])
def test_errors_before_the_app_are_json(hardened, payload):
    sock = connect(hardened)
    sock.sendall(payload)
    reply = answer(sock, wait_s=5)
    sock.close()
    assert reply is not None and reply[0] == 400 and "invalid HTTP request" in reply[1]["error"], reply


# --- answers ------------------------------------------------------------------------------------------
def test_a_model_answering_nan_is_a_500_naming_the_material(hardened):
    q = random_queries(300, seed=4)
    q[:, C.U] = np.abs(q[:, C.U])
    q[123, C.U] = 150.0  # the one row the model answers NaN for
    before = metric(hardened, 'neumip_nonfinite_answers_total{material="nanny"}')
    resp = httpx.post(hardened.url + wire.EVALUATE_PATH.format(name="nanny"), content=wire.encode_request(q),
                      headers={"content-type": wire.MSGPACK_MEDIA_TYPE}, timeout=30)
    assert resp.status_code == 500, resp.text
    message = resp.json()["error"]
    assert "'nanny'" in message and "query row 123" in message and "nan" in message
    v2 = httpx.post(hardened.url + "/v2/models/nanny/infer", timeout=30,
                    json={"inputs": [{"name": "queries", "datatype": "FP32", "shape": [300, 7], "data": q.ravel().tolist()}]})
    assert v2.status_code == 500 and "'nanny'" in v2.json()["error"]
    assert metric(hardened, 'neumip_nonfinite_answers_total{material="nanny"}') - before == 2
    q[123, C.U] = 0.5
    ok = httpx.post(hardened.url + wire.EVALUATE_PATH.format(name="nanny"), content=wire.encode_request(q),
                    headers={"content-type": wire.MSGPACK_MEDIA_TYPE}, timeout=30)
    np.testing.assert_allclose(wire.decode_response(ok.content), 0.1, rtol=1e-6)


# --- start-up ------------------------------------------------------------------------------------------
def test_serve_on_a_busy_port_fails_at_once_with_one_line(model_dir):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        start = time.perf_counter()
        run = subprocess.run(
            [sys.executable, "-m", "neumip.client.cli", "serve", "--port", str(port), "--model-dir", str(model_dir)],
            capture_output=True, text=True, timeout=60,
        )
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and f"cannot listen on 127.0.0.1:{port}" in lines[0], run.stderr
    assert "startup complete" not in run.stderr + run.stdout
    print(f"busy port: exit 2 after {time.perf_counter() - start:.1f} s: {lines[0]}")
