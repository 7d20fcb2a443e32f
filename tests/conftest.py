"""Shared fixtures: small exported materials built from numpy weights (no training needed), and real
`neumip serve` processes on loopback serving them."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from neumip.core import contract as C


@pytest.fixture(scope="session")
def model_dir(tmp_path_factory):
    """A folder with two small random materials (`rand16`, offset on; `flat16`, offset off) and a
    constant Lambertian `lambert` answering 0.5 / pi."""
    from neumip.core.config import MaterialConfig
    from neumip.training.export import build_onnx, constant_weights, random_weights, save_onnx

    folder = tmp_path_factory.mktemp("models")
    cfg = MaterialConfig(resolution=16)
    save_onnx(build_onnx(cfg, random_weights(cfg, seed=1), "random test material"), folder / "rand16.onnx")
    flat = MaterialConfig(resolution=16, offset=False)
    save_onnx(build_onnx(flat, random_weights(flat, seed=2)), folder / "flat16.onnx")
    save_onnx(
        build_onnx(cfg, constant_weights(cfg, [0.5 / np.pi] * 3), "Lambertian, albedo 0.5"),
        folder / "lambert.onnx",
    )
    return folder


def _groups_of(n: int, lights: int, seed: int) -> np.ndarray:
    """(n, 5 + 2 lights) valid query groups: random queries plus the wi of further random queries."""
    extra = [C.random_queries(n, seed=seed * 100 + j)[:, C.WI_X:C.WI_Y + 1] for j in range(1, lights)]
    return np.ascontiguousarray(np.hstack([C.random_queries(n, seed=seed), *extra]))


@pytest.fixture(scope="session")
def groups_of():
    """groups_of(n, lights, seed) -> (n, 5 + 2 lights) float32 valid query groups (`contract`)."""
    return _groups_of


@pytest.fixture(scope="session")
def write_nan_weight():
    """``write(src, dst)``: the model file `src` saved as `dst` with one texel of its pyramid NaN (a file
    every engine must refuse to serve, with a clear error)."""
    import onnx

    def write(src: Path, dst: Path) -> None:
        model = onnx.load(src)
        for init in model.graph.initializer:
            if init.name == "pyramid":
                values = onnx.numpy_helper.to_array(init).copy()
                values[3, 1] = np.nan
                init.CopyFrom(onnx.numpy_helper.from_array(values, "pyramid"))
        onnx.save(model, dst)

    return write


@pytest.fixture
def default_sigint():
    """A `preexec_fn` that gives a child process the default SIGINT disposition, as in a terminal, so that
    the Ctrl-C a test sends it interrupts it: a test run started in the background (a shell's ``&`` job
    ignores SIGINT, and children inherit that) would otherwise make Python in the child ignore it."""
    return lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def port_finder():
    """port_finder() -> a free TCP port on 127.0.0.1 (for servers a test starts itself)."""
    return free_port


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
            with urllib.request.urlopen(server.url + "/v2/health/ready", timeout=1) as reply:
                if reply.status == 200:
                    return server
        except OSError:  # refused while starting, or 400 (HTTPError) until warm
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


def _servers(model_dir: Path, log_path):
    """A `start(folder=None, **settings)` that starts `neumip serve` processes; after the yield each
    is stopped and must have exited with status 0."""
    servers = []

    def start(folder: Path | None = None, **env) -> LiveServer:
        servers.append(start_server(folder or model_dir, log_path(len(servers)), **env))
        return servers[-1]

    yield start
    for server in servers:
        assert server.stop() == 0, server.log.read_text()


@pytest.fixture
def serve(model_dir, tmp_path):
    """Start real `neumip serve` processes for one test: ``serve(max_rows=5000)`` (settings as keyword
    arguments, NEUMIP_* without the prefix; the folder defaults to the test materials). Each stops
    after the test, and must have exited with status 0."""
    yield from _servers(model_dir, lambda i: tmp_path / f"server{i}.log")


@pytest.fixture(scope="module")
def serve_module(model_dir, tmp_path_factory):
    """`serve` for servers that a whole test module shares."""
    yield from _servers(model_dir, lambda i: tmp_path_factory.mktemp("server") / f"server{i}.log")
