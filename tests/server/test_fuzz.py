"""Property-based fuzzing of every endpoint of our OpenAPI schema with schemathesis, against a real
server process: no generated request may cause a 5xx.

Two runs: one with fuzzed material names (mostly 404/400 paths), one with the name fixed to a served
material so that bodies reach the decoders. Afterwards the server's own metrics must hold no 5xx.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

SCHEMATHESIS = shutil.which("schemathesis") or str(Path(sys.executable).with_name("schemathesis"))


@pytest.mark.parametrize("fixed_name", [False, True], ids=["fuzzed-names", "served-name"])
def test_no_generated_request_causes_a_server_error(live_server, tmp_path, fixed_name):
    if not Path(SCHEMATHESIS).exists():
        pytest.skip("schemathesis is missing: pip install 'neumip[test]'")
    config = tmp_path / "schemathesis.toml"
    config.write_text('[parameters]\n"path.name" = "rand16"\n' if fixed_name else "")
    cmd = [SCHEMATHESIS, "--config-file", str(config), "run", live_server.url + "/openapi.json",
           "--checks", "not_a_server_error", "--max-examples", "30", "--seed", "1", "--workers", "1",
           "--request-timeout", "30", "--no-color"]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert "passed" in run.stdout
    metrics = httpx.get(live_server.url + "/metrics").text
    server_errors = [line for line in metrics.splitlines() if line.startswith("neumip_http_requests_total") and 'status="5' in line
                     and 'route="/v2/health/ready"' not in line]  # (503 while the models load)
    assert server_errors == [], server_errors
    assert httpx.get(live_server.url + "/v2/health/live").status_code == 200
