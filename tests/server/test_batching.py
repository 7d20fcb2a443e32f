"""The batcher: split large requests, merge small concurrent ones, keep bits, bound the queue."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from neumip.engines.local import LocalMaterials, load_material
from neumip.server.batching import Batcher, split
from neumip.server.engine import Engine
from neumip.server.metrics import Metrics
from neumip.server.settings import Settings
from neumip.core.contract import random_queries


def make_batcher(model_dir, **settings) -> tuple[Batcher, Metrics]:
    config = Settings(model_dir=model_dir, **settings)
    metrics = Metrics()
    materials = {name: load_material(model_dir / f"{name}.onnx", config.ort_threads) for name in ("rand16", "flat16")}
    return Batcher(materials, config, metrics, Engine.from_settings(config)), metrics


def sample(metrics: Metrics, name: str) -> float:
    return metrics.registry.get_sample_value(name) or 0.0


async def run_all(batcher: Batcher, requests: list[tuple[str, np.ndarray]], arriving: bool = False) -> list:
    """Evaluate `requests` concurrently; `arriving`: while another request is being received."""
    batcher.start()
    try:
        if not arriving:
            return await asyncio.gather(*(batcher.evaluate(n, q) for n, q in requests), return_exceptions=True)
        with batcher.receiving():
            return await asyncio.gather(*(batcher.evaluate(n, q) for n, q in requests), return_exceptions=True)
    finally:
        await batcher.close()


def test_split_cuts_pieces_of_at_most_chunk_rows_in_order():
    q = np.arange(7000, dtype=np.float32).reshape(1000, 7)
    out = np.zeros((1000, 3), np.float32)
    pieces = split(q, out, 256, job=None)
    assert [p.rows for p in pieces] == [256, 256, 256, 232]
    np.testing.assert_array_equal(np.concatenate([p.queries for p in pieces]), q)
    assert all(np.shares_memory(p.out, out) for p in pieces)
    assert [p.rows for p in split(q[:17], out[:17], 256, job=None)] == [17]


def test_large_request_is_split_into_chunks(model_dir, reference):
    batcher, metrics = make_batcher(model_dir, chunk_rows=1024, max_wait_ms=0)
    q = random_queries(5000, seed=1)
    [rgb] = asyncio.run(run_all(batcher, [("rand16", q)]))
    np.testing.assert_array_equal(rgb, reference.evaluate("rand16", q))
    one_thread = LocalMaterials(model_dir, threads=1, chunk=333)  # chunks cut unlike the server's
    np.testing.assert_array_equal(rgb, one_thread.evaluate("rand16", q))
    assert sample(metrics, "neumip_batch_rows_count") == 5  # 4 x 1024 + 904
    assert sample(metrics, "neumip_batch_rows_sum") == 5000


def test_small_concurrent_requests_are_merged_and_keep_their_bits(model_dir, reference):
    batcher, metrics = make_batcher(model_dir, ort_workers=1, chunk_rows=4096, max_wait_ms=200)
    sizes = [64, 100, 7, 256, 33, 512, 1, 48, 300, 16] * 2
    requests = [("rand16" if i % 3 else "flat16", random_queries(n, seed=i)) for i, n in enumerate(sizes)]
    answers = asyncio.run(run_all(batcher, requests, arriving=True))
    for (name, q), rgb in zip(requests, answers):
        np.testing.assert_array_equal(rgb, reference.evaluate(name, q))
    calls = sample(metrics, "neumip_batch_rows_count")
    assert calls < len(requests), f"{calls} ONNX Runtime calls for {len(requests)} requests: nothing merged"
    assert sample(metrics, "neumip_batch_rows_sum") == sum(sizes)


def test_query_groups_merge_only_with_their_own_width(model_dir, reference):
    """Concurrent requests of 1, 2 and 3 lights: one call per width (a call never mixes widths), each
    answer (N, 3 K) with the bits of in-process evaluation; large groups split by answers."""
    batcher, metrics = make_batcher(model_dir, ort_workers=1, chunk_rows=4096, max_wait_ms=200)
    requests = []
    for i, lights in enumerate([1, 2, 3, 2, 1, 3]):
        q = random_queries(50 + i, seed=i)
        extra = [random_queries(50 + i, seed=100 + 10 * i + j)[:, 3:5] for j in range(1, lights)]
        requests.append(("rand16", np.ascontiguousarray(np.hstack([q, *extra]))))
    answers = asyncio.run(run_all(batcher, requests, arriving=True))
    for (name, q), rgb in zip(requests, answers):
        assert rgb.shape == (q.shape[0], 3 * (q.shape[1] - 5) // 2)
        np.testing.assert_array_equal(rgb, reference.evaluate(name, q))
    assert sample(metrics, "neumip_batch_rows_count") == 3
    big = np.hstack([random_queries(5000, seed=1), random_queries(5000, seed=2)[:, 3:5]])  # 10 000 answers
    batcher, metrics = make_batcher(model_dir, chunk_rows=4096, max_wait_ms=0)
    [rgb] = asyncio.run(run_all(batcher, [("rand16", big)]))
    np.testing.assert_array_equal(rgb, reference.evaluate("rand16", big))
    assert sample(metrics, "neumip_batch_rows_count") == 3  # 2048 groups (4096 answers) a call


def test_lone_requests_do_not_wait_to_be_merged(model_dir, reference):
    """With nothing else being received, a small request and the tail of a split one run at once,
    not after max_wait_ms (here a minute: waiting would fail the 30 s bound)."""
    batcher, metrics = make_batcher(model_dir, chunk_rows=1024, max_wait_ms=60_000)

    async def lone() -> list:
        batcher.start()
        try:
            small = await asyncio.wait_for(batcher.evaluate("rand16", random_queries(10, seed=1)), 30)
            split_tail = await asyncio.wait_for(batcher.evaluate("rand16", random_queries(2500, seed=2)), 30)
            return [small, split_tail]
        finally:
            await batcher.close()

    small, split_tail = asyncio.run(lone())
    np.testing.assert_array_equal(small, reference.evaluate("rand16", random_queries(10, seed=1)))
    np.testing.assert_array_equal(split_tail, reference.evaluate("rand16", random_queries(2500, seed=2)))
    assert sample(metrics, "neumip_batch_rows_count") == 1 + 3


def test_model_failure_fails_the_batch_not_the_batcher(model_dir):
    batcher, _ = make_batcher(model_dir, max_wait_ms=0)
    bad = np.zeros((4, 7), np.float64)  # bypasses validation: ONNX Runtime rejects the dtype

    async def scenario():
        batcher.start()
        try:
            with pytest.raises(Exception, match="failed"):
                await batcher.evaluate("rand16", bad)
            return await batcher.evaluate("rand16", random_queries(10))
        finally:
            await batcher.close()

    assert asyncio.run(scenario()).shape == (10, 3)


def test_a_request_never_waits_for_itself_and_waiting_batches_take_its_rows(model_dir, reference):
    """`receiving().submit` queues the rows and ends the wait in one step: a lone request runs at once
    (here the answer is awaited inside its own block, with a minute of merge wait), and a batch that
    waited for a request being decoded takes its rows in the same call."""
    batcher, metrics = make_batcher(model_dir, ort_workers=1, chunk_rows=4096, max_wait_ms=60_000)
    q1, q2 = random_queries(10, seed=1), random_queries(20, seed=2)

    async def scenario():
        batcher.start()
        try:
            with batcher.receiving() as lone:
                alone = await asyncio.wait_for(lone.submit("rand16", q1), 30)
            with batcher.receiving() as first, batcher.receiving() as second:
                a = first.submit("rand16", q1)
                await asyncio.sleep(0.05)  # the batch holding a waits: second is still being decoded
                assert not a.done()
                b = second.submit("rand16", q2)
                return alone, await asyncio.wait_for(asyncio.gather(a, b), 30)
        finally:
            await batcher.close()

    alone, (a, b) = asyncio.run(scenario())
    np.testing.assert_array_equal(alone, reference.evaluate("rand16", q1))
    np.testing.assert_array_equal(a, alone)
    np.testing.assert_array_equal(b, reference.evaluate("rand16", q2))
    assert sample(metrics, "neumip_batch_rows_count") == 2  # the lone request, then a and b merged


@pytest.mark.parametrize("engine", ["onnxruntime", "kernel"])
def test_an_idle_worker_keeps_nothing_of_the_requests_it_ran(model_dir, engine):
    """Once a request is answered and the workers wait, nothing of the batcher holds its queries (in the server
    a view of its body) or its answers: the worker that ran the last batch kept both, 76 MB after a 2M-query
    request, until its next batch. With either engine's workers and chunks (the calls are ONNX Runtime's here)."""
    import gc
    import weakref

    if engine == "kernel":
        pytest.importorskip("drjit")
    batcher, _ = make_batcher(model_dir, engine=engine)

    async def run() -> list[bool]:
        batcher.start()
        try:
            queries = random_queries(20_000, seed=4)
            answers = await batcher.evaluate("rand16", queries)
            kept = weakref.ref(queries), weakref.ref(answers)
            del queries, answers
            await asyncio.sleep(0.2)  # the workers back to waiting
            gc.collect()
            return [ref() is None for ref in kept]  # while they wait: close() ends them and their frames
        finally:
            await batcher.close()

    assert asyncio.run(run()) == [True, True]
