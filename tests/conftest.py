"""Shared fixtures: small exported materials built from numpy weights (no training needed)."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.client import contract as C


def random_queries(n: int, seed: int = 0, max_theta_deg: float = 85.0) -> np.ndarray:
    """(n, 7) float32 queries: u, v in [-2, 3), sigma log-uniform over all levels, directions in a cone."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-2, 3, n)
    v = rng.uniform(-2, 3, n)
    sigma = 2.0 ** rng.uniform(-11, 1, n)
    r = np.sin(np.radians(max_theta_deg)) * np.sqrt(rng.uniform(0, 1, (n, 2)))
    phi = rng.uniform(0, 2 * np.pi, (n, 2))
    wi = np.stack([r[:, 0] * np.cos(phi[:, 0]), r[:, 0] * np.sin(phi[:, 0])], 1)
    wo = np.stack([r[:, 1] * np.cos(phi[:, 1]), r[:, 1] * np.sin(phi[:, 1])], 1)
    return C.pack_queries(u, v, sigma, wi, wo)


@pytest.fixture(scope="session")
def model_dir(tmp_path_factory):
    """A folder with two small random materials (`rand16`, offset on; `flat16`, offset off) and a
    constant Lambertian `lambert` answering 0.5 / pi."""
    from neumip.training.config import MaterialConfig
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
