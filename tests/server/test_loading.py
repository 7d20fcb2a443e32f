"""Loading on demand, against real `neumip serve` processes: lazy start-up, a render that loads only
its scene's materials, the LRU memory budget under concurrent requests, following the folder (new,
changed, deleted files; explicit load/unload through tritonclient), and a file replaced in place
that is never served half-written."""

from __future__ import annotations

import re
import shutil
import threading
import time
import urllib.request

import httpx
import numpy as np
import pytest

from neumip.core import wire
from neumip.core.contract import random_queries
from neumip.client.http import MaterialClient
from neumip.engines.local import LocalMaterials
from neumip.core.config import MaterialConfig
from neumip.training.export.graph import build_onnx, random_weights, save_onnx


def metric(server, name: str, **labels) -> float:
    """Sum of the samples of metric `name` whose labels include `labels`."""
    with urllib.request.urlopen(server.url + "/metrics", timeout=10) as reply:
        text = reply.read().decode()
    total = 0.0
    for line in text.splitlines():
        match = re.match(rf"^{name}(?:{{(.*)}})? (\S+)$", line)
        if match and all(f'{k}="{v}"' in (match.group(1) or "") for k, v in labels.items()):
            total += float(match.group(2))
    return total


def distinct_models(folder, count: int, offset: bool = False):
    """`count` small materials m0..m{count-1} with different answers."""
    folder.mkdir(exist_ok=True)
    config = MaterialConfig(resolution=16, offset=offset)
    for i in range(count):
        save_onnx(build_onnx(config, random_weights(config, seed=100 + i)), folder / f"m{i}.onnx")
    return folder


def evaluate(server, name: str, q: np.ndarray) -> httpx.Response:
    return httpx.post(server.url + wire.EVALUATE_PATH.format(name=name), content=wire.encode_request(q),
                      headers={"content-type": wire.MSGPACK_MEDIA_TYPE}, timeout=60)


def test_a_folder_of_200_models_starts_without_loading_any(serve, model_dir, tmp_path):
    folder = tmp_path / "many"
    folder.mkdir()
    for i in range(200):
        shutil.copy(model_dir / "rand16.onnx", folder / f"mat{i:03d}.onnx")
    server = serve(folder, load="lazy", poll_s=0)
    assert metric(server, "neumip_model_loads_total") == 0
    listing = httpx.get(server.url + wire.MATERIALS_PATH).json()["materials"]
    assert len(listing) == 200 and not any(m["loaded"] for m in listing)
    q = random_queries(100, seed=3)
    resp = evaluate(server, "mat123", q)
    assert resp.status_code == 200
    np.testing.assert_array_equal(wire.decode_response(resp.content), LocalMaterials(model_dir).evaluate("rand16", q))
    assert metric(server, "neumip_model_loads_total") == 1
    assert metric(server, "neumip_model_loads_total", material="mat123", outcome="loaded") == 1
    assert metric(server, "neumip_model_resident_bytes", material="mat123") == (folder / "mat123.onnx").stat().st_size
    assert metric(server, "neumip_model_load_seconds_count") == 1
    assert evaluate(server, "mat200", q).status_code == 404
    index = httpx.post(server.url + "/v2/repository/index", json={}).json()
    assert len(index) == 200 and [m["name"] for m in index if m["state"] == "READY"] == ["mat123"]
    assert {m.get("reason") for m in index if m["state"] != "READY"} == {"not loaded: loads on its first request"}
    assert [m["name"] for m in httpx.post(server.url + "/v2/repository/index", json={"ready": True}).json()] == ["mat123"]


def test_a_render_through_the_server_loads_exactly_its_materials(serve, model_dir):
    from neumip.client.mitsuba.bsdf import mi
    from neumip.client.mitsuba.render import RenderConfig, render_scene

    from ..client.mitsuba.scenes import facing_plane

    server = serve(load="lazy", poll_s=0)
    render_scene(mi.load_dict(facing_plane(uv_scale=2.0)), MaterialClient(server.url), RenderConfig(spp=2))
    loaded = {name for name in ("rand16", "flat16", "lambert")
              if metric(server, "neumip_model_loads_total", material=name, outcome="loaded")}
    assert loaded == {"lambert"}
    # in-process, the same lazy mode
    local = LocalMaterials(model_dir, lazy=True)
    render_scene(mi.load_dict(facing_plane(uv_scale=2.0)), local, RenderConfig(spp=2))
    assert local.loaded() == ["lambert"] and "rand16" in local.materials()


