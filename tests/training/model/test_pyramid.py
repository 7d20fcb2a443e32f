"""Unit tests of the pure lookup math (training/model/pyramid.py, training/model/offset.py)."""

import math

import numpy as np
import pytest
import torch

from neumip.core import contract as C
from neumip.core.config import MaterialConfig
from neumip.training.model.offset import parallax_shift
from neumip.training.model.material import NeuMIPMaterial
from neumip.training.model.pyramid import level_of_detail, mip_atlas, mip_levels, pyramid_lookup, texture_lookup


def test_level_of_detail_matches_contract():
    sigma = np.array([-1.0, 0.0, 1e-9, 1 / 256, 2 / 256, 3 / 256, 0.5, 1.0, 1e9], np.float32)
    want = C.level_of_detail(sigma, 256)
    got = level_of_detail(torch.from_numpy(sigma), 256).numpy()
    np.testing.assert_allclose(got, want, atol=1e-6)
    assert got[0] == 0 and got[3] == 0 and got[4] == pytest.approx(1) and got[-1] == 8


def test_texel_centres_return_texels_exactly():
    tex = torch.randn(8, 8, 3)
    iy, ix = torch.meshgrid(torch.arange(8), torch.arange(8), indexing="ij")
    u, v = (ix.flatten() + 0.5) / 8, (iy.flatten() + 0.5) / 8
    out = texture_lookup(tex, u, v)
    torch.testing.assert_close(out, tex.reshape(64, 3))


def test_lookup_wraps_with_period_one():
    tex = torch.randn(4, 4, 2)
    u = torch.rand(100)
    v = torch.rand(100)
    base = texture_lookup(tex, u, v)
    # float32 keeps ~1e-7 relative precision: at |u| = 1000 positions move by ~6e-5 tile units
    for shift, atol in ((-3.0, 1e-5), (1.0, 1e-5), (1000.0, 3e-3)):
        shifted = texture_lookup(tex, u + shift, v - shift)
        torch.testing.assert_close(shifted, base, atol=atol, rtol=0)


def test_seam_blends_opposite_edges():
    tex = torch.zeros(4, 4, 1)
    tex[:, 0] = 1.0  # first column
    # u = 0 is halfway between the last column's centre and the first column's centre
    out = texture_lookup(tex, torch.tensor([0.0]), torch.tensor([0.5]))
    assert out.item() == pytest.approx(0.5)


def test_pyramid_interpolates_linearly_between_levels():
    cfg = MaterialConfig(resolution=4, channels=1)
    sizes = cfg.level_sizes()
    atlas = torch.cat([torch.full((s * s, 1), float(i)) for i, s in enumerate(sizes)])
    sigma = torch.tensor([2.0 ** (lod - 2) for lod in (0.0, 0.5, 1.0, 1.25, 2.0, 5.0)])
    out = pyramid_lookup(atlas, cfg, torch.rand(6), torch.rand(6), sigma)[:, 0]
    torch.testing.assert_close(out, torch.tensor([0.0, 0.5, 1.0, 1.25, 2.0, 2.0]))


def test_parallax_shift_follows_view_direction():
    theta = math.radians(45)
    du, dv = parallax_shift(torch.tensor([0.1]), torch.tensor([math.sin(theta)]), torch.tensor([0.0]), 0.6)
    assert du.item() == pytest.approx(0.1 * math.tan(theta), rel=1e-5) and dv.item() == 0
    # grazing: wo_z is clamped at min_cos, so the shift stays bounded
    du, _ = parallax_shift(torch.tensor([0.1]), torch.tensor([1.0]), torch.tensor([0.0]), 0.6)
    assert du.item() == pytest.approx(0.1 / 0.6, rel=1e-5)


