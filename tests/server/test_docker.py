"""The Docker image, end to end: docker/smoke.sh builds it with `docker compose`, waits for its
healthcheck, sends real queries, checks non-root / no torch / loopback port / graceful stop."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def docker_engine() -> str | None:
    """None if a Docker engine answers, else why not."""
    if shutil.which("docker") is None:
        return "no docker command (apt-get install -y docker.io)"
    info = subprocess.run(["docker", "info"], capture_output=True, text=True, timeout=30)
    if info.returncode != 0:
        return "no Docker engine answers (start one: dockerd --iptables=false --bridge=none &)"
    if subprocess.run(["docker", "compose", "version"], capture_output=True, timeout=30).returncode != 0:
        return "the docker compose plugin is missing"
    return None


@pytest.mark.slow
@pytest.mark.docker
def test_docker_smoke():
    reason = docker_engine()
    if reason:
        pytest.skip(f"Docker smoke test skipped: {reason}")
    run = subprocess.run(
        [str(ROOT / "docker" / "smoke.sh")],
        cwd=ROOT, capture_output=True, text=True, timeout=900, env={**os.environ, "PYTHON": sys.executable},
    )
    assert run.returncode == 0, run.stdout[-6000:] + run.stderr[-6000:]
    assert "smoke: OK" in run.stdout
