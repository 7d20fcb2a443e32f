"""Issue 27 against real `neumip serve` processes: answers are bounded on the way out (an answer budget
reserved before evaluation, a write timeout for clients that do not read), JSON answers leave the event
loop free, header integers never cause a 500, a shutdown answers a stalled upload in JSON, trailing
slashes are not redirected, and a fuzz of headers causes no 5xx."""

from __future__ import annotations

import json
import os
import random
import socket
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest

from neumip.core import wire
from neumip.core.contract import random_queries

from .raw_http import answer, connect, metric

MiB = 1 << 20


def infer_json_output(url: str, q: np.ndarray) -> httpx.Response:
    """A v2 infer with binary queries and the answer as JSON (no binary_data_output)."""
    head = json.dumps({"inputs": [{"name": "queries", "datatype": "FP32", "shape": list(q.shape),
                                   "parameters": {"binary_data_size": q.nbytes}}]}).encode()
    return httpx.post(url + "/v2/models/rand16/infer", content=head + q.tobytes(), timeout=120,
                      headers={wire.INFER_HEADER_LENGTH: str(len(head))})


def status_of(sock: socket.socket, wait_s: float) -> int | None:
    """The status of the answer arriving on `sock`; None if none came (closed, reset, or `wait_s` passed)."""
    sock.settimeout(wait_s)
    head = b""
    try:
        while b"\r\n\r\n" not in head:
            chunk = sock.recv(4096)
            if not chunk:
                break
            head += chunk
    except (TimeoutError, ConnectionResetError):
        pass
    return int(head.split(b" ", 2)[1]) if b"\r\n\r\n" in head else None


PROBE = """
import sys, time, httpx
took = []
with httpx.Client(timeout=30) as http:
    http.get(sys.argv[1])
    print("ready", flush=True)
    while not sys.stdin.readline().strip():  # an empty line: probe again; "stop": end
        start = time.perf_counter()
        assert http.get(sys.argv[1]).status_code == 200
        took.append(time.perf_counter() - start)
took.sort()
print(took[-1], took[int(0.99 * len(took))], len(took))
"""
"""Probes /v2/health/live from a process of its own (a thread of the test would wait for the GIL that
the test's own request threads hold)."""


