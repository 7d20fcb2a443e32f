"""A render through models trimmed to the level `neumip budget` found safe (every pyramid: the latents, the base
maps, the relief's heights) differs from the untrimmed render by far less than Monte-Carlo noise (the demo scene
seen small, shipped models, the budget taken for the render's spp)."""

from __future__ import annotations

import numpy as np

from neumip.engines.local import LocalMaterials
from neumip.client.mitsuba.budget import scene_budget
from neumip.client.mitsuba.render import RenderConfig, load_scene, render_scene
from neumip.training.export.trim import trim_file

PARAMS = {"resx": "32", "resy": "32", "max_depth": "4"}
SPP = 4


def test_trimmed_render_is_within_noise(tmp_path):
    budget = scene_budget(load_scene("scenes/demo.xml", **PARAMS), "models", spp=4, render_spp=SPP)
    assert all(m.finest_level >= 1 for m in budget.materials)  # the cut is safe at 99.9 %
    for m in budget.materials:
        trim_file(f"models/{m.material}.onnx", tmp_path / f"{m.material}.onnx", m.finest_level)
        # every pyramid cut (the maps' too): no larger than the budget said, and under half the model
        assert (tmp_path / f"{m.material}.onnx").stat().st_size <= m.trimmed_bytes + 1000
        assert m.trimmed_bytes < 0.5 * m.model_bytes

    def render(folder, seed):
        scene = load_scene("scenes/demo.xml", **PARAMS)
        return render_scene(scene, LocalMaterials(folder, threads=1), RenderConfig(spp=SPP, seed=seed)).image[..., :3]

    full, trimmed, other_seed = render("models", 0), render(tmp_path, 0), render("models", 1)
    noise = np.abs(other_seed - full).mean()
    difference = np.abs(trimmed - full).mean()
    assert noise > 0 and difference < 0.1 * noise, (difference, noise)