def test_lru_keeps_the_budget_and_answers_everything_under_concurrent_requests(serve, tmp_path):
    folder = distinct_models(tmp_path / "six", 6)
    size = (folder / "m0.onnx").stat().st_size
    budget_mb = 2.5 * size / 2**20  # room for two models
    server = serve(folder, load="lazy", poll_s=0, memory_budget_mb=budget_mb, ort_workers=2)
    reference = LocalMaterials(folder, threads=1)
    q = random_queries(3000, seed=5)
    expected = {f"m{i}": reference.evaluate(f"m{i}", q) for i in range(6)}
    errors, peaks = [], []
    stop = threading.Event()

    def client(seed: int) -> None:
        rng = np.random.default_rng(seed)
        for _ in range(12):
            name = f"m{rng.integers(6)}"
            resp = evaluate(server, name, q)
            if resp.status_code != 200 or not np.array_equal(wire.decode_response(resp.content), expected[name]):
                errors.append((name, resp.status_code, resp.text[:200]))

    def watch() -> None:
        while not stop.is_set():
            peaks.append(metric(server, "neumip_model_resident_bytes"))
            time.sleep(0.02)

    watcher = threading.Thread(target=watch)
    watcher.start()
    clients = [threading.Thread(target=client, args=(seed,)) for seed in range(6)]
    for t in clients:
        t.start()
    for t in clients:
        t.join()
    stop.set()
    watcher.join()
    assert not errors
    assert metric(server, "neumip_model_unloads_total", reason="memory") > 0
    assert metric(server, "neumip_model_resident_bytes") <= budget_mb * 2**20  # idle: within the budget
    # busy: over it only by models with requests in flight (at most one per client)
    assert max(peaks) <= budget_mb * 2**20 + 6 * size


def test_following_the_folder_and_explicit_load_unload(serve, tmp_path):
    import tritonclient.http as triton

    folder = distinct_models(tmp_path / "follow", 2)
    server = serve(folder, poll_s=0.1, model_control="explicit", model_control_token="s3cret")
    q = random_queries(50, seed=7)
    assert evaluate(server, "m0", q).status_code == 200
    # a file copied in later is served; a deleted one answers 404, for that material only
    distinct_models(tmp_path / "extra", 3)
    shutil.copy(tmp_path / "extra" / "m2.onnx", folder / "new.onnx")
    assert evaluate(server, "new", q).status_code == 200
    (folder / "m1.onnx").unlink()
    deadline = time.monotonic() + 10
    while evaluate(server, "m1", q).status_code != 404 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert evaluate(server, "m1", q).status_code == 404
    listing = httpx.get(server.url + wire.MATERIALS_PATH)
    assert listing.status_code == 200 and [m["name"] for m in listing.json()["materials"]] == ["m0", "new"]
    assert evaluate(server, "m0", q).status_code == 200
    # explicit model control, as tritonclient calls it: with the token only
    client = triton.InferenceServerClient(server.host_port)
    for wrong in ({}, {"Authorization": "Bearer guess"}):
        with pytest.raises(Exception, match="Authorization: Bearer"):
            client.unload_model("m0", headers=wrong)
    assert evaluate(server, "m0", q).status_code == 200
    token = {"Authorization": "Bearer s3cret"}
    client.unload_model("m0", headers=token)
    assert evaluate(server, "m0", q).status_code == 400
    assert not client.is_model_ready("m0")
    client.load_model("m0", headers=token)
    assert client.is_model_ready("m0") and evaluate(server, "m0", q).status_code == 200
    with pytest.raises(Exception, match="unknown material"):
        client.load_model("nothing", headers=token)
    assert metric(server, "neumip_model_unloads_total", material="m1", reason="deleted") == 1


