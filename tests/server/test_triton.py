"""A real NVIDIA Triton serving a `neumip export-repository --backend python` repository (slow).

Triton comes from PyPI's nvidia-pytriton, which bundles a `tritonserver` binary with the python backend
only. What it needs here: the python stub for this interpreter's version beside
``backends/python/libtriton_python.so`` (copied into a temporary backend folder, with the wheel's
bundled libraries on LD_LIBRARY_PATH), and a ``python`` on PATH with onnxruntime and numpy 1.x (the
stub of Triton 2.51 sends empty outputs with numpy 2; see `neumip.server.triton_python_model`).
NEUMIP_TRITON_PYTHON names that interpreter; by default the test's own Python is used if it fits.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from neumip.core.contract import random_queries
from neumip.engines.local import LocalMaterials

pytestmark = pytest.mark.slow


def triton_python() -> str | None:
    """A Python whose numpy is 1.x and that has onnxruntime, or None."""
    python = os.environ.get("NEUMIP_TRITON_PYTHON", sys.executable)
    probe = "import numpy, onnxruntime, sys; sys.exit(int(numpy.__version__.split('.')[0]) >= 2)"
    return python if subprocess.run([python, "-c", probe], capture_output=True).returncode == 0 else None


@pytest.fixture(scope="module")
def triton(model_dir, tmp_path_factory, port_finder):
    spec = importlib.util.find_spec("pytriton")
    if spec is None:
        pytest.skip("nvidia-pytriton is not installed (pip install --no-deps nvidia-pytriton)")
    python = triton_python()
    if python is None:
        pytest.skip("no Python with onnxruntime and numpy<2 for Triton's python stub: set NEUMIP_TRITON_PYTHON")
    root = Path(spec.submodule_search_locations[0]) / "tritonserver"
    work = tmp_path_factory.mktemp("triton")
    backends = work / "backends"
    shutil.copytree(root / "backends" / "python", backends / "python")
    version = f"{sys.version_info.major}.{sys.version_info.minor}"
    shutil.copy(root / "python_backend_stubs" / version / "triton_python_backend_stub", backends / "python")
    repo = work / "repo"
    env = {**os.environ, "NEUMIP_MAX_WAIT_MS": "20"}  # 20 ms queue delay: concurrent requests merge
    subprocess.run([sys.executable, "-m", "neumip.client.cli", "export-repository", str(model_dir), "-o", str(repo),
                    "--backend", "python", "--threads", "1"], check=True, env=env)
    port = port_finder()
    log = work / "triton.log"
    env = {**os.environ, "PATH": f"{Path(python).parent}:{os.environ['PATH']}",
           "LD_LIBRARY_PATH": str(root.parent.parent / "nvidia_pytriton.libs")}
    cmd = [str(root / "bin" / "tritonserver"), f"--model-repository={repo}", f"--backend-directory={backends}",
           "--http-address=127.0.0.1", f"--http-port={port}", "--allow-grpc=false", "--allow-metrics=false",
           "--disable-auto-complete-config"]
    process = subprocess.Popen(cmd, env=env, stdout=log.open("w"), stderr=subprocess.STDOUT)
    import tritonclient.http as http

    client = http.InferenceServerClient(f"127.0.0.1:{port}")
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and process.poll() is None:
        try:
            if client.is_server_ready():
                break
        except Exception:
            pass
        time.sleep(0.5)
    else:
        process.kill()
        pytest.fail(f"tritonserver did not become ready (exit {process.poll()}):\n{log.read_text()[-4000:]}")
    yield client, f"127.0.0.1:{port}"
    process.terminate()
    process.wait(timeout=60)


def test_triton_serves_every_material_bit_identical_to_in_process(triton, model_dir):
    import tritonclient.http as http

    client, _ = triton
    local = LocalMaterials(model_dir)
    index = {m["name"]: m["state"] for m in client.get_model_repository_index()}
    assert index == {name: "READY" for name in local.materials()}
    for i, name in enumerate(local.materials()):
        q = random_queries(5000, seed=i)
        tensor = http.InferInput("queries", list(q.shape), "FP32")
        tensor.set_data_from_numpy(q, binary_data=True)
        out = client.infer(name, [tensor]).as_numpy("rgb")
        assert np.array_equal(out, local.evaluate(name, q)), name


def test_triton_batches_concurrent_requests(triton, model_dir):
    import tritonclient.http as http

    _, url = triton
    local = LocalMaterials(model_dir)
    sizes = [3, 50, 700, 1, 64, 9] * 6

    def infer(i: int) -> bool:
        q = random_queries(sizes[i], seed=100 + i)
        tensor = http.InferInput("queries", list(q.shape), "FP32")
        tensor.set_data_from_numpy(q, binary_data=True)
        out = http.InferenceServerClient(url).infer("rand16", [tensor]).as_numpy("rgb")
        return np.array_equal(out, local.evaluate("rand16", q))

    with ThreadPoolExecutor(12) as pool:
        assert all(pool.map(infer, range(len(sizes))))
    stats = http.InferenceServerClient(url).get_inference_statistics("rand16")["model_stats"][0]
    requests = int(stats["inference_stats"]["success"]["count"])
    assert requests >= len(sizes) and int(stats["inference_count"]) >= sum(sizes)
    assert int(stats["execution_count"]) < requests, stats  # dynamic batching merged requests
    print(f"triton: {requests} requests, {stats['inference_count']} rows in {stats['execution_count']} model.py calls")


def test_triton_refuses_nan_with_an_error(triton):
    import tritonclient.http as http
    from tritonclient.utils import InferenceServerException

    client, _ = triton
    q = random_queries(4, seed=1)
    q[2, 3] = np.nan
    tensor = http.InferInput("queries", list(q.shape), "FP32")
    tensor.set_data_from_numpy(q, binary_data=True)
    with pytest.raises(InferenceServerException, match="row 2 holds NaN"):
        client.infer("rand16", [tensor])


def test_material_client_over_v2_against_triton(triton, model_dir):
    """The renderer's client speaks the Open Inference Protocol to a real Triton: the same answers as
    in-process, large buffers split into several requests, and Triton's errors reported as ServerError."""
    from neumip.client.http import ClientConfig, MaterialClient, ServerError

    _, url = triton
    local = LocalMaterials(model_dir)
    with MaterialClient(f"http://{url}", ClientConfig(max_rows=4096), protocol="v2") as client:
        for i, name in enumerate(local.materials()):
            q = random_queries(10_000, seed=200 + i)  # three requests of <= 4096 rows
            np.testing.assert_array_equal(client.evaluate(name, q), local.evaluate(name, q))
        with pytest.raises(ServerError) as info:
            client.evaluate("no_such_material", random_queries(4))
        assert info.value.status in (400, 404)
