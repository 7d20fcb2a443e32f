"""Procedural generators: periodic (seamless) tiles, valid ranges, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.groundtruth import procedural
from neumip.groundtruth.procedural import GENERATORS

RES = 64


def seam_ratio(height: np.ndarray) -> float:
    """Height jump across the tile seam relative to the typical jump between neighbouring texels."""
    seam = max(np.abs(height[:, 0] - height[:, -1]).mean(), np.abs(height[0] - height[-1]).mean())
    inner = max(np.abs(np.diff(height, axis=1)).mean(), np.abs(np.diff(height, axis=0)).mean())
    return seam / max(inner, 1e-12)


@pytest.mark.parametrize("name", sorted(GENERATORS))
def test_generator_maps_are_valid(name):
    maps = GENERATORS[name](RES, np.random.default_rng(0))
    assert maps["height"].shape == (RES, RES) and maps["base_color"].shape == (RES, RES, 3)
    for key in ("base_color", "roughness", "metallic"):
        assert maps[key].min() >= 0 and maps[key].max() <= 1, key
    assert all(np.isfinite(m).all() and m.dtype == np.float32 for m in maps.values())


@pytest.mark.parametrize("name", ["yarn", "rock", "turtle", "foam"])
def test_generator_tiles_are_seamless_and_not_flat(name):
    height = GENERATORS[name](RES, np.random.default_rng(0))["height"]
    assert np.ptp(height) > 0.5
    assert seam_ratio(height) < 3.0  # a seam no worse than the usual texel-to-texel change


def test_a_non_periodic_map_fails_the_seam_check():
    ramp = np.tile(np.linspace(0, 1, RES), (RES, 1))
    assert seam_ratio(ramp) > 10  # the check above can fail


@pytest.mark.parametrize("name", sorted(GENERATORS))
def test_same_seed_same_maps(name):
    a = GENERATORS[name](RES, np.random.default_rng(5))
    b = GENERATORS[name](RES, np.random.default_rng(5))
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


def test_voronoi_wraps_around():
    f1, f2, nearest = procedural.voronoi(32, np.array([[0.02, 16.5 / 32], [0.5, 0.5]]))
    # the texel at u = 31.5/32 is 0.036 from the point at u = 0.02 across the seam
    assert nearest[16, 31] == 0 and f1[16, 31] == pytest.approx(0.02 + 0.5 / 32, abs=1e-9)
    assert (f2 >= f1).all()
