"""Shared fixtures of the training tests: edge queries, the torch vs ONNX parity check, an
analytic flat-plane data set with a known answer at every level of detail, and one local Ray."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core.contract import random_queries

PARITY_ATOL, PARITY_RTOL = 1e-5, 1e-4
"""The export's parity contract: ONNX Runtime answers within 1e-5 abs or 1e-4 rel of torch."""

PLANE_COLOR = np.array([0.9, 0.6, 0.3])
"""Base albedo of the analytic plane."""


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


def _write_plane_data(path, n: int, seed: int = 0):
    from neumip.training.dataset import write_dataset

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