def test_lod_bias_raises_every_footprints_level():
    """`MaterialConfig.lod_bias` 2: a footprint of one texel's std reads level 2, a quarter texel the finest;
    torch and the contract agree, and the coarsest level still ends the range."""
    sigma = np.array([0.0, 0.1 / 256, 0.25 / 256, 0.5 / 256, 1 / 256, 4 / 256, 64 / 256, 1.0], np.float32)
    want = C.level_of_detail(sigma, 256, 2)
    np.testing.assert_allclose(want, [0, 0, 0, 1, 2, 4, 8, 8], atol=1e-6)
    np.testing.assert_allclose(level_of_detail(torch.from_numpy(sigma), 256, 2).numpy(), want, atol=1e-6)
    assert C.sigma_for_level(2, 256, 2) == pytest.approx(1 / 256)
    cfg = MaterialConfig(resolution=4, channels=1, lod_bias=1)
    atlas = torch.cat([torch.full((s * s, 1), float(i)) for i, s in enumerate(cfg.level_sizes())])
    out = pyramid_lookup(atlas, cfg, torch.rand(3), torch.rand(3), torch.tensor([0.125, 0.25, 0.5]))[:, 0]
    torch.testing.assert_close(out, torch.tensor([0.0, 1.0, 2.0]))
    assert cfg.base_pyramid() is None and MaterialConfig(base=8, lod_bias=1).base_pyramid().lod_bias == 1
    assert MaterialConfig(relief=8, lod_bias=1).relief_pyramid().lod_bias == 1
    assert "lod_bias" not in MaterialConfig().to_json()
    assert MaterialConfig.from_json(MaterialConfig(lod_bias=2).to_json()).lod_bias == 2
    for bad in (-1, 9, 1.5):
        with pytest.raises(ValueError, match="lod_bias"):
            MaterialConfig(lod_bias=bad)


def test_mip_levels_are_the_means_of_their_two_by_two_in_a_fixed_order():
    """Each coarser level of `mip_levels` is ((a + b) + (c + d)) / 4 of the texels under it: the mean, in the one
    float32 order the export derives too; `mip_atlas` stacks them finest first as a pyramid's atlas."""
    texture = torch.randn(8, 8, 3) * 10
    levels = mip_levels(texture)
    assert [lvl.shape[0] for lvl in levels] == [8, 4, 2, 1] and levels[0] is texture
    t = texture.numpy()
    want = ((t[0::2, 0::2] + t[0::2, 1::2]) + (t[1::2, 0::2] + t[1::2, 1::2])) * np.float32(0.25)
    np.testing.assert_array_equal(levels[1].numpy(), want)
    torch.testing.assert_close(levels[-1][0, 0], texture.mean((0, 1)), rtol=1e-5, atol=1e-5)
    atlas = mip_atlas(texture)
    cfg = MaterialConfig(resolution=8, channels=3)
    assert atlas.shape == (cfg.atlas_rows(), 3)
    np.testing.assert_array_equal(atlas[cfg.level_starts()[2]:cfg.level_starts()[3]].numpy(), levels[2].reshape(-1, 3).numpy())


def test_offset_mip_reads_the_offset_at_the_footprint():
    """With `MaterialConfig.offset_mip` a footprint of level 1 reads the offset texture's 2 x 2 means: a pattern of
    zero mean in every 2 x 2 added to the texture leaves its answers as they were. The paper's offset reads the
    finest level at every footprint, so the same pattern moves them."""
    checker = torch.tensor([[1.0, -1.0], [-1.0, 1.0]]).repeat(4, 4)[:, :, None] * 8.0  # (8, 8, 1)
    q = torch.zeros(256, 7)
    q[:, C.U], q[:, C.V] = torch.rand(256), torch.rand(256)
    q[:, C.SIGMA] = 2.0 / 8  # level 1 of an 8^2 pyramid
    q[:, C.WO_X] = 0.5
    moved = {}
    for mip in (False, True):
        torch.manual_seed(0)
        material = NeuMIPMaterial(MaterialConfig(resolution=8, channels=2, offset_mip=mip), init_std=1.0)
        with torch.no_grad():
            material.offset_mlp[-1].bias.fill_(0.5)
            before = material(q)
            material.offset_texture.add_(checker)
            moved[mip] = (material(q) - before).abs().max().item()
    assert moved[True] < 1e-6 < 1e-3 < moved[False]
    assert MaterialConfig(offset_mip=True).offset_pyramid().channels == MaterialConfig().offset_channels
    without = MaterialConfig(offset=False, offset_mip=True)  # a recipe's value, over --no-offset: nothing to read
    assert without.offset_pyramid() is None and "offset_mip" not in without.to_json()
