"""Progressive blur: schedule, wrap-around, both 1-D paths agree, per-level division."""

import math

import pytest
import torch

from neumip.training.loop.blur import _blur_rows, blur_pyramid, blur_sigma, blur_texture, circulant, gaussian_kernel, schedule_end
from neumip.training.loop.config import TrainConfig


def test_schedule_halves_and_ends():
    cfg = TrainConfig(blur_start=8.0, blur_half_life=100.0, blur_min=0.2)
    assert blur_sigma(0, cfg) == 8.0
    assert blur_sigma(100, cfg) == pytest.approx(4.0)
    assert blur_sigma(300, cfg) == pytest.approx(1.0)
    end = schedule_end(cfg)
    assert end == math.ceil(100 * math.log2(8 / 0.2))
    assert blur_sigma(end - 1, cfg) >= 0.2 and blur_sigma(end, cfg) == 0.0


def test_blur_keeps_constant_and_mean_and_wraps():
    torch.manual_seed(0)
    tex = torch.randn(16, 16, 3)
    out = blur_texture(tex, 1.5)
    torch.testing.assert_close(out.mean((0, 1)), tex.mean((0, 1)), atol=1e-5, rtol=0)
    const = torch.full((8, 8, 2), 0.7)
    torch.testing.assert_close(blur_texture(const, 5.0), const)
    # a delta at the corner spreads symmetrically across the seam
    delta = torch.zeros(16, 16, 1)
    delta[0, 0, 0] = 1.0
    b = blur_texture(delta, 1.0)[..., 0]
    assert b[0, 1] == pytest.approx(float(b[0, 15]), rel=1e-5) and b[1, 0] == pytest.approx(float(b[15, 0]), rel=1e-5)
    assert b[0, 1] > 0.05 and b[0, 8] < 1e-3


@pytest.mark.parametrize("sigma", [0.5, 2.0])
def test_convolution_path_equals_circulant(sigma, monkeypatch):
    torch.manual_seed(1)
    rows = torch.randn(5, 32)
    k = gaussian_kernel(sigma, torch.float32, torch.device("cpu"))
    want = rows @ circulant(32, k).T
    got = _blur_rows(rows, k)  # radius < 32: the circular-convolution path
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    tex = torch.randn(32, 32, 3)
    by_matrix = blur_texture(tex, sigma)
    monkeypatch.setattr("neumip.training.loop.blur.MATRIX_MAX_SIZE", 16)
    torch.testing.assert_close(blur_texture(tex, sigma), by_matrix, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


def test_wide_kernel_on_small_level_is_folded():
    k = gaussian_kernel(8.0, torch.float32, torch.device("cpu"))  # radius 24 on a 4-texel level
    m = circulant(4, k)
    torch.testing.assert_close(m.sum(1), torch.ones(4))
    tex = torch.randn(4, 4, 2)
    out = blur_texture(tex, 8.0)  # nearly flat: the mean everywhere
    assert (out - tex.mean((0, 1))).abs().max() < 0.05


def test_pyramid_sigma_divided_per_level_and_skipped():
    torch.manual_seed(2)
    levels = [torch.randn(s, s, 2) for s in (16, 8, 4, 2, 1)]
    out = blur_pyramid(levels, 0.8, sigma_min=0.2)
    torch.testing.assert_close(out[1], blur_texture(levels[1], 0.4))
    assert out[3] is levels[3] and out[4] is levels[4]  # 0.1 < 0.2: skipped; 1 x 1: identity
    assert not torch.allclose(out[0], levels[0])


def test_blur_is_differentiable():
    tex = torch.randn(8, 8, 3, requires_grad=True)
    blur_texture(tex, 1.0).square().sum().backward()
    assert tex.grad is not None and torch.isfinite(tex.grad).all()
