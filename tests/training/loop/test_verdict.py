"""The fit's verdict: a model's query error against the ground truth's own noise."""

from __future__ import annotations

import json

import numpy as np
import pytest

from neumip.training.loop.verdict import noise_floor, ratio_at, shipped_ratios, verdict_line


def test_the_noise_floor_is_the_variance_of_a_target_s_mean():
    rng = np.random.default_rng(0)
    spp, sigma = 16, 0.3
    samples = rng.normal(1.0, sigma, (20000, 2 * spp, 3)).astype(np.float32)
    targets, floor = noise_floor(samples, spp)
    assert floor == pytest.approx(sigma**2 / spp, rel=0.02)
    assert np.mean((targets - 1.0) ** 2) == pytest.approx(floor, rel=0.05)  # a perfect model's MSE is the floor


def test_the_verdict_places_the_model_among_the_shipped_ones(tmp_path):
    for name, ratio in (("a", 1.5), ("b", 3.0)):
        (tmp_path / f"{name}.json").write_text(json.dumps({"validation": {"noise": {"ratio": ratio, "spp": 16}}}))
    (tmp_path / "c.json").write_text(json.dumps({"validation": {}}))  # a record without the check
    (tmp_path / "d.json").write_text("not json")
    shipped = shipped_ratios(tmp_path)
    assert shipped == {"a": (1.5, 16), "b": (3.0, 16)}
    noise = {"mse": 2e-3, "noise_floor": 1e-3, "ratio": 2.0, "spp": 16}
    line = verdict_line(noise, shipped)
    assert "2.00x the ground truth's own noise" in line and "1 of 2 closer" in line
    assert "closer to the noise than every one" in verdict_line({**noise, "mse": 1.1e-3, "ratio": 1.1}, shipped)
    assert "shipped" not in verdict_line(noise, {}) and shipped_ratios(tmp_path / "none") == {}
    # the same model error on 4-spp data: 4x the floor there, the same place among 16-spp models
    low = {"mse": 1e-3 + 4e-3, "noise_floor": 4e-3, "ratio": 1.25, "spp": 4}
    assert ratio_at(low, 16) == pytest.approx(2.0) and "1 of 2 closer" in verdict_line(low, shipped)
