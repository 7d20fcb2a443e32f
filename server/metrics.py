"""Prometheus metrics of the server: requests, rows, batch sizes, latencies, queue depth, model loads.

Each app owns its own `CollectorRegistry`, so several apps (tests) never share counters. The ASGI
middleware labels requests by route template (``/v1/materials/{name}/evaluate``), never by raw path,
so a stream of odd URLs cannot blow up the label set.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, Histogram
from prometheus_client import generate_latest

ROW_BUCKETS = tuple(float(2**k) for k in range(0, 22, 2))
"""Histogram buckets for rows per batch / request: 1, 4, 16, ... 2^20."""
LATENCY_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60)
"""Histogram buckets for latencies in seconds."""


@dataclass
class Metrics:
    """The server's Prometheus collectors, registered in a registry of their own."""

    registry: CollectorRegistry = field(default_factory=CollectorRegistry)
    """Registry the collectors below live in (rendered by ``GET /metrics``)."""

    def __post_init__(self) -> None:
        r = self.registry
        self.requests = Counter(
            "neumip_http_requests", "HTTP requests answered", ["route", "method", "status"], registry=r
        )
        self.latency = Histogram(
            "neumip_http_request_seconds", "Time to answer an HTTP request", ["route"],
            buckets=LATENCY_BUCKETS, registry=r,
        )
        self.rows = Counter("neumip_query_rows", "Query rows evaluated", ["material"], registry=r)
        self.request_rows = Histogram(
            "neumip_request_rows", "Query rows per evaluation request", buckets=ROW_BUCKETS, registry=r
        )
        self.batch_rows = Histogram(
            "neumip_batch_rows", "Rows per engine call", buckets=ROW_BUCKETS, registry=r
        )
        self.batch_requests = Histogram(
            "neumip_batch_requests", "Request pieces merged into one engine call",
            buckets=(1, 2, 4, 8, 16, 32, 64, 128), registry=r,
        )
        self.predict_seconds = Histogram(
            "neumip_predict_seconds", "Time of one engine call", buckets=LATENCY_BUCKETS, registry=r
        )
        self.queue_rows = Gauge("neumip_queue_rows", "Rows admitted and not yet answered", registry=r)
        self.queue_requests = Gauge(
            "neumip_queue_requests", "Evaluation requests admitted and not yet answered", registry=r
        )
        self.body_bytes = Gauge(
            "neumip_body_bytes", "Bytes of request-body memory reserved by requests in flight", registry=r
        )
        self.answer_bytes = Gauge(
            "neumip_answer_bytes", "Bytes of answer memory reserved by requests in flight (evaluated or being sent)",
            registry=r,
        )
        self.rejected = Counter(
            "neumip_queue_rejected", "Requests refused with 503 because the row queue or body budget was full",
            registry=r,
        )
        self.nonfinite = Counter(
            "neumip_nonfinite_answers", "Requests refused with 500 because the model answered NaN or Inf",
            ["material"], registry=r,
        )

        self.model_loads = Counter(
            "neumip_model_loads", "Model loads by outcome (loaded, failed)", ["material", "outcome"], registry=r
        )
        self.model_unloads = Counter(
            "neumip_model_unloads", "Models unloaded, by reason (memory, request, deleted)", ["material", "reason"],
            registry=r,
        )
        self.resident_bytes = Gauge(
            "neumip_model_resident_bytes", "Bytes of each loaded model (its file's size; 0 once unloaded)",
            ["material"], registry=r,
        )
        self.model_load_seconds = Histogram(
            "neumip_model_load_seconds", "Time to read, load and warm up one model", buckets=LATENCY_BUCKETS,
            registry=r,
        )

    def render(self) -> tuple[bytes, str]:
        """The exposition text and its media type."""
        return generate_latest(self.registry), CONTENT_TYPE_LATEST


class MetricsMiddleware:
    """Pure ASGI middleware counting every HTTP request and timing it by route template."""

    def __init__(self, app, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = {"code": 500}

        async def send_and_record(message) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_and_record)
        finally:
            route = scope.get("route")
            template = getattr(route, "path", None) or "unmatched"
            self.metrics.requests.labels(template, scope["method"], str(status["code"])).inc()
            self.metrics.latency.labels(template).observe(time.perf_counter() - start)


class StageTimer:
    """Durations of a request's stages, sent back in a ``Server-Timing`` header (milliseconds)."""

    def __init__(self) -> None:
        self._last = time.perf_counter()
        self._stages: list[tuple[str, float]] = []

    def mark(self, stage: str) -> None:
        """Close the stage that ends now."""
        now = time.perf_counter()
        self._stages.append((stage, now - self._last))
        self._last = now

    def header(self) -> dict[str, str]:
        return {"Server-Timing": ", ".join(f"{name};dur={sec * 1e3:.2f}" for name, sec in self._stages)}
