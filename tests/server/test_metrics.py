"""/metrics exposes requests, rows, batch sizes, latencies and queue depth; OpenAPI docs are served."""

from __future__ import annotations

from neumip.core import wire
from neumip.core.contract import random_queries


def value(text: str, prefix: str) -> float:
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if line.startswith(prefix))


def test_metrics_count_requests_rows_and_batches(client):
    before = client.get("/metrics").text
    q = random_queries(300, seed=3)
    client.post(wire.EVALUATE_PATH.format(name="flat16"), content=wire.encode_request(q), headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
    client.post(wire.EVALUATE_PATH.format(name="flat16"), content=b"junk", headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
    text = client.get("/metrics").text
    route = 'route="/v1/materials/{name}/evaluate"'
    assert value(text, f'neumip_http_requests_total{{method="POST",{route},status="200"}}') >= 1
    assert value(text, f'neumip_http_requests_total{{method="POST",{route},status="400"}}') >= 1
    assert value(text, 'neumip_query_rows_total{material="flat16"}') - value(before, 'neumip_query_rows_total{material="flat16"}') == 300
    for name in ("neumip_batch_rows_bucket", "neumip_http_request_seconds_bucket", "neumip_predict_seconds_bucket",
                 "neumip_request_rows_bucket", "neumip_queue_rows", "neumip_queue_requests"):
        assert name in text, name
    assert value(text, "neumip_queue_rows ") == 0


def test_odd_paths_do_not_grow_the_label_set(client):
    for i in range(5):
        client.get(f"/some/odd/path/{i}")
    text = client.get("/metrics").text
    assert "/some/odd" not in text and 'route="unmatched"' in text


def test_openapi_and_docs(client):
    spec = client.get("/openapi.json").json()
    evaluate = spec["paths"][wire.EVALUATE_PATH]["post"]
    assert set(evaluate["requestBody"]["content"]) == {"application/json", wire.MSGPACK_MEDIA_TYPE}
    assert "/v2/models/{name}/infer" in spec["paths"]
    assert client.get("/docs").status_code == 200


def test_server_timing_header_names_the_stages_in_milliseconds(client):
    """The stages add up to no more than the client's round trip, and the evaluate stage covers the
    ONNX Runtime time the metrics recorded for the request (both in ms: a unit slip fails one)."""
    import time

    q = random_queries(5000, seed=1)  # fewer than chunk_rows: one ONNX Runtime call
    before = client.get("/metrics").text
    start = time.perf_counter()
    resp = client.post(wire.EVALUATE_PATH.format(name="rand16"), content=wire.encode_request(q), headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
    wall_ms = (time.perf_counter() - start) * 1e3
    after = client.get("/metrics").text
    stages = {part.split(";dur=")[0]: float(part.split(";dur=")[1]) for part in resp.headers["server-timing"].split(", ")}
    assert list(stages) == ["read", "decode", "evaluate", "encode"]
    predict_ms = (value(after, "neumip_predict_seconds_sum") - value(before, "neumip_predict_seconds_sum")) * 1e3
    assert predict_ms > 0
    assert stages["evaluate"] + 0.01 >= predict_ms, (stages, predict_ms)  # the header rounds to 0.01 ms
    assert sum(stages.values()) <= wall_ms, (stages, wall_ms)
