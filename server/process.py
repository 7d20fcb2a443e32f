"""A `neumip serve` process on loopback: the one way tests, benchmarks and the Docker smoke test start a
server of their own.

    from neumip.server.process import ServerProcess

    with ServerProcess.start("models", log=Path("server.log"), max_rows=50_000) as server:
        httpx.get(server.url + "/v2/health/ready")      # ready: start() waited for it

Settings are keyword arguments, ``NEUMIP_*`` names without the prefix (``engine="kernel"``); `env`
adds other environment variables (``HOME`` for an empty drjit cache, ``PYTHONPATH`` for another
checkout's code). The port is a free one on 127.0.0.1. Leaving the ``with`` block (or `stop`) sends
SIGTERM and waits for the graceful exit.
"""

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

from neumip.server.uvicorn_run import ServeError


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class ServerProcess:
    """A server process on loopback (`start`)."""

    url: str
    """``http://127.0.0.1:PORT``."""
    process: subprocess.Popen
    """The process (its pid, its exit status)."""
    log: Path | None
    """Where its stdout and stderr go (None: nowhere)."""
    ready_s: float = 0.0
    """Seconds from the start until it reported ready."""

    @classmethod
    def start(cls, model_dir: str | Path, log: Path | None = None, *, env: dict[str, str] | None = None,
              command: list[str] | None = None, cores: set[int] | None = None, cwd: Path | None = None,
              timeout_s: float = 120.0, **settings) -> "ServerProcess":
        """Start `neumip serve` on a free loopback port serving `model_dir`, and wait until
        ``/v2/health/ready`` says 200 (ServeError, with the log's tail, if it exits or is not ready within
        `timeout_s`). `command`: another server instead (``{port}`` in it is replaced by the port; it
        must answer ``/v2/health/ready`` too); `cores`: the CPU cores it may run on (set before exec)."""
        port = free_port()
        environ = {**os.environ, **(env or {}), **{f"NEUMIP_{k.upper()}": str(v) for k, v in settings.items()}}
        if command is None:
            command = [sys.executable, "-m", "neumip.client.cli", "serve", "--host", "127.0.0.1", "--port", "{port}",
                       "--model-dir", str(model_dir)]
        command = [part.replace("{port}", str(port)) for part in command]
        place = (lambda: os.sched_setaffinity(0, cores)) if cores else None  # the child, one thread, before exec
        out = log.open("w") if log is not None else subprocess.DEVNULL
        began = time.perf_counter()
        process = subprocess.Popen(command, env=environ, stdout=out, stderr=subprocess.STDOUT, preexec_fn=place,
                                   cwd=cwd)
        server = cls(f"http://127.0.0.1:{port}", process, log)
        try:
            server._wait_ready(timeout_s)
        except BaseException:
            server.kill()
            raise
        server.ready_s = time.perf_counter() - began
        return server

    def _wait_ready(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise ServeError(f"server exited with {self.process.returncode}:\n{self.log_tail()}")
            try:
                with urllib.request.urlopen(self.url + "/v2/health/ready", timeout=1) as reply:
                    if reply.status == 200:
                        return
            except OSError:  # refused while starting, or 400 (HTTPError) until warm
                pass
            time.sleep(0.02)
        raise ServeError(f"server not ready within {timeout_s:g} s:\n{self.log_tail()}")

    def log_tail(self, chars: int = 4000) -> str:
        """The end of the log (empty without one)."""
        return self.log.read_text(errors="replace")[-chars:] if self.log is not None and self.log.exists() else ""

    @property
    def host_port(self) -> str:
        """``127.0.0.1:PORT`` (what tritonclient takes)."""
        return self.url.split("://", 1)[1]

    def rss_bytes(self) -> int:
        """Resident memory of the process."""
        for line in Path(f"/proc/{self.process.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        raise ServeError("no VmRSS in /proc (not Linux?)")

    def stop(self, timeout_s: float = 60.0) -> int:
        """SIGTERM, then wait for the graceful exit; returns the exit status (killed after `timeout_s`:
        TimeoutExpired)."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                return self.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.kill()
                raise
        return self.process.returncode

    def kill(self) -> None:
        """SIGKILL, and reap."""
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()

    def __enter__(self) -> "ServerProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