def test_a_file_replaced_in_place_is_never_served_half_written(serve, tmp_path):
    import tritonclient.http as triton

    folder = distinct_models(tmp_path / "swap", 1, offset=True)
    new = distinct_models(tmp_path / "new", 2, offset=True) / "m1.onnx"
    server = serve(folder, poll_s=0.05, model_control="explicit")
    q = random_queries(2000, seed=11)
    old_answer = LocalMaterials(folder).evaluate("m0", q)
    new_answer = LocalMaterials(new.parent).evaluate("m1", q)
    outcomes, stop = [], threading.Event()

    def hammer() -> None:
        while not stop.is_set():
            resp = evaluate(server, "m0", q)
            rgb = wire.decode_response(resp.content) if resp.status_code == 200 else None
            outcomes.append("old" if rgb is not None and np.array_equal(rgb, old_answer) else
                            "new" if rgb is not None and np.array_equal(rgb, new_answer) else
                            f"bad {resp.status_code} {resp.text[:100]}")

    thread = threading.Thread(target=hammer)
    thread.start()
    data = new.read_bytes()
    with open(folder / "m0.onnx", "r+b") as f:  # in place, in two halves, a second apart
        f.truncate(0)
        f.write(data[: len(data) // 2])
        f.flush()
        time.sleep(0.5)  # ten polls see the half-written file
        with pytest.raises(Exception, match="cannot load"):
            triton.InferenceServerClient(server.host_port).load_model("m0")
        time.sleep(0.5)
        f.write(data[len(data) // 2:])
    deadline = time.monotonic() + 10
    while (not outcomes or outcomes[-1] != "new") and time.monotonic() < deadline:
        time.sleep(0.05)
    stop.set()
    thread.join()
    assert set(outcomes) == {"old", "new"}, sorted(set(outcomes))
    first_new = outcomes.index("new")
    assert all(o == "new" for o in outcomes[first_new:])  # swapped once, for good
    assert metric(server, "neumip_model_loads_total", material="m0", outcome="failed") >= 1


def test_the_listing_shows_what_a_trim_cut(model_dir, tmp_path):
    from fastapi.testclient import TestClient

    from neumip.server.app import create_app
    from neumip.server.settings import Settings
    from neumip.training.export.trim import trim_file

    folder = tmp_path / "trimmed"
    folder.mkdir()
    trim_file(model_dir / "rand16.onnx", folder / "rand16.onnx", 2)
    shutil.copy(model_dir / "flat16.onnx", folder / "flat16.onnx")
    with TestClient(create_app(Settings(model_dir=folder, warmup_rows=16, poll_s=0))) as client:
        listing = {m["name"]: m for m in client.get(wire.MATERIALS_PATH).json()["materials"]}
    assert listing["rand16"]["trim"]["finest_level"] == 2 and listing["rand16"]["trim"]["levels_cut"] == [16, 8]
    assert listing["flat16"]["trim"] is None
    assert listing["rand16"]["bytes"] == (folder / "rand16.onnx").stat().st_size


def test_a_deleted_file_without_polling(tmp_path):
    """The listing answers 200 at once (it used to stat every file: 500), and an explicit load
    drops the material: 404 for it alone."""
    from fastapi.testclient import TestClient

    from neumip.server.app import create_app
    from neumip.server.settings import Settings

    folder = distinct_models(tmp_path / "del", 2)
    settings = Settings(model_dir=folder, warmup_rows=16, poll_s=0, model_control="explicit")
    with TestClient(create_app(settings)) as client:
        (folder / "m1.onnx").unlink()
        assert client.get(wire.MATERIALS_PATH).status_code == 200
        assert client.post("/v2/repository/models/m1/load").status_code == 404
        assert [m["name"] for m in client.get(wire.MATERIALS_PATH).json()["materials"]] == ["m0"]
        q = wire.encode_request(random_queries(10))
        headers = {"content-type": wire.MSGPACK_MEDIA_TYPE}
        assert client.post(wire.EVALUATE_PATH.format(name="m1"), content=q, headers=headers).status_code == 404
        assert client.post(wire.EVALUATE_PATH.format(name="m0"), content=q, headers=headers).status_code == 200