class HealthProbe:
    """/v2/health/live timed every 20 ms from another process, from `start` until `stop` -> (max s, 99th
    percentile s, count)."""

    def __init__(self, url: str) -> None:
        self.process = subprocess.Popen([sys.executable, "-c", PROBE, url + "/v2/health/live"], text=True,
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        assert self.process.stdout.readline().strip() == "ready"
        self.busy = threading.Event()
        self.thread = threading.Thread(target=self._tick)

    def _tick(self) -> None:
        while self.busy.is_set():
            self.process.stdin.write("\n")
            self.process.stdin.flush()
            time.sleep(0.02)

    def start(self) -> None:
        self.busy.set()
        self.thread.start()

    def stop(self) -> tuple[float, float, int]:
        self.busy.clear()
        self.thread.join()
        out, _ = self.process.communicate("stop\n", timeout=30)
        worst, p99, count = out.split()
        return float(worst), float(p99), int(count)


@pytest.mark.parametrize("rows, requests, bound_s", [
    (300_000, 2, 0.3),
    pytest.param(2_000_000, 3, 0.3, marks=pytest.mark.slow),
], ids=["300k-rows", "2M-rows"])
def test_json_answers_leave_the_event_loop_free(serve, reference, rows, requests, bound_s):
    """F3: a 2M-row JSON answer was encoded on the event loop, freezing every client, health included,
    for 2.7-2.9 s. It is encoded in a thread, piece by piece, and streamed. The issue's goal is 100 ms
    (met at 2M rows, load average 11: max 100-132 ms, 99th percentile 64 ms); the bound leaves room for
    the busy shared machine. Old code: max 1.2 s at 300k rows, 11 s at 2M."""
    server = serve()
    q = random_queries(rows, seed=3)
    replies, probe = [], HealthProbe(server.url)
    probe.start()
    try:
        workers = [threading.Thread(target=lambda: replies.append(infer_json_output(server.url, q)))
                   for _ in range(requests)]
        for worker in workers:
            worker.start()
        for worker in workers:
            worker.join(timeout=300)
    finally:
        worst, p99, count = probe.stop()
    assert [r.status_code for r in replies] == [200] * requests
    rgb = np.asarray(replies[0].json()["outputs"][0]["data"], dtype=np.float32).reshape(rows, 3)
    np.testing.assert_array_equal(rgb, reference.evaluate("rand16", q))  # the bits, through JSON
    print(f"health while {requests} x {rows}-row JSON answers: max {worst * 1e3:.0f} ms, 99th percentile "
          f"{p99 * 1e3:.0f} ms over {count} (load average {os.getloadavg()[0]:.1f})")
    assert worst < bound_s


def test_clients_that_do_not_read_are_bounded_then_dropped(serve):
    """F2: clients that send valid large requests and never read held every answer in memory, without
    bound or end (13 of them OOM-killed a 2 GiB container). Answers are reserved before evaluation
    (past the budget: 503 at once), and a client that reads nothing for write_timeout_s is dropped,
    its answer freed."""
    rows, clients = 500_000, 8  # 6 MB answers: more than loopback's socket buffers hold
    server = serve(max_rows=rows, answer_budget_bytes=4 * 12 * rows + 1024, write_timeout_s=2, body_timeout_s=30)
    body = wire.encode_request(random_queries(rows, seed=2))
    idle = server.rss_bytes()
    host, port = server.host_port.split(":")
    socks = []
    for _ in range(clients):
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # reads nothing, takes little
        sock.settimeout(30)
        sock.connect((host, int(port)))
        sock.sendall((f"POST {wire.EVALUATE_PATH.format(name='rand16')} HTTP/1.1\r\nHost: x\r\n"
                      f"Content-Type: {wire.MSGPACK_MEDIA_TYPE}\r\nContent-Length: {len(body)}\r\n\r\n").encode()
                     + body)
        socks.append(sock)
    deadline = time.monotonic() + 60
    while metric(server, "neumip_queue_rows") > 0 and time.monotonic() < deadline:
        time.sleep(0.1)
    held = metric(server, "neumip_answer_bytes")
    peak = server.rss_bytes()
    took = []
    for _ in range(5):
        start = time.perf_counter()
        assert httpx.get(server.url + "/v2/health/live", timeout=10).status_code == 200
        took.append(time.perf_counter() - start)
    time.sleep(4)  # past the write timeout
    statuses = []
    for sock in socks:
        statuses.append(status_of(sock, wait_s=5))
        sock.close()
    freed = metric(server, "neumip_answer_bytes")
    print(f"answers held {held / MiB:.1f} MiB; RSS idle {idle / MiB:.0f}, with the clients {peak / MiB:.0f}, "
          f"after {server.rss_bytes() / MiB:.0f} MiB; health max {max(took) * 1e3:.0f} ms; statuses {statuses}")
    assert statuses.count(503) == clients - 4  # the budget held four answers
    assert 0 < held <= 4 * 12 * rows and freed == 0
    assert max(took) < 1.0
    assert "did not read its answer" in server.log.read_text()


@pytest.mark.parametrize("value", ["\xb2", "\xb9", "\xb3", "1\xb2", "9" * 5000, "-1", "0x10", ""])
def test_header_integers_are_ascii_digits(live_server, value):
    """F1: an Inference-Header-Content-Length of "²" was a 500 (str.isdigit accepts superscripts, int
    refuses them); 5000 digits too (int refuses more than 4300). Now 400 naming the header."""
    sock = connect(live_server)
    sock.sendall(b"POST /v2/models/rand16/infer HTTP/1.1\r\nHost: x\r\nInference-Header-Content-Length: "
                 + value.encode("latin-1") + b"\r\nContent-Length: 2\r\nConnection: close\r\n\r\n{}")
    reply = answer(sock, wait_s=10)
    sock.close()
    assert reply is not None and reply[0] == 400, reply
    assert "Inference-Header-Content-Length must be a non-negative integer" in reply[1]["error"]


def test_trailing_slashes_are_not_redirected(live_server):
    """A trailing slash was a 307 to the path without it; it is an unknown path (404), in JSON."""
    for path in ("/v2/health/live/", "/v1/materials/", "/v2/models/rand16/"):
        reply = httpx.get(live_server.url + path, follow_redirects=False)
        assert reply.status_code == 404 and "no such endpoint" in reply.json()["error"], path


def test_a_stalled_upload_cut_off_by_shutdown_is_answered_in_json(serve):
    """On SIGTERM a client whose body had not arrived got a plain-text 500 once the graceful period ran
    out; it gets a JSON 503 saying to retry, and the server still exits 0."""
    server = serve(graceful_shutdown_s=1)
    sock = connect(server)
    sock.sendall((f"POST {wire.EVALUATE_PATH.format(name='rand16')} HTTP/1.1\r\nHost: x\r\n"
                  f"Content-Type: {wire.MSGPACK_MEDIA_TYPE}\r\nContent-Length: 1000\r\n\r\n").encode() + b"x" * 10)
    time.sleep(0.3)
    server.process.terminate()
    reply = answer(sock, wait_s=10)
    sock.close()
    assert reply is not None and reply[0] == 503 and "shut down" in reply[1]["error"], reply
    assert server.process.wait(30) == 0  # before the fixture's own SIGTERM, which would find it exiting


TEXT_BYTES = [*range(0x20, 0x7F), *range(0x80, 0x100)]
"""Bytes a header value may hold (RFC 9110's VCHAR, space and obs-text; control bytes get a 400 from the
HTTP parser before the app sees them)."""


def fuzzed_headers(rng: random.Random) -> bytes:
    """A request with a two-byte body to an infer, evaluate or control path, with one to three headers of
    fuzzed values (the v2 header length, the finding's, in 60 %): numbers in odd spellings (superscripts, signs, hex, spaces, 30 digits), media types,
    or random bytes (`TEXT_BYTES`)."""
    names = [b"Content-Length", b"Content-Type", b"Content-Encoding", b"Authorization", b"Transfer-Encoding",
             b"Expect", b"X-" + bytes(rng.choice(b"abc-") for _ in range(5))]
    values = [b"\xb2", b"\xb9", b"\xb3", b"1\xb2", b"\xd9\xa3", b"-1", b"+2", b"1e3", b"0x10", b" 2 ", b"9" * 30,
              b"\x00", b"0", b"2", b"chunked", b"application/json", b"application/msgpack", b"100-continue",
              b"gzip", b""]
    path = rng.choice([b"/v2/models/rand16/infer"] * 3 + [wire.EVALUATE_PATH.format(name="rand16").encode(),
                       b"/v2/repository/models/flat16/unload", b"/v2/health/live/"])
    headers = {b"Host": b"x", b"Connection": b"close", b"Content-Length": b"2"}
    picked = rng.sample(names, rng.randint(0, 2)) + [b"Inference-Header-Content-Length"] * (rng.random() < 0.6)
    for name in picked or names[:1]:
        headers[name] = rng.choice(values) if rng.random() < 0.7 else bytes(
            rng.choice(TEXT_BYTES) for _ in range(rng.randint(1, 12)))
    lines = [b"POST " + path + b" HTTP/1.1"] + [name + b": " + value for name, value in headers.items()]
    return b"\r\n".join(lines) + b"\r\n\r\n{}"


@pytest.mark.parametrize("count", [1500, pytest.param(10_000, marks=pytest.mark.slow)])
def test_fuzzed_headers_cause_no_server_error(live_server, count):
    """Issue 27's goal: a header fuzz of 10 000 requests gives 0 x 5xx (the default run sends 1 500)."""
    rng = random.Random(count)
    host, port = live_server.host_port.split(":")
    statuses: dict[int, int] = {}
    for _ in range(count):
        with socket.create_connection((host, int(port)), timeout=10) as sock:
            sock.sendall(fuzzed_headers(rng))
            status = status_of(sock, wait_s=2)
            if status == 100:  # Expect: 100-continue, then the answer
                status = status_of(sock, wait_s=2)
        statuses[status] = statuses.get(status, 0) + 1
    print(f"{count} fuzzed requests (None: no answer within 2 s, a body still awaited): {statuses}")
    assert not [s for s in statuses if s is not None and s >= 500], statuses
