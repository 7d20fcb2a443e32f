"""Configs read from files refuse unknown keys and round-trip."""

import pytest

from neumip.core.config import MaterialConfig
from neumip.training.loop.config import SHIP, TrainConfig


def test_material_config_roundtrip_and_unknown_keys():
    cfg = MaterialConfig(resolution=32, offset=False)
    assert MaterialConfig.from_json(cfg.to_json()) == cfg
    with pytest.raises(ValueError, match=r"unknown MaterialConfig fields: \['resolutoin'\]"):
        MaterialConfig.from_dict({"resolutoin": 64})
    with pytest.raises(ValueError, match="power of two"):
        MaterialConfig(resolution=48)


def test_ceiling_is_stored_only_when_set_and_must_be_a_finite_answer():
    assert "ceiling" not in MaterialConfig(resolution=32).to_json()  # the paper's models read as before
    cfg = MaterialConfig(resolution=32, ceiling=209.90163)
    assert MaterialConfig.from_json(cfg.to_json()) == cfg
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="ceiling must be 0"):
            MaterialConfig(ceiling=bad)


def test_train_config_roundtrip_and_unknown_keys():
    assert TrainConfig.from_dict(SHIP.to_dict()) == SHIP
    with pytest.raises(ValueError, match=r"unknown TrainConfig fields: \['stpes'\]"):
        TrainConfig.from_dict({"stpes": 10})
