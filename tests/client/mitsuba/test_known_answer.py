"""Known answer: a neural Lambertian renders like Mitsuba's own `diffuse` with the stock `path`.

Images are compared by block means against a seed-to-seed noise baseline of the stock renderer: the
difference between our render and three stock renders may not exceed what the stock renders differ
by among themselves (with a margin), and a stock render with a slightly different albedo must fail
the same criterion (so the check can fail).
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest

from neumip.engines.local import LocalMaterials
from neumip.client.mitsuba.bsdf import mi
from neumip.client.mitsuba.render import RenderConfig, render_scene

from .scenes import DIFFUSE, LAMBERT, MAX_DEPTH, block_error, mixed, simple, stock



def neural(scene_fn, evaluator, seed: int) -> np.ndarray:
    scene = mi.load_dict(scene_fn(LAMBERT, {"type": "neumip_path", "max_depth": MAX_DEPTH}))
    return render_scene(scene, evaluator, RenderConfig(spp=64, seed=seed)).image


@pytest.mark.parametrize(
    ("scene_fn", "control_albedo"), [(simple, 0.45), (mixed, 0.4)], ids=["lambert-only", "mixed-materials"]
)
def test_neural_lambert_matches_stock_diffuse(model_dir, scene_fn, control_albedo):
    references = [stock(scene_fn, DIFFUSE, seed=s) for s in (1, 2, 3)]
    noise = np.mean([block_error(a, b) for a, b in itertools.combinations(references, 2)])
    ours = neural(scene_fn, LocalMaterials(model_dir), seed=4)
    error = np.mean([block_error(ours, r) for r in references])
    print(f"block RMS error {error:.5f}, seed-to-seed noise {noise:.5f}")
    assert error < 1.5 * noise
    mean = np.mean([r[..., :3].mean() for r in references])
    assert abs(ours[..., :3].mean() / mean - 1) < 0.02
    # The criterion discriminates: a slightly darker diffuse in place of the neural one is caught.
    control = {"type": "diffuse", "reflectance": {"type": "rgb", "value": control_albedo}}
    darker = stock(scene_fn, control, seed=5)
    assert np.mean([block_error(darker, r) for r in references]) > 1.5 * noise


def test_same_seed_follows_the_stock_sample_sequence(model_dir):
    """neumip_path draws its random numbers as `path` does: with one seed and one emitter chosen per
    shading point, as `path` chooses it, the images agree closely."""
    scene = mi.load_dict(simple(LAMBERT, {"type": "neumip_path", "max_depth": MAX_DEPTH, "all_emitters": False}))
    ours = render_scene(scene, LocalMaterials(model_dir), RenderConfig(spp=64, seed=7)).image
    reference = stock(simple, DIFFUSE, seed=7)
    assert np.abs(ours - reference).mean() < 1e-3 * reference.mean()


SHIPPED_FLAT = Path(__file__).resolve().parents[3] / "models" / "flat.onnx"


@pytest.mark.skipif(not SHIPPED_FLAT.exists(), reason="models/flat.onnx (trained flat Lambertian) not shipped yet")
def test_trained_flat_material_renders_like_diffuse(tmp_path):
    """The whole pipeline: a material trained on path-traced data of a flat albedo-0.5 plane renders
    like Mitsuba's diffuse 0.5, up to the model's fitting error (a few percent)."""
    (tmp_path / "lambert.onnx").symlink_to(SHIPPED_FLAT)  # LAMBERT names the material 'lambert'
    ours = neural(simple, LocalMaterials(tmp_path), seed=4)
    reference = stock(simple, DIFFUSE, seed=1)
    assert abs(ours[..., :3].mean() / reference[..., :3].mean() - 1) < 0.05
    assert block_error(ours, reference) < 0.05 * reference[..., :3].mean() + 2 * block_error(
        stock(simple, DIFFUSE, seed=2), reference
    )
