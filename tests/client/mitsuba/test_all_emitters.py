"""Next-event estimation towards every emitter at neural surfaces (`PathConfig.all_emitters`): it must
keep the image (the known answer of a neural Lambertian, `test_known_answer`) and lower the noise of
the light choice; with more than `MAX_ALL_EMITTERS` the integrator chooses one, as the stock `path`."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.engines.local import LocalMaterials
from neumip.client.mitsuba.bsdf import mi
from neumip.client.mitsuba.integrator import MAX_ALL_EMITTERS
from neumip.client.mitsuba.render import RenderConfig, render_scene

from .scenes import DIFFUSE, LAMBERT, MAX_DEPTH, simple, stock


def sun_and_sky(bsdf: dict, integrator: dict, lights: int = 1) -> dict:
    """`simple` lit by ``lights`` directional suns and the sky, without the area light."""
    scene = simple(bsdf, integrator, size=32)
    scene.pop("light")
    for i in range(lights):
        scene[f"sun{i}"] = {"type": "directional", "direction": [0.3 * i - 0.3, -1.0, -0.4],
                            "irradiance": {"type": "rgb", "value": 2.0 / lights}}
    return scene


def render(model_dir, scene: dict, seed: int, spp: int = 16) -> np.ndarray:
    return render_scene(mi.load_dict(scene), LocalMaterials(model_dir), RenderConfig(spp=spp, seed=seed)).image[..., :3]


def pair_noise(model_dir, scene: dict, spp: int = 16) -> float:
    a, b = (render(model_dir, scene, seed, spp) for seed in (1, 2))
    return float(np.mean((a - b) ** 2) / 2)


@pytest.mark.parametrize("lights", [1, MAX_ALL_EMITTERS])  # 2 emitters (sun, sky); 5: one is chosen
def test_the_image_keeps_its_mean(model_dir, lights):
    integrator = {"type": "neumip_path", "max_depth": MAX_DEPTH}
    ours = np.mean([render(model_dir, sun_and_sky(LAMBERT, integrator, lights), seed, 64).mean() for seed in (3, 4)])
    reference = np.mean([stock(lambda b, i: sun_and_sky(b, i, lights), DIFFUSE, seed)[..., :3].mean()
                         for seed in (5, 6)])
    assert ours == pytest.approx(reference, rel=0.01)


def test_sampling_every_emitter_lowers_the_noise(model_dir):
    one = pair_noise(model_dir, sun_and_sky(LAMBERT, {"type": "neumip_path", "max_depth": MAX_DEPTH,
                                                       "all_emitters": False}))
    every = pair_noise(model_dir, sun_and_sky(LAMBERT, {"type": "neumip_path", "max_depth": MAX_DEPTH}))
    print(f"noise: one emitter {one:.3e}, every emitter {every:.3e}")
    assert every < 0.7 * one


def test_more_emitters_than_the_limit_choose_one(model_dir):
    """Above the limit the neural lanes' light sample is the stock choice: the same image as
    `all_emitters` off (up to float rounding)."""
    base = {"type": "neumip_path", "max_depth": MAX_DEPTH}
    scene = sun_and_sky(LAMBERT, base, MAX_ALL_EMITTERS)  # 5 emitters
    off = sun_and_sky(LAMBERT, {**base, "all_emitters": False}, MAX_ALL_EMITTERS)
    np.testing.assert_allclose(render(model_dir, scene, 7), render(model_dir, off, 7), rtol=1e-5, atol=1e-7)
