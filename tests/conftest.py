"""Shared fixtures: small exported materials built from numpy weights (no training needed), and real
`neumip serve` processes on loopback serving them."""

from __future__ import annotations

import importlib.util
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core.contract import random_queries

from .ray_workers import killing_the_first_busy_worker as _kill_first_busy_worker

os.environ.setdefault("NEUMIP_ENGINE", "onnxruntime")
"""The servers of the tests compare answers with ONNX Runtime's bit for bit; the default engine, auto, is
tested on its own (tests/server/test_engine.py)."""

PLANE_COLOR = np.array([0.9, 0.6, 0.3])
"""Base albedo of the analytic plane."""



def plane_mbtf(queries: np.ndarray) -> np.ndarray:
    """(N, 7) queries -> (N, 3) MBTF of a flat plane with a periodic albedo and a glossy lobe.

    albedo(u, v) = 0.6 + 0.3 sin(2 pi u) cos(2 pi v); a Gaussian footprint of std sigma scales the
    pattern by exp(-4 pi^2 sigma^2) (exact filtering). The glossy term peaks at wi = -wo (mirror).
    """
    u, v, sigma = (queries[:, i].astype(np.float64) for i in (C.U, C.V, C.SIGMA))
    damp = np.exp(-4 * np.pi**2 * np.maximum(sigma, 0) ** 2)
    albedo = 0.6 + 0.3 * damp * np.sin(2 * np.pi * u) * np.cos(2 * np.pi * v)
    hx = queries[:, C.WI_X] + queries[:, C.WO_X]
    hy = queries[:, C.WI_Y] + queries[:, C.WO_Y]
    gloss = 0.5 * np.exp(-(hx**2 + hy**2) / 0.08)
    rgb = albedo[:, None] * PLANE_COLOR[None, :] / np.pi + gloss[:, None]
    return rgb.astype(np.float32)


@pytest.fixture(scope="session")
def plane_color() -> np.ndarray:
    """The analytic plane's base colour (`PLANE_COLOR`)."""
    return PLANE_COLOR


@pytest.fixture(name="plane_mbtf", scope="session")
def plane_mbtf_fixture():
    """plane_mbtf(queries) -> the analytic plane's exact answers (`plane_mbtf`)."""
    return plane_mbtf


@pytest.fixture(scope="session")
def killing_the_first_busy_worker():
    """The context manager that kills the first Ray worker busy with a function (`tests/ray_workers.py`)."""
    return _kill_first_busy_worker


@pytest.fixture(scope="session")
def model_dir(tmp_path_factory):
    """A folder with two small random materials (`rand16`, offset on; `flat16`, offset off) and a
    constant Lambertian `lambert` answering 0.5 / pi."""
    from neumip.core.config import MaterialConfig
    from neumip.training.export.graph import build_onnx, constant_weights, random_weights, save_onnx

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


@pytest.fixture(scope="session")
def port_finder():
    """port_finder() -> a free TCP port on 127.0.0.1 (for servers a test starts itself)."""
    from neumip.server.process import free_port

    return free_port


def start_server(model_dir: Path, log: Path, **settings):
    """`neumip serve` on a free loopback port, ready (`neumip.server.process.ServerProcess`); settings as
    keyword arguments (``NEUMIP_*`` without the prefix), a small warm-up unless given."""
    from neumip.server.process import ServerProcess

    return ServerProcess.start(model_dir, log, timeout_s=60, **{"warmup_rows": 256, **settings})


@pytest.fixture(scope="module")
def live_server(model_dir, tmp_path_factory):
    """A real `neumip serve` process serving the test materials; checks the graceful exit after."""
    server = start_server(model_dir, tmp_path_factory.mktemp("server") / "server.log")
    yield server
    assert server.stop(30) == 0, server.log.read_text()


