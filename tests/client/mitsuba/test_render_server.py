"""Rendering through a real `neumip serve` process: the same image as in-process, bit for bit; a server
that stops mid-render is a clear error and no image is written."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from neumip.client import cli
from neumip.client.http import ClientConfig, MaterialClient
from neumip.engines.local import LocalMaterials
from neumip.client.mitsuba.render import RenderConfig, load_scene, render_scene

from .scenes import write_xml


@pytest.fixture
def one_drjit_thread():
    """Render on one drjit thread, restored after: the film adds samples into pixels with atomic adds
    whose order, on several threads, varies from render to render (the last bit of some pixels, also
    where no neural material is seen); one thread fixes the order, so images compare bit for bit."""
    from neumip.client.mitsuba.render import dr

    before = dr.thread_count()
    yield 1
    dr.set_thread_count(before)


@pytest.fixture
def server(serve):
    """A real `neumip serve` process serving the test materials, shared memory allowed (stopped after the test)."""
    return serve(allow_shared_memory="true")


@pytest.mark.parametrize("protocol", ["msgpack", "v2", "shm"])
def test_server_render_equals_in_process(model_dir, server, tmp_path, one_drjit_thread, protocol):
    """Through msgpack /v1, the Open Inference Protocol's binary tensors and shared memory alike: the same bits."""
    path = write_xml(tmp_path)
    config = RenderConfig(spp=16, seed=5, max_lanes=32 * 32 * 8, threads=one_drjit_thread)  # two passes
    local = render_scene(load_scene(path), LocalMaterials(model_dir), config)
    with MaterialClient(server.url, protocol=protocol) as client:
        remote = render_scene(load_scene(path), client, config)
    assert remote.stats.queries == local.stats.queries > 0
    assert local.image.mean() > 0.01
    np.testing.assert_array_equal(remote.image, local.image)


def test_render_command_over_v2_equals_msgpack(model_dir, server, tmp_path, caplog):
    """`neumip render --protocol v2` and `--protocol shm` write the image `--protocol msgpack` writes (up to the film's
    thread-dependent summation order; bit for bit on one thread: test_server_render_equals_in_process).
    Its HTTP requests are logged only with -v (DEBUG), not one INFO line per request."""
    import logging

    from neumip.client.mitsuba.render import mi

    caplog.set_level(logging.DEBUG)
    scene = write_xml(tmp_path)
    images = {}
    for protocol in ("msgpack", "v2", "shm"):
        out = tmp_path / f"{protocol}.exr"
        assert cli.main(["render", scene, "-o", str(out), "--server", server.url, "--protocol", protocol]) == 0
        images[protocol] = np.array(mi.Bitmap(str(out)))
    assert images["v2"].mean() > 0.01
    np.testing.assert_allclose(images["v2"], images["msgpack"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(images["shm"], images["msgpack"], rtol=1e-5, atol=1e-6)
    import httpx

    assert httpx.get(server.url + "/v2/systemsharedmemory/status").json() == []  # the render closed its client
    assert "HTTP Request" not in caplog.text
    assert cli.main(["render", scene, "-o", str(out), "--server", server.url, "--spp", "1", "-v"]) == 0
    assert "HTTP Request: POST" in caplog.text


SHIPPED = Path(__file__).resolve().parents[3] / "models"
"""The trained materials the repository ships."""


def test_server_render_of_trained_materials_is_bit_identical(tmp_path, serve, one_drjit_thread):
    """Trained rock and yarn rendered in process (default evaluator; and calls cut every 17 rows, over
    two threads) and through the server (which cuts and merges calls its own way): the same bits.
    With the export's former Log-based level of detail the 17-row cut alone changed a pixel here, and
    server renders of trained materials differed from in-process ones by up to 0.09 in some pixels."""
    folder = tmp_path / "models"
    folder.mkdir()
    for name in ("rock", "yarn"):
        shutil.copy(SHIPPED / f"{name}.onnx", folder)
    path = write_xml(tmp_path, a="rock", b="yarn")
    config = RenderConfig(spp=16, seed=11, max_lanes=32 * 32 * 5, threads=one_drjit_thread)  # 4 passes
    local = render_scene(load_scene(path), LocalMaterials(folder), config)
    cut = render_scene(load_scene(path), LocalMaterials(folder, threads=2, chunk=17), config)
    with MaterialClient(serve(folder).url) as client:
        remote = render_scene(load_scene(path), client, config)
    assert remote.stats.queries == local.stats.queries > 0
    assert local.image.mean() > 0.01 and local.image.std() > 0.01
    np.testing.assert_array_equal(cut.image, local.image)
    np.testing.assert_array_equal(remote.image, local.image)


def stop_server_at_second_call(server, monkeypatch) -> dict:
    """Make MaterialClient stop `server` just before its second evaluation; returns the call count."""
    calls = {"n": 0}
    evaluate = MaterialClient.evaluate

    def stop_after_first_call(self, material, queries):
        calls["n"] += 1
        if calls["n"] == 2:
            server.stop()
        return evaluate(self, material, queries)

    monkeypatch.setattr(MaterialClient, "evaluate", stop_after_first_call)
    return calls


def test_server_stopped_mid_render_is_an_error_and_writes_nothing(model_dir, server, tmp_path, monkeypatch, capsys):
    calls = stop_server_at_second_call(server, monkeypatch)
    monkeypatch.setattr("neumip.client.http.ClientConfig", lambda: ClientConfig(retries=1, backoff_s=0.01))
    out = tmp_path / "out.png"
    rc = cli.main(["render", write_xml(tmp_path), "-o", str(out), "--server", server.url])
    assert rc == 2
    err = capsys.readouterr().err
    assert "unreachable" in err and "no image written" in err, err
    assert calls["n"] >= 2
    assert not out.exists() and not list(tmp_path.glob("*.png"))


def test_fallback_finishes_in_process_when_the_server_stops(model_dir, server, tmp_path, monkeypatch, capsys):
    calls = stop_server_at_second_call(server, monkeypatch)
    monkeypatch.setattr("neumip.client.http.ClientConfig", lambda: ClientConfig(retries=0))
    scene = write_xml(tmp_path)
    out, reference = tmp_path / "out.exr", tmp_path / "reference.exr"
    rc = cli.main(["render", scene, "-o", str(out), "--server", server.url, "--fallback", "--models", str(model_dir)])
    assert rc == 0
    assert "evaluated in-process" in capsys.readouterr().out
    assert calls["n"] >= 2  # the server was stopped mid-render, not before it
    assert cli.main(["render", scene, "-o", str(reference), "--models", str(model_dir)]) == 0
    from neumip.client.mitsuba.bsdf import mi

    np.testing.assert_allclose(np.array(mi.Bitmap(str(out))), np.array(mi.Bitmap(str(reference))), rtol=1e-4, atol=1e-5)
