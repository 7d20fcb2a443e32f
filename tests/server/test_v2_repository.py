"""Triton's model configuration, statistics and repository index, through tritonclient.http against a
real `neumip serve` process (one corrupt model file beside the good ones)."""

from __future__ import annotations

import shutil
from concurrent.futures import ThreadPoolExecutor

import pytest

from neumip.core.contract import random_queries

pytest.importorskip("tritonclient.grpc", reason="needs tritonclient[grpc] (Triton's ModelConfig schema)")
import tritonclient.http as triton  # noqa: E402
from google.protobuf import json_format  # noqa: E402
from tritonclient.grpc import model_config_pb2  # noqa: E402
from tritonclient.utils import InferenceServerException  # noqa: E402

SETTINGS = {"chunk_rows": 1024, "max_wait_ms": 3, "ort_workers": 2, "ort_threads": 1, "max_rows": 50_000,
            "max_queue_rows": 200_000}


@pytest.fixture(scope="module")
def server(model_dir, tmp_path_factory, serve_module):
    folder = tmp_path_factory.mktemp("repo-models")
    for path in model_dir.glob("*.onnx"):
        shutil.copy(path, folder)
    (folder / "broken.onnx").write_bytes(b"not an onnx graph")
    return serve_module(folder, **SETTINGS)


@pytest.fixture(scope="module")
def tc(server):
    return triton.InferenceServerClient(server.host_port)


def test_model_config_is_a_valid_triton_config_with_the_server_settings(tc):
    raw = tc.get_model_config("rand16")
    config = json_format.ParseDict(raw, model_config_pb2.ModelConfig())  # unknown field or type: error
    assert config.name == "rand16" and config.platform == "onnxruntime_onnx"
    assert config.max_batch_size == SETTINGS["max_rows"]
    # -1: any width, (N, 7) queries or (N, 5 + 2 K) query groups -> (N, 3 K)
    assert [(t.name, list(t.dims), t.data_type) for t in config.input] == [("queries", [-1], model_config_pb2.TYPE_FP32)]
    assert [(t.name, list(t.dims), t.data_type) for t in config.output] == [("rgb", [-1], model_config_pb2.TYPE_FP32)]
    assert list(config.dynamic_batching.preferred_batch_size) == [SETTINGS["chunk_rows"]]
    assert config.dynamic_batching.max_queue_delay_microseconds == 3000
    assert [(g.count, g.kind) for g in config.instance_group] == [(2, model_config_pb2.ModelInstanceGroup.KIND_CPU)]
    assert config.parameters["intra_op_thread_count"].string_value == "1"
    assert tc.get_model_config("rand16", model_version="1") == raw


def test_unknown_model_or_version_is_an_error(tc):
    for call, words in ((lambda: tc.get_model_config("nope"), "unknown material 'nope'"),
                        (lambda: tc.get_model_config("rand16", model_version="2"), "unknown model version '2'"),
                        (lambda: tc.get_inference_statistics("nope"), "unknown material 'nope'")):
        with pytest.raises(InferenceServerException) as err:
            call()
        assert err.value.status() == "404" and words in str(err.value)


def test_repository_index_lists_ready_and_failed_models(tc):
    index = tc.get_model_repository_index()
    states = {m["name"]: m["state"] for m in index}
    assert states == {"broken": "UNAVAILABLE", "flat16": "READY", "lambert": "READY", "rand16": "READY"}
    assert "broken.onnx" in next(m["reason"] for m in index if m["name"] == "broken")
    assert [m["name"] for m in tc.get_model_repository_index(query_params=None, headers=None)] == sorted(states)


def test_statistics_count_requests_rows_and_batched_calls(tc, server):
    before = tc.get_inference_statistics("flat16")["model_stats"][0]
    sizes = [1, 7, 300, 2000, 5, 64] * 4  # 2000 rows: split into two calls of <= 1024 rows

    def infer(i: int) -> None:
        client = triton.InferenceServerClient(server.host_port)
        q = random_queries(sizes[i], seed=i)
        tensor = triton.InferInput("queries", list(q.shape), "FP32")
        tensor.set_data_from_numpy(q, binary_data=True)
        assert client.infer("flat16", [tensor]).as_numpy("rgb").shape == (sizes[i], 3)

    with ThreadPoolExecutor(6) as pool:
        list(pool.map(infer, range(len(sizes))))
    after = tc.get_inference_statistics("flat16")["model_stats"][0]
    assert after["name"] == "flat16" and after["version"] == "1"
    assert after["inference_count"] - before["inference_count"] == sum(sizes)
    stats, old = after["inference_stats"], before["inference_stats"]
    assert stats["success"]["count"] - old["success"]["count"] == len(sizes)
    assert stats["success"]["ns"] > old["success"]["ns"] and stats["fail"] == old["fail"]
    calls = after["execution_count"] - before["execution_count"]
    assert 8 <= calls  # at least the two halves of each 2000-row request
    # every call is in the per-batch-size table, whose rows add up to the rows evaluated
    batches = after["batch_stats"]
    assert sum(b["compute_infer"]["count"] for b in batches) == after["execution_count"]
    assert sum(b["batch_size"] * b["compute_infer"]["count"] for b in batches) == after["inference_count"]
    assert max(b["batch_size"] for b in batches) <= SETTINGS["chunk_rows"]
    assert stats["compute_infer"]["count"] == after["execution_count"] and stats["compute_infer"]["ns"] > 0
    assert after["last_inference"] > 0


def test_statistics_of_every_model(tc):
    names = [m["name"] for m in tc.get_inference_statistics()["model_stats"]]
    assert names == ["flat16", "lambert", "rand16"]
    untouched = tc.get_inference_statistics("lambert")["model_stats"][0]
    assert untouched["inference_count"] == 0 and untouched["batch_stats"] == []


def test_repository_index_refuses_a_bad_body(server):
    import httpx

    resp = httpx.post(server.url + "/v2/repository/index", content=b'{"ready": "yes"}')
    assert resp.status_code == 400 and "ready" in resp.json()["error"]
    ready = httpx.post(server.url + "/v2/repository/index", json={"ready": True}).json()
    assert [m["name"] for m in ready] == ["flat16", "lambert", "rand16"]


def test_model_control_is_off_by_default(tc, server):
    """Issue 27, F5: any client could unload a model (every request then got 400 until a reload). As in
    Triton's default mode, load and unload answer 403 unless NEUMIP_MODEL_CONTROL=explicit."""
    for call in (tc.unload_model, tc.load_model):
        with pytest.raises(InferenceServerException, match="model control is off") as refused:
            call("rand16")
        assert refused.value.status() == "403"
    assert tc.is_model_ready("rand16")
    tensor = triton.InferInput("queries", [8, 7], "FP32")
    tensor.set_data_from_numpy(random_queries(8, seed=2), binary_data=True)
    assert tc.infer("rand16", [tensor]).as_numpy("rgb").shape == (8, 3)
