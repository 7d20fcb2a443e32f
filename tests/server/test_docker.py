"""The Docker image, end to end: docker/smoke.sh builds it with each compose that is installed (the
v2 plugin `docker compose`, the v1 `docker-compose`), waits for its healthcheck, sends real queries,
checks non-root / no torch / loopback port / memory limit / graceful stop."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def docker_engine(compose: str) -> str | None:
    """None if a Docker engine answers and `compose` runs, else why not."""
    if shutil.which("docker") is None:
        return "no docker command (apt-get install -y docker.io)"
    info = subprocess.run(["docker", "info"], capture_output=True, text=True, timeout=30)
    if info.returncode != 0:
        return "no Docker engine answers (start one: dockerd --iptables=false --bridge=none &)"
    try:
        if subprocess.run([*compose.split(), "version"], capture_output=True, timeout=30).returncode == 0:
            return None
    except FileNotFoundError:
        pass
    return f"`{compose}` is not installed"


@pytest.mark.slow
@pytest.mark.docker
@pytest.mark.parametrize("compose", ["docker compose", "docker-compose"])
def test_docker_smoke(compose):
    reason = docker_engine(compose)
    if reason:
        pytest.skip(f"Docker smoke test skipped: {reason}")
    run = subprocess.run(
        [str(ROOT / "docker" / "smoke.sh")],
        cwd=ROOT, capture_output=True, text=True, timeout=900,
        env={**os.environ, "PYTHON": sys.executable, "NEUMIP_COMPOSE": compose},
    )
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-6000:]
    assert f"smoke: OK with {compose} " in run.stdout
