"""Per-material inference statistics in Triton's shape (``GET /v2/models/{name}/stats``).

The batcher records two things (`neumip.server.batching`): each request once it is answered or has
failed (`ModelStats.track`), and each ONNX Runtime call (`ModelStats.executed`). Counts follow Triton:
``inference_count`` counts rows (Triton counts a request's batch size), ``execution_count`` counts model
calls, so ``inference_count / execution_count`` is the mean rows per call that dynamic batching made.
Durations are nanoseconds: ``success``/``fail`` from admission to answer, ``queue`` the wait of each
request piece before its call started, ``compute_infer`` the whole call (merge, ONNX Runtime, copy back;
neumip does not time input and output apart, so ``compute_input``/``compute_output`` stay zero).
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field


@dataclass
class Duration:
    """Count and total nanoseconds (Triton's ``StatisticDuration``)."""

    count: int = 0
    ns: int = 0

    def add(self, ns: int, count: int = 1) -> None:
        self.count += count
        self.ns += ns

    def json(self) -> dict:
        return {"count": self.count, "ns": self.ns}


@dataclass
class _Model:
    inference_count: int = 0
    execution_count: int = 0
    last_inference_ms: int = 0
    success: Duration = field(default_factory=Duration)
    fail: Duration = field(default_factory=Duration)
    queue: Duration = field(default_factory=Duration)
    compute_infer: Duration = field(default_factory=Duration)
    batches: dict[int, Duration] = field(default_factory=dict)  # rows per call -> compute_infer


class ModelStats:
    """Thread-safe statistics of every material (written by worker threads and the event loop)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._models: dict[str, _Model] = defaultdict(_Model)

    def track(self, name: str, future: asyncio.Future, rows: int) -> None:
        """Count request `future` of `rows` rows for material `name` when it is done (answered or failed)."""
        start = time.perf_counter_ns()

        def done(f: asyncio.Future) -> None:
            ns = time.perf_counter_ns() - start
            ok = not f.cancelled() and f.exception() is None
            with self._lock:
                model = self._models[name]
                (model.success if ok else model.fail).add(ns)
                if ok:
                    model.inference_count += rows
                    model.last_inference_ms = time.time_ns() // 1_000_000

        future.add_done_callback(done)

    def executed(self, name: str, rows: int, seconds: float, arrived: list[float]) -> None:
        """One model call of `rows` rows for `name` that took `seconds` and has just ended; `arrived`:
        when each merged piece was queued (`time.monotonic()`)."""
        ns = round(seconds * 1e9)
        began = time.monotonic() - seconds
        waits = [max(began - t, 0.0) for t in arrived]
        with self._lock:
            model = self._models[name]
            model.execution_count += 1
            model.compute_infer.add(ns)
            model.queue.add(round(sum(waits) * 1e9), len(waits))
            model.batches.setdefault(rows, Duration()).add(ns)

    def json(self, name: str, version: str) -> dict:
        """Triton's ``ModelStatistics`` of material `name` (zeros if it has seen no request)."""
        zero = Duration().json()
        with self._lock:
            model = self._models.get(name) or _Model()
            return {
                "name": name,
                "version": version,
                "last_inference": model.last_inference_ms,
                "inference_count": model.inference_count,
                "execution_count": model.execution_count,
                "inference_stats": {
                    "success": model.success.json(),
                    "fail": model.fail.json(),
                    "queue": model.queue.json(),
                    "compute_input": zero,
                    "compute_infer": model.compute_infer.json(),
                    "compute_output": zero,
                    "cache_hit": zero,
                    "cache_miss": zero,
                },
                "batch_stats": [
                    {"batch_size": rows, "compute_input": zero, "compute_infer": d.json(), "compute_output": zero}
                    for rows, d in sorted(model.batches.items())
                ],
            }
