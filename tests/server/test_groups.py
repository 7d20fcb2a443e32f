"""Query groups (N, 5 + 2 K) through a real `neumip serve` process: msgpack /v1 and OIP /v2 answer
(N, 3 K) with the bits of in-process evaluation and of the single queries; bad widths are 400s; a batch
never mixes widths; a model file of contract version 1 (before groups) is refused, naming its upgrade."""

from __future__ import annotations

import shutil
import threading
from pathlib import Path

import httpx
import msgpack
import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core import wire
from neumip.client.http import ClientConfig, MaterialClient
from neumip.engines.local import LocalMaterials

OLD_MODEL = Path(__file__).parents[1] / "data" / "pre_issue12_offset.onnx"


@pytest.fixture(scope="module")
def folder(model_dir, tmp_path_factory):
    """The test materials and `old`, a model file of contract version 1 (exported before query groups)."""
    out = tmp_path_factory.mktemp("groups")
    for path in model_dir.glob("*.onnx"):
        shutil.copy(path, out)
    shutil.copy(OLD_MODEL, out / "old.onnx")
    return out


@pytest.fixture(scope="module")
def server(serve_module, folder):
    # a long merge wait: concurrent requests of several widths sit in the queue together
    return serve_module(folder, max_rows=5000, max_wait_ms=50)


@pytest.fixture(scope="module")
def local(folder):
    return LocalMaterials(folder)


@pytest.mark.parametrize("protocol", ["msgpack", "v2"])
@pytest.mark.parametrize("material", ["rand16", "flat16"])
def test_groups_answer_with_the_bits_of_in_process_and_of_single_queries(server, local, protocol, material, groups_of):
    groups = groups_of(7000, 2, seed=1)  # (N, 9); 7000 > max_rows of the client: split by groups
    with MaterialClient(server.url, ClientConfig(max_rows=3000), protocol=protocol) as client:
        rgb = client.evaluate(material, groups)
        assert rgb.shape == (7000, 6)
        np.testing.assert_array_equal(rgb, local.evaluate(material, groups))
        np.testing.assert_array_equal(rgb.reshape(-1, 3), local.evaluate(material, C.ungroup(groups)))
        assert client.evaluate(material, np.zeros((0, 9), np.float32)).shape == (0, 6)


