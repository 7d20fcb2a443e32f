"""What an operator sees of a server: each 4xx/5xx answer logged at INFO with its message (successes only
with NEUMIP_ACCESS_LOG), and, while the models load, a port that answers: liveness 200, readiness and
the model endpoints 503 saying why."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
import time

import httpx
import pytest
from fastapi.testclient import TestClient

from neumip.core import wire
from neumip.server.app import create_app
from neumip.server.process import free_port
from neumip.server.registry import Registry
from neumip.server.settings import Settings

QUERY = [[0.25, 0.5, 0.0, 0.3, 0.2, 0.0, 0.0]]
EVALUATE = wire.EVALUATE_PATH.format(name="rand16")


def logged(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name == "neumip.server.logs" and r.levelno == logging.INFO]


def test_errors_are_logged_with_their_message_and_successes_are_not(client, caplog):
    caplog.set_level(logging.INFO, logger="neumip.server.logs")
    assert client.post(EVALUATE, json={"queries": QUERY}).status_code == 200
    assert client.get("/v2/health/ready").status_code == 200
    assert logged(caplog) == []

    assert client.post(wire.EVALUATE_PATH.format(name="nope"), json={"queries": QUERY}).status_code == 404
    assert client.post(EVALUATE, content=b"{", headers={"content-type": "application/json"}).status_code == 400
    assert client.post(EVALUATE, content=b"x", headers={"content-type": "text/plain"}).status_code == 415
    assert client.get("/v1/materials/rand16/evaluate").status_code == 405
    lines = logged(caplog)
    assert len(lines) == 4, lines
    assert lines[0].startswith("POST /v1/materials/nope/evaluate -> 404: unknown material 'nope'")
    assert lines[1].startswith("POST /v1/materials/rand16/evaluate -> 400: ")
    assert lines[2].startswith("POST /v1/materials/rand16/evaluate -> 415: Content-Type must be")
    assert lines[3] == "GET /v1/materials/rand16/evaluate -> 405: method GET not allowed on /v1/materials/rand16/evaluate"
    assert all("\n" not in line for line in lines)


def test_a_client_cannot_forge_log_lines(client, caplog):
    caplog.set_level(logging.INFO, logger="neumip.server.logs")
    assert client.get("/nope%0AINFO%20forged%1b[2K").status_code == 404
    [line] = logged(caplog)
    assert line.startswith("GET /nope\\nINFO forged\\x1b[2K -> 404: no such endpoint") and line.isprintable(), line


def test_a_5xx_is_logged(client, caplog, monkeypatch):
    """A fault inside the app (here: listing the materials raises) is a 500 and one log line."""
    caplog.set_level(logging.INFO, logger="neumip.server.logs")

    def broken(self):
        raise RuntimeError("disk on fire\nsecond line")

    monkeypatch.setattr(Registry, "listing", broken)
    assert client.get(wire.MATERIALS_PATH).status_code == 500
    assert logged(caplog) == ["GET /v1/materials -> 500: RuntimeError: disk on fire"]


def test_access_log_logs_every_request(model_dir, caplog):
    caplog.set_level(logging.INFO, logger="neumip.server.logs")
    with TestClient(create_app(Settings(model_dir=model_dir, warmup_rows=0, access_log=True))) as client:
        assert client.get("/v2/health/live").status_code == 200
    assert logged(caplog) == ["GET /v2/health/live -> 200"]


@pytest.fixture
def slow_load(monkeypatch):
    """Registry.load waits for the returned event (set it to let the models load)."""
    gate = threading.Event()
    load = Registry.load

    def waiting(*args, **kwargs):
        assert gate.wait(60), "the test never let the models load"
        return load(*args, **kwargs)

    monkeypatch.setattr(Registry, "load", waiting)
    yield gate
    gate.set()


def test_while_models_load_the_server_answers_and_says_so(model_dir, slow_load):
    app = create_app(Settings(model_dir=model_dir, warmup_rows=16), load_in_background=True)
    with TestClient(app, raise_server_exceptions=False) as client:
        assert client.get("/v2/health/live").status_code == 200
        ready = client.get("/v2/health/ready")
        assert ready.status_code == 503 and ready.json()["status"] == "loading", ready.text
        for answer in (client.post(EVALUATE, json={"queries": QUERY}), client.get(wire.MATERIALS_PATH),
                       client.get("/v2/models/rand16")):
            assert answer.status_code == 503 and "loading" in answer.json()["error"], answer.text
            assert answer.headers["Retry-After"] == "1"

        slow_load.set()
        deadline = time.monotonic() + 30
        while client.get("/v2/health/ready").status_code != 200:
            assert time.monotonic() < deadline, "not ready 30 s after the load was let go"
            time.sleep(0.02)
        assert client.get("/v2/health/ready").content == b""  # ready: as Triton, an empty 200
        assert client.post(EVALUATE, json={"queries": QUERY}).status_code == 200


def test_a_failed_load_says_why_and_stops_the_server(tmp_path):
    folder = tmp_path / "gone"
    folder.mkdir()
    app = create_app(Settings(model_dir=folder), load_in_background=True)
    stopped = threading.Event()
    app.state.neumip.stop = stopped.set
    folder.rmdir()  # between `neumip serve`'s check and the load
    with TestClient(app) as client:
        assert stopped.wait(30)
        ready = client.get("/v2/health/ready")
        assert ready.status_code == 503 and ready.json()["status"] == "failed", ready.text
        assert "does not exist" in ready.json()["reason"]
        assert client.get("/v2/health/live").status_code == 200


def test_neumip_serve_answers_while_it_loads_and_logs_errors(tmp_path):
    """A real `neumip serve` with a long warm-up: from its first answer on, liveness is 200 and readiness
    503 "loading" until it turns 200, with no refused or reset connection; its log (stderr) holds one line
    per error answer and none for the successes."""
    import shutil
    from pathlib import Path

    folder = tmp_path / "models"
    folder.mkdir()
    shutil.copy(Path(__file__).resolve().parents[2] / "models" / "rock.onnx", folder / "rock.onnx")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = {**os.environ, "NEUMIP_WARMUP_ROWS": "200000", "NEUMIP_POLL_S": "0"}
    log = tmp_path / "server.log"
    with log.open("w") as out:
        process = subprocess.Popen([sys.executable, "-m", "neumip.client.cli", "serve", "--port", str(port),
                                    "--model-dir", str(folder)], env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while True:  # refused until the process has bound its port
            assert process.poll() is None and time.monotonic() < deadline, log.read_text()
            try:
                first = httpx.get(url + "/v2/health/ready", timeout=5)
                break
            except httpx.ConnectError:
                time.sleep(0.01)
        assert first.status_code == 503 and first.json()["status"] == "loading", first.text
        seen = []
        with httpx.Client(base_url=url, timeout=5) as client:  # any connection error fails the test
            while True:
                assert client.get("/v2/health/live").status_code == 200
                ready = client.get("/v2/health/ready")
                seen.append(ready.status_code)
                if ready.status_code == 200:
                    break
                assert ready.status_code == 503 and time.monotonic() < deadline, ready.text
                time.sleep(0.02)
            assert client.post("/v1/materials/rok/evaluate", json={"queries": QUERY}).status_code == 404
            assert client.post("/v1/materials/rock/evaluate", json={"queries": QUERY}).status_code == 200
    finally:
        process.terminate()
        status = process.wait(30)
    text = log.read_text()
    assert status == 0, text
    assert "POST /v1/materials/rok/evaluate -> 404: unknown material 'rok' (served: rock)" in text
    assert "GET /v2/health/ready -> 503: models are loading" in text
    assert "-> 200" not in text
