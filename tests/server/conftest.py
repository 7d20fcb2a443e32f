"""Server fixtures: an in-process app (TestClient, lifespan run) and the in-process reference answers.

Real `neumip serve` processes: `serve` and `live_server` in tests/conftest.py."""

from __future__ import annotations

import pytest

from neumip.server.app import create_app
from neumip.server.settings import Settings


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
    from neumip.engines.local import LocalMaterials

    return LocalMaterials(model_dir)