def test_every_material_takes_groups_and_a_version_1_file_is_refused_with_its_upgrade(server, local, groups_of):
    """The v2 model metadata and the v2 config state variable widths for every material, as Triton
    states the exported repository; the version-1 file is listed as failed, with the command that
    upgrades it, and evaluating it is a 400 that says so."""
    groups = groups_of(300, 2, seed=4)
    with httpx.Client(base_url=server.url, timeout=30) as http:
        listing = http.get(wire.MATERIALS_PATH).json()
        [failed] = [f for f in listing["failed"] if f["name"] == "old"]
        assert "query contract version 1" in str(failed) and "neumip export old.onnx -o NEW.onnx" in str(failed)
        resp = http.post(wire.EVALUATE_PATH.format(name="old"), content=wire.encode_request(groups),
                         headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
        assert resp.status_code == 400 and "neumip export old.onnx" in resp.json()["error"], resp.text
        for name in ("rand16", "flat16"):
            metadata = http.get(wire.MODEL_PATH.format(name=name)).json()
            assert [metadata["inputs"][0]["shape"], metadata["outputs"][0]["shape"]] == [[-1, -1], [-1, -1]]
            config = http.get(f"/v2/models/{name}/config").json()
            assert [config["input"][0]["dims"], config["output"][0]["dims"]] == [[-1], [-1]]
            resp = http.post(wire.EVALUATE_PATH.format(name=name), content=wire.encode_request(groups),
                             headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
            assert resp.status_code == 200, resp.text
            np.testing.assert_array_equal(wire.decode_response(resp.content).reshape(-1, 3),
                                          local.evaluate(name, C.ungroup(groups)))


def test_bad_widths_are_400_and_the_server_keeps_serving(server, local, groups_of):
    path = wire.EVALUATE_PATH.format(name="rand16")
    msgpack_type = {"content-type": wire.MSGPACK_MEDIA_TYPE}
    with httpx.Client(base_url=server.url, timeout=30) as http:
        for body, words in (
            (msgpack.packb({"n": 3, "queries": np.zeros((3, 8), np.float32).tobytes()}), "8 float32 per row"),
            (msgpack.packb({"n": 3, "queries": b"\0" * (3 * 36 + 4)}), "not n=3 rows"),
            # "lights" states the width: the bytes of 3 rows of 9 are neither 3 rows of 1 light nor of 3
            (msgpack.packb({"n": 3, "lights": 1, "queries": np.zeros((3, 9), np.float32).tobytes()}),
             "holds 108 bytes, but n=3 rows of 1 light(s) (7 float32 each) need 84"),
            (wire.encode_request(np.zeros((3, 9), np.float32)).replace(b"lights\x02", b"lights\x03"),
             "n=3 rows of 3 light(s) (11 float32 each) need 132"),
            (msgpack.packb({"n": 3, "lights": "2", "queries": np.zeros((3, 9), np.float32).tobytes()}),
             "'lights' must be an integer from 1 to 64"),
        ):
            resp = http.post(path, content=body, headers=msgpack_type)
            assert resp.status_code == 400 and words in resp.json()["error"], resp.text
        resp = http.post(path, json={"queries": np.zeros((2, 8)).tolist()})
        assert resp.status_code == 400 and "5 + 2 K" in resp.json()["error"], resp.text
        head = {"inputs": [{"name": "queries", "datatype": "FP32", "shape": [2, 8], "data": [0.0] * 16}]}
        resp = http.post("/v2/models/rand16/infer", json=head)
        assert resp.status_code == 400 and "5 + 2 K" in resp.json()["error"], resp.text
        groups = groups_of(5, 3, seed=2)  # (5, 11): JSON rows of 11 numbers
        resp = http.post(path, json={"queries": groups.tolist()})
        assert resp.status_code == 200, resp.text
        np.testing.assert_array_equal(np.asarray(resp.json()["rgb"], np.float32), local.evaluate("rand16", groups))


def test_concurrent_clients_of_mixed_widths_each_get_their_answers(server, local, groups_of):
    """Threads send 1, 2 and 3 lights at once to two materials; the server merges what it can (only
    rows of one width share a call) and every answer keeps its bits."""
    jobs = [(material, lights, seed) for material in ("rand16", "flat16") for lights in (1, 2, 3) for seed in range(2)]
    answers, errors = {}, []

    def run(job):
        material, lights, seed = job
        try:
            with MaterialClient(server.url) as client:
                for round_ in range(4):
                    groups = groups_of(200 + 37 * seed, lights, seed=10 * seed + round_)
                    answers[job + (round_,)] = (groups, client.evaluate(material, groups))
        except Exception as exc:  # reported below, with the job
            errors.append((job, exc))

    threads = [threading.Thread(target=run, args=(job,)) for job in jobs]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    assert not errors, errors
    assert len(answers) == 4 * len(jobs)
    for (material, lights, *_), (groups, rgb) in answers.items():
        assert rgb.shape == (groups.shape[0], 3 * lights)
        np.testing.assert_array_equal(rgb, local.evaluate(material, groups))


def test_the_row_limit_counts_each_light_of_a_group(server, local, groups_of):
    """max_rows (5000 here) bounds the queries a request asks for: 2600 groups of two lights are 5200."""
    groups = groups_of(2600, 2, seed=9)
    with MaterialClient(server.url, ClientConfig(max_rows=10_000)) as client:  # one request: refused
        with pytest.raises(Exception, match="5200 queries"):
            client.evaluate("rand16", groups)
    with MaterialClient(server.url, ClientConfig(max_rows=5000)) as client:  # split: 2500 groups a request
        np.testing.assert_array_equal(client.evaluate("rand16", groups).reshape(-1, 3),
                                      local.evaluate("rand16", C.ungroup(groups)))
