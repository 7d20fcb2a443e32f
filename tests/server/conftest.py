"""Server fixtures: an in-process app (TestClient, lifespan run) and a real `neumip serve` process."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest

from neumip.server.app import create_app
from neumip.server.settings import Settings


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class LiveServer:
    """A `neumip serve` process on loopback."""

    url: str
    process: subprocess.Popen
    log: Path

    @property
    def host_port(self) -> str:
        return self.url.split("://", 1)[1]

    def rss_bytes(self) -> int:
        """Resident memory of the server process."""
        for line in Path(f"/proc/{self.process.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        raise RuntimeError("no VmRSS")

    def stop(self) -> int:
        """SIGTERM, wait for the graceful exit; returns the exit status."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                return self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
                raise
        return self.process.returncode


def start_server(model_dir: Path, log: Path, **env: str) -> LiveServer:
    """Start `neumip serve` on a free loopback port and wait (<= 60 s) until it reports ready."""
    port = free_port()
    environ = {**os.environ, "NEUMIP_WARMUP_ROWS": "256", **{f"NEUMIP_{k.upper()}": str(v) for k, v in env.items()}}
    cmd = [sys.executable, "-m", "neumip.client.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
           "--model-dir", str(model_dir)]
    process = subprocess.Popen(cmd, env=environ, stdout=log.open("w"), stderr=subprocess.STDOUT)
    server = LiveServer(f"http://127.0.0.1:{port}", process, log)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"server exited with {process.returncode}:\n{log.read_text()}")
        try:
            if httpx.get(server.url + "/v2/health/ready", timeout=1).status_code == 200:
                return server
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    server.stop()
    raise RuntimeError(f"server not ready within 60 s:\n{log.read_text()}")


@pytest.fixture(scope="module")
def live_server(model_dir, tmp_path_factory):
    """A real `neumip serve` process serving the test materials; checks the graceful exit after."""
    server = start_server(model_dir, tmp_path_factory.mktemp("server") / "server.log")
    yield server
    assert server.stop() == 0, server.log.read_text()


@pytest.fixture(scope="module")
def client(model_dir):
    """TestClient of an in-process app (lifespan run) serving the test materials."""
    from fastapi.testclient import TestClient

    app = create_app(Settings(model_dir=model_dir, warmup_rows=64, max_rows=50_000, max_body_bytes=4 << 20))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


@pytest.fixture(scope="module")
def reference(model_dir):
    """In-process evaluation to compare server answers with, bit for bit: the default `LocalMaterials`
    (one chunk worker per core, chunks cut unlike the server's). The exported graph answers a row with
    the same bits in any batch, so no alignment of the server's calls to the reference's is needed.
    """
    from neumip.client.local import LocalMaterials

    return LocalMaterials(model_dir)
