"""The sampling lobe of a material made from maps (`training.microgeometry.lobe`)."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.core.contract import SamplingLobe
from neumip.groundtruth.description import Microgeometry
from neumip.groundtruth.lobe import MAX_WEIGHT, SHARP_ALPHA, material_lobe, sampling_lobe


def maps(height: np.ndarray, roughness) -> Microgeometry:
    roughness = np.asarray(roughness, np.float32).reshape(np.shape(roughness) or (1, 1))
    return Microgeometry(height=height.astype(np.float32), base_color=np.full((1, 1, 3), 0.5, np.float32),
                         roughness=roughness, metallic=np.zeros((1, 1), np.float32), specular=0.5, bsdf=None,
                         normals="smooth")


def test_a_flat_varnish_gets_its_own_lobe():
    lobe = sampling_lobe(maps(np.zeros((16, 16)), 0.3))
    assert lobe == SamplingLobe(pytest.approx(0.09), MAX_WEIGHT)


def test_rough_maps_keep_the_cosine_and_slopes_take_the_sharp_share():
    assert sampling_lobe(maps(np.zeros((16, 16)), 0.8)) is None  # alpha 0.64: wider than the cosine
    x = np.arange(16) / 16
    steep = np.tile(0.2 * np.sin(2 * np.pi * x), (16, 1))  # slopes up to 1.26: tilted lobes
    assert sampling_lobe(maps(steep, 0.1)) is not None  # its flat crests and troughs are sharp
    assert sampling_lobe(maps(3 * steep, 0.1)).weight < sampling_lobe(maps(steep, 0.1)).weight
    nearly_rough = np.full((16, 16), 0.9)
    nearly_rough[0, :5] = 0.2  # 2 % sharp: below MIN_WEIGHT
    assert sampling_lobe(maps(np.zeros((16, 16)), nearly_rough)) is None


def test_a_roughness_map_of_another_size_is_resampled_to_the_height():
    roughness = np.full((32, 32), 0.9)
    roughness[:, :16] = 0.3
    lobe = sampling_lobe(maps(np.zeros((16, 16)) + np.arange(16)[:, None] * 1e-3, roughness))
    assert lobe.alpha == pytest.approx(0.09, abs=0.01) and lobe.weight == pytest.approx(MAX_WEIGHT)
    assert sampling_lobe(maps(np.full((16, 16), np.nan), 0.3)) is None  # NaN texels are not sharp


def test_the_weight_is_the_sharp_share():
    roughness = np.full((16, 16), 0.9)
    roughness[:4] = 0.2  # a quarter of the texels: alpha 0.04
    lobe = sampling_lobe(maps(np.zeros((16, 16)), roughness))
    assert lobe.weight == pytest.approx(0.25) and lobe.alpha == pytest.approx(0.04)
    assert lobe.alpha < SHARP_ALPHA


def test_a_homogeneous_bsdf_has_its_own_alpha_or_none():
    geo = maps(np.zeros((1, 1)), 0.5)
    assert sampling_lobe(Microgeometry(**{**vars(geo), "bsdf": {"type": "roughconductor", "alpha": 0.1}})) == (
        SamplingLobe(0.1, MAX_WEIGHT))
    assert sampling_lobe(Microgeometry(**{**vars(geo), "bsdf": {"type": "roughconductor", "alpha": 0.7}})) is None
    assert sampling_lobe(Microgeometry(**{**vars(geo), "bsdf": {"type": "twosided", "bsdf": {
        "type": "roughplastic"}}})) == SamplingLobe(0.1, MAX_WEIGHT)  # Mitsuba's default alpha
    assert sampling_lobe(Microgeometry(**{**vars(geo), "bsdf": {"type": "conductor"}})).alpha == 0.02
    x = np.arange(16) / 16
    bumpy = Microgeometry(**{**vars(maps(np.tile(0.5 * np.sin(2 * np.pi * x), (16, 1)), 0.5)),
                             "bsdf": {"type": "roughconductor", "alpha": 0.1}})
    assert sampling_lobe(bumpy).weight < MAX_WEIGHT  # the height tilts it as it tilts the maps
    assert material_lobe("flat") is None  # the library's diffuse plane
