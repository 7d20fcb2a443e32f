"""Fixtures of the training tests: one local Ray for every test that runs Ray tasks."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def local_ray():
    """A local Ray with 2 CPUs, started once (it costs seconds); skips when Ray is not installed."""
    ray = pytest.importorskip("ray", reason="Ray is not installed: pip install 'neumip[cluster]'")
    ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level="WARNING")
    yield ray
    ray.shutdown()
