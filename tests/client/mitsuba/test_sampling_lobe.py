"""The sampling lobe of a neural material (`bsdf.NeuMIPBSDF`): a GGX lobe mixed with the cosine, from
the model's metadata or the scene. It must move noise only: the pdf is the sampler's density and a
neural Lambertian sampled with a lobe still renders like Mitsuba's `diffuse`."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.engines.kernel import KernelMaterials
from neumip.engines.local import LocalMaterials
from neumip.client.mitsuba.bsdf import dr, mi
from neumip.client.mitsuba.render import RenderConfig, render_scene
from neumip.core import contract as C

from .scenes import DIFFUSE, LAMBERT, MAX_DEPTH, block_error, simple, stock

LOBE = C.SamplingLobe(0.2, 0.5)
N = 1 << 20


@pytest.fixture(scope="module")
def lobe_dir(tmp_path_factory):
    """The Lambertian test material (0.5 / pi) whose file declares `LOBE`."""
    from neumip.core.config import MaterialConfig
    from neumip.training.export.graph import build_onnx, constant_weights, save_onnx

    folder = tmp_path_factory.mktemp("lobe_models")
    cfg = MaterialConfig(resolution=16)
    save_onnx(build_onnx(cfg, constant_weights(cfg, [0.5 / np.pi] * 3), "Lambertian with a sampling lobe",
                         {C.META_SAMPLING: LOBE.to_json()}), folder / "lambert.onnx")
    return folder


def lanes(theta: float):
    si = dr.zeros(mi.SurfaceInteraction3f, N)
    si.wi = mi.Vector3f(float(np.sin(theta)), 0.0, float(np.cos(theta)))
    rng = np.random.default_rng(int(theta * 100))
    return si, rng


@pytest.mark.parametrize("theta", [0.1, 0.8, 1.4])
def test_pdf_is_the_density_of_the_samples(theta):
    """E[g cos / pdf] over the BSDF's samples equals the integral of g cos, for a flat g (the hemisphere's
    pi) and for one peaked at the mirror direction (integrated by uniform samples)."""
    bsdf = mi.load_dict({**LAMBERT, "lobe_alpha": LOBE.alpha, "lobe_weight": LOBE.weight})
    ctx = mi.BSDFContext()
    si, rng = lanes(theta)
    mirror = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)

    def peaked(wo):
        return dr.power(dr.maximum(dr.dot(wo, mirror), 0.0), 20.0) * mi.Frame3f.cos_theta(wo)

    s1, s2 = mi.Float(rng.random(N)), mi.Point2f(rng.random(N), rng.random(N))
    bs, _ = bsdf.sample(ctx, si, s1, s2)
    ok = bs.pdf > 0
    flat = dr.mean(dr.select(ok, mi.Frame3f.cos_theta(bs.wo) / bs.pdf, 0.0))[0]
    glossy = dr.mean(dr.select(ok, peaked(bs.wo) / bs.pdf, 0.0))[0]
    below = mi.Vector3f(0.3, 0.1, -0.9)  # a failed sample's pdf is 0 (Mitsuba's convention)
    assert dr.max(dr.abs(bsdf.pdf(ctx, si, dr.normalize(below))))[0] == 0
    wo = mi.warp.square_to_uniform_hemisphere(mi.Point2f(rng.random(N), rng.random(N)))
    glossy_true = dr.mean(peaked(wo))[0] * 2 * np.pi
    assert flat == pytest.approx(np.pi, rel=0.01)
    assert glossy == pytest.approx(glossy_true, rel=0.02)


def test_the_lobe_moves_noise_towards_the_mirror():
    """For the peaked integrand the mixture's estimate varies less than the cosine's."""
    ctx = mi.BSDFContext()
    si, rng = lanes(0.8)
    mirror = mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z)
    s1, s2 = mi.Float(rng.random(N)), mi.Point2f(rng.random(N), rng.random(N))
    spreads = []
    for props in ({}, {"lobe_alpha": LOBE.alpha, "lobe_weight": LOBE.weight}):
        bs, _ = mi.load_dict({**LAMBERT, **props}).sample(ctx, si, s1, s2)
        g = dr.power(dr.maximum(dr.dot(bs.wo, mirror), 0.0), 20.0) * mi.Frame3f.cos_theta(bs.wo)
        spreads.append(np.std(dr.select(bs.pdf > 0, g / bs.pdf, 0.0).numpy()))
    assert spreads[1] < 0.5 * spreads[0]


@pytest.mark.parametrize(("props", "message"), [
    ({"lobe_alpha": 0.0}, "lobe_alpha must be in"), ({"lobe_alpha": 2.0}, "lobe_alpha must be in"),
    ({"lobe_alpha": -1.0, "lobe_weight": 0.0}, "lobe_alpha must be in"), ({"lobe_weight": 0.5}, "needs a lobe_alpha"),
    ({"lobe_alpha": 0.2, "lobe_weight": 1.0}, "lobe_weight")])
def test_bad_scene_lobes_are_refused(props, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict({**LAMBERT, **props})


@pytest.mark.parametrize("engine", [LocalMaterials, KernelMaterials])
def test_a_declared_lobe_is_used_and_the_image_stays_right(lobe_dir, engine):
    """The model's lobe is set on the scene's BSDF at bind, and the neural Lambertian still renders like
    the stock diffuse (the known-answer criterion of `test_known_answer`)."""
    references = [stock(simple, DIFFUSE, seed=s) for s in (1, 2, 3)]
    noise = np.mean([block_error(a, b) for a, b in ((references[0], references[1]), (references[1], references[2]),
                                                    (references[0], references[2]))])
    scene = mi.load_dict(simple(LAMBERT, {"type": "neumip_path", "max_depth": MAX_DEPTH}))
    ours = render_scene(scene, engine(lobe_dir), RenderConfig(spp=64, seed=4)).image
    bsdf = next(s.bsdf() for s in scene.shapes() if "NeuMIPBSDF" in str(s.bsdf()))
    assert bsdf.lobe == LOBE
    assert np.mean([block_error(ours, r) for r in references]) < 1.5 * noise
    assert abs(ours[..., :3].mean() / np.mean([r[..., :3].mean() for r in references]) - 1) < 0.02


def test_the_scene_overrides_the_model(model_dir, lobe_dir):
    """``lobe_weight`` 0 in the scene samples the cosine alone: the same image as a model without a lobe
    (up to float rounding of cos / pdf)."""
    def render(folder, bsdf):
        scene = mi.load_dict(simple(bsdf, {"type": "neumip_path", "max_depth": MAX_DEPTH}))
        return render_scene(scene, LocalMaterials(folder), RenderConfig(spp=16, seed=9)).image

    cosine = render(model_dir, LAMBERT)
    np.testing.assert_allclose(render(lobe_dir, {**LAMBERT, "lobe_weight": 0.0}), cosine, rtol=1e-5, atol=1e-7)
    assert np.abs(render(lobe_dir, LAMBERT) - cosine).max() > 1e-3


def test_the_scene_lobe_wins_and_an_evaluator_without_lobes_keeps_it(lobe_dir):
    """A lobe set in the scene is kept whatever the model declares; an evaluator that declares none (a
    server of an older build, a footprint recorder) leaves the BSDF's lobe as it is."""
    from neumip.client.http import FallbackEvaluator
    from neumip.client.mitsuba.shading import NeuralShading

    scene = mi.load_dict(simple({**LAMBERT, "lobe_alpha": 0.4, "lobe_weight": 0.2}, {"type": "neumip_path"}))
    NeuralShading(scene, LocalMaterials(lobe_dir))
    bsdf = next(s.bsdf() for s in scene.shapes() if "NeuMIPBSDF" in str(s.bsdf()))
    assert bsdf.lobe == C.SamplingLobe(0.4, 0.2)

    class Plain:  # a `contract.Evaluator` without `sampling`
        def materials(self):
            return ["lambert"]

        def evaluate(self, material, queries):
            return LocalMaterials(lobe_dir).evaluate(material, queries)

    scene = mi.load_dict(simple(LAMBERT, {"type": "neumip_path"}))
    bsdf = next(s.bsdf() for s in scene.shapes() if "NeuMIPBSDF" in str(s.bsdf()))
    NeuralShading(scene, Plain())
    assert bsdf.lobe is None
    NeuralShading(scene, FallbackEvaluator(Plain(), LocalMaterials(lobe_dir)))  # the primary declares none
    assert bsdf.lobe is None
    NeuralShading(scene, FallbackEvaluator(LocalMaterials(lobe_dir), Plain()))
    assert bsdf.lobe == LOBE
