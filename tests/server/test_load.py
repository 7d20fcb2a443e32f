"""Load and faults against a real `neumip serve` process on loopback (bounded in time).

16 concurrent clients for a few seconds: zero errors, answers bit-identical to in-process evaluation,
resident memory growth bounded. A tiny queue under the same load answers 503 + Retry-After, never
a timeout or a crash.
"""

from __future__ import annotations

import threading
import time

import httpx
import numpy as np
import pytest

from neumip.core import wire
from neumip.core.contract import random_queries

CLIENTS = 16
MEMORY_BOUND = 64 << 20
"""Most resident memory the server may gain between the warm-up round and the end of the load."""


def hammer(url: str, work: list[tuple[str, np.ndarray, np.ndarray]], seconds: float, seed: int) -> dict:
    """One client: random requests from `work` for `seconds`; returns counts and the bad answers."""
    rng = np.random.default_rng(seed)
    stats = {"ok": 0, "mismatch": 0, "status": {}, "retry_after": set()}
    deadline = time.monotonic() + seconds
    with httpx.Client(base_url=url, timeout=30) as http:
        while time.monotonic() < deadline:
            name, q, expected = work[rng.integers(len(work))]
            resp = http.post(wire.EVALUATE_PATH.format(name=name), content=wire.encode_request(q),
                             headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
            stats["status"][resp.status_code] = stats["status"].get(resp.status_code, 0) + 1
            if resp.status_code == 200:
                stats["ok"] += 1
                stats["mismatch"] += not np.array_equal(wire.decode_response(resp.content), expected)
            elif resp.status_code == 503:
                stats["retry_after"].add(resp.headers.get("retry-after"))
    return stats


def run_clients(url: str, work, seconds: float) -> list[dict]:
    results: list[dict] = [None] * CLIENTS

    def client(i: int) -> None:
        results[i] = hammer(url, work, seconds, seed=i)

    threads = [threading.Thread(target=client, args=(i,)) for i in range(CLIENTS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=seconds + 60)
    assert all(r is not None for r in results), "a client thread did not finish"
    return results


@pytest.fixture(scope="module")
def work(reference):
    """Requests of mixed sizes (aligned and not) with their in-process answers."""
    sizes = [1, 5, 16, 100, 333, 1024, 2000, 4096]
    return [
        (name, q, reference.evaluate(name, q))
        for i, (name, n) in enumerate((name, n) for name in ("rand16", "flat16") for n in sizes)
        for q in [random_queries(n, seed=100 + i)]
    ]


def test_sixteen_clients_no_errors_bit_identical_bounded_memory(live_server, work):
    run_clients(live_server.url, work, seconds=2)  # warm-up round: allocator pools, thread stacks
    before = live_server.rss_bytes()
    results = run_clients(live_server.url, work, seconds=8)
    growth = live_server.rss_bytes() - before
    statuses = {}
    for r in results:
        for code, count in r["status"].items():
            statuses[code] = statuses.get(code, 0) + count
    total_ok = sum(r["ok"] for r in results)
    print(f"load: {total_ok} requests answered, statuses {statuses}, RSS growth {growth / 2**20:.1f} MiB")
    assert set(statuses) == {200}, statuses
    assert total_ok >= CLIENTS
    assert sum(r["mismatch"] for r in results) == 0
    assert growth < MEMORY_BOUND, f"resident memory grew by {growth / 2**20:.1f} MiB under load"
    assert httpx.get(live_server.url + "/v2/health/ready").status_code == 200


def test_queue_overflow_gives_503_not_timeouts(serve, work):
    server = serve(max_rows=4096, max_queue_rows=4096, ort_workers=1)
    big = [w for w in work if w[1].shape[0] >= 2000]
    results = run_clients(server.url, big, seconds=3)
    statuses = {}
    for r in results:
        for code, count in r["status"].items():
            statuses[code] = statuses.get(code, 0) + count
    print(f"overflow: statuses {statuses}")
    assert set(statuses) == {200, 503}, statuses
    assert set().union(*(r["retry_after"] for r in results)) == {"1"}
    assert sum(r["mismatch"] for r in results) == 0
    metrics = httpx.get(server.url + "/metrics").text
    assert "neumip_queue_rejected_total" in metrics
    assert httpx.get(server.url + "/v2/health/ready").status_code == 200


def test_sigterm_finishes_requests_in_flight(serve):
    server = serve(ort_workers=1, chunk_rows=1024)
    q = random_queries(400_000, seed=8)
    answer = {}

    def request() -> None:
        with httpx.Client(timeout=60) as http:
            answer["resp"] = http.post(server.url + wire.EVALUATE_PATH.format(name="flat16"), content=wire.encode_request(q),
                                       headers={"content-type": wire.MSGPACK_MEDIA_TYPE})

    thread = threading.Thread(target=request)
    thread.start()
    deadline, admitted = time.monotonic() + 10, False
    while time.monotonic() < deadline and not admitted:
        admitted = "neumip_queue_rows 0.0" not in httpx.get(server.url + "/metrics").text
        time.sleep(0.005)
    assert admitted, "the request was not seen in flight"
    assert server.stop() == 0, server.log.read_text()
    thread.join(timeout=60)
    assert answer["resp"].status_code == 200
    assert wire.decode_response(answer["resp"].content).shape == (400_000, 3)
    assert "Application shutdown complete" in server.log.read_text()