def _servers(model_dir: Path, log_path):
    """A `start(folder=None, **settings)` that starts `neumip serve` processes; after the yield each
    is stopped and must have exited with status 0."""
    servers = []

    def start(folder: Path | None = None, **env):
        servers.append(start_server(folder or model_dir, log_path(len(servers)), **env))
        return servers[-1]

    yield start
    for server in servers:
        assert server.stop(30) == 0, server.log.read_text()


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


CHECKERBOARD = Path(__file__).resolve().parents[1] / "scenes" / "checkerboard.py"


@pytest.fixture(scope="session")
def checkerboard():
    """``checkerboard(checks, light, dark)``: the foreign material of scenes/checkerboard.py, an
    ``onnx.ModelProto`` written with onnx.helper alone (no neumip metadata, no query groups)."""
    spec = importlib.util.spec_from_file_location("checkerboard", CHECKERBOARD)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.checkerboard


PARITY_ATOL, PARITY_RTOL = 1e-5, 1e-4
"""The export's parity contract: ONNX Runtime answers within 1e-5 abs or 1e-4 rel of torch."""

def _edge_queries(resolution: int) -> np.ndarray:
    """Queries at the contract's edges: sigma out of range and on level boundaries, huge |u|,
    directions at 89.9 degrees, tile seams."""
    rng = np.random.default_rng(7)
    levels = int(np.log2(resolution))
    sigmas = [0.0, -1.0, 1e-12, 0.1 / resolution, 1e3, 1e30]
    sigmas += [2.0**j / resolution for j in range(levels + 1)]  # exactly on level boundaries
    positions = [0.0, 1.0, -1.0, 0.5 / resolution, 1 - 1e-7, -1e-7, -1000.25, 1000.75, -1234.5]
    s89 = np.sin(np.radians(89.9))
    dirs = [(0.0, 0.0), (s89, 0.0), (0.0, -s89), (s89 / np.sqrt(2), s89 / np.sqrt(2)), (1.0, 0.0)]
    rows = []
    for s in sigmas:
        for p in positions:
            wi, wo = dirs[rng.integers(len(dirs))], dirs[rng.integers(len(dirs))]
            rows.append([p, positions[rng.integers(len(positions))], s, *wi, *wo])
    for (wi, wo) in [(a, b) for a in dirs for b in dirs]:
        rows.append([0.3, 0.7, 1.5 / resolution, *wi, *wo])
    return np.asarray(rows, np.float32)


@pytest.fixture(scope="session")
def edge_queries():
    """edge_queries(resolution) -> (N, 7) queries at the contract's edges for that resolution."""
    return _edge_queries


def _assert_parity(got: np.ndarray, want: np.ndarray) -> None:
    np.testing.assert_allclose(got, want, atol=PARITY_ATOL, rtol=PARITY_RTOL)


@pytest.fixture(scope="session")
def assert_parity():
    """assert_parity(onnx_answers, torch_answers): the export's parity contract holds."""
    return _assert_parity


@pytest.fixture(scope="session")
def parity_tolerances():
    """(atol, rtol) of the export's parity contract."""
    return PARITY_ATOL, PARITY_RTOL


def _write_plane_data(path, n: int, seed: int = 0):
    from neumip.groundtruth.dataset import write_dataset

    q = random_queries(n, seed)
    return write_dataset(path, q, plane_mbtf(q), {"material": "analytic-plane", "generator": "tests"})


@pytest.fixture(scope="session")
def plane_data():
    """plane_data(path, n, seed=0): write an n-query analytic plane data set to `path`, return it opened."""
    return _write_plane_data


@pytest.fixture(scope="session")
def local_ray():
    """A local Ray with 2 CPUs, started once (it costs seconds); skips when Ray is not installed."""
    ray = pytest.importorskip("ray", reason="Ray is not installed: pip install 'neumip[cluster]'")
    ray.init(address="local", num_cpus=2, include_dashboard=False, logging_level="WARNING")
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a test module (`pytestmark = pytest.mark.usefixtures("one_torch_thread")`):
    tiny batches run faster on one, and far faster on an oversubscribed machine."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
