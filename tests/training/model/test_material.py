"""The material's output heads: the YUV head's known answers, its gradient, and its ONNX export; the coarse levels'
decoder."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from neumip.core import contract as C
from neumip.core.contract import random_queries
from neumip.core import head
from neumip.core.config import MaterialConfig
from neumip.training.export.graph import build_onnx, constant_weights, weights_from_state
from neumip.training.model.material import NeuMIPMaterial
from neumip.training.model.pyramid import level_of_detail
from neumip.training.loop.train import init_output

FLAT = 0.5 / math.pi
"""MBTF of the flat Lambertian plane of albedo 0.5 (the shipped `flat` material)."""


def test_yuv_matrices_are_inverse_and_grey_has_no_chroma():
    np.testing.assert_allclose(head.YUV_TO_RGB @ head.RGB_TO_YUV, np.eye(3), atol=1e-12)
    y, u, v = head.RGB_TO_YUV @ np.ones(3)
    assert y == pytest.approx(1.0) and abs(u) < 1e-4 and abs(v) < 1e-4


def test_yuv_head_answers_the_flat_plane_when_started_at_its_colour():
    """init_output sets the yuv head to the data's mean: with the last layer's weights at 0 the
    material answers albedo/pi for every query (exp(log1p(x)) - 1 = x, shadow mask exactly 1)."""
    torch.manual_seed(0)
    material = NeuMIPMaterial(MaterialConfig(resolution=8, head="yuv"))
    init_output(material, np.full((16, 3), FLAT))
    with torch.no_grad():
        material.decoder[-1].weight.zero_()
        out = material(torch.from_numpy(random_queries(500, seed=1)))
    np.testing.assert_allclose(out.numpy(), FLAT, rtol=1e-5)
    assert material.decoder[-1].out_features == 6


def test_yuv_head_formula_by_hand():
    """Decoder outputs (y, u, v, s1, s2, s3) -> RGB = (exp(YUV_TO_RGB yuv) - 1) * (0.1 + sigmoid(s))."""
    material = NeuMIPMaterial(MaterialConfig(resolution=1, head="yuv", offset=False, layers=1))
    yuv, shadow = np.array([0.3, 0.05, -0.02]), np.array([0.0, 2.0, -2.0])
    with torch.no_grad():
        material.decoder[-1].weight.zero_()
        material.decoder[-1].bias.copy_(torch.tensor(np.concatenate([yuv, shadow]), dtype=torch.float32))
        out = material(torch.from_numpy(random_queries(3, seed=0)))[0].numpy()
    want = np.expm1(head.YUV_TO_RGB @ yuv) * (0.1 + 1 / (1 + np.exp(-shadow)))
    np.testing.assert_allclose(out, want, rtol=1e-5)
    # a strongly negative colour is clamped to 0 (exp - 1 >= -1, times a mask > 0)
    with torch.no_grad():
        material.decoder[-1].bias[:3] = torch.tensor([-5.0, 0.0, 0.0])
        assert float(material(torch.from_numpy(random_queries(3, seed=0))).max()) == 0.0


def test_yuv_head_trains_towards_a_bright_glint():
    """One gradient step on a glint 50x the mean raises the prediction (the head is not stuck)."""
    torch.manual_seed(0)
    material = NeuMIPMaterial(MaterialConfig(resolution=4, head="yuv", offset=False))
    init_output(material, np.full((4, 3), 0.1))
    q = torch.from_numpy(random_queries(64, seed=2))
    before = material(q).mean().detach()
    loss = ((torch.log1p(material(q)) - math.log1p(5.0)) ** 2).mean()
    loss.backward()
    with torch.no_grad():
        for p in material.parameters():
            p -= 0.05 * p.grad
    with torch.no_grad():
        assert float(material(q).mean()) > float(before)


@pytest.mark.parametrize("config", [MaterialConfig(resolution=8, head="yuv"),
                                    MaterialConfig(resolution=4, head="yuv", offset=False, layers=2)])
def test_yuv_head_export_matches_torch(config, assert_parity, edge_queries):
    import onnxruntime as ort

    torch.manual_seed(3)
    material = NeuMIPMaterial(config).eval()
    queries = np.concatenate([random_queries(300, seed=4), edge_queries(config.resolution)])
    with torch.no_grad():
        want = material(torch.from_numpy(queries)).numpy()
    weights = weights_from_state(material.state_dict(), config)
    session = ort.InferenceSession(build_onnx(config, weights).SerializeToString())
    got = session.run(None, {session.get_inputs()[0].name: queries})[0]
    assert_parity(got, want)


def test_constant_weights_of_the_yuv_head_answer_the_colour():
    import onnxruntime as ort

    config = MaterialConfig(resolution=4, head="yuv")
    session = ort.InferenceSession(build_onnx(config, constant_weights(config, [FLAT, 0.2, 0.0])).SerializeToString())
    got = session.run(None, {session.get_inputs()[0].name: random_queries(50, seed=5)})[0]
    np.testing.assert_allclose(got, np.broadcast_to([FLAT, 0.2, 0.0], got.shape), atol=1e-6)


def test_unknown_head_is_refused():
    with pytest.raises(ValueError, match="head must be one of"):
        MaterialConfig(head="srgb")


def test_the_coarse_decoder_answers_from_its_level_on_and_the_first_below():
    """`MaterialConfig.coarse_decoder` K: level K and finer answer with the first decoder alone, K + 1 and coarser
    with the second alone, and between them a blend; the second starts as the first does (zero last layer with a
    base) and is its own weights."""
    torch.manual_seed(0)
    config = MaterialConfig(resolution=32, coarse_decoder=2)
    two = NeuMIPMaterial(config, init_std=0.5)
    first, second = NeuMIPMaterial(replace(config, coarse_decoder=0)), NeuMIPMaterial(replace(config, coarse_decoder=0))
    state = {k: v for k, v in two.state_dict().items() if not k.startswith("coarse_decoder.")}
    first.load_state_dict(state)
    second.load_state_dict({**state, **{k.replace("coarse_decoder.", "decoder."): v
                                        for k, v in two.state_dict().items() if k.startswith("coarse_decoder.")}})
    q = torch.from_numpy(random_queries(3000, seed=2))
    lod = level_of_detail(q[:, C.SIGMA], config.resolution)
    with torch.no_grad():
        answers = [m(q) for m in (two, first, second)]
    fine, coarse, between = lod <= 2, lod >= 3, (lod > 2.2) & (lod < 2.8)
    assert fine.sum() > 100 and coarse.sum() > 100 and between.sum() > 10
    torch.testing.assert_close(answers[0][fine], answers[1][fine], rtol=0, atol=0)
    torch.testing.assert_close(answers[0][coarse], answers[2][coarse])  # out + 1 (c - out): c up to rounding
    assert not torch.allclose(answers[1][between], answers[2][between])  # two decoders, their own weights
    with_base = NeuMIPMaterial(replace(config, base=32))
    assert all(float(d[-1].weight.abs().sum()) == 0.0 for d in with_base.decoders()) and len(with_base.decoders()) == 2
    with pytest.raises(ValueError, match="coarse_decoder"):
        MaterialConfig(resolution=32, coarse_decoder=5)
