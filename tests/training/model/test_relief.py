"""The relief stage: its height pyramid, the march's known answers (a flat floor, the zenith, a ridge that
occludes what lies behind it), agreement with a fine march, and a material that reads where the ray lands."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.config import RELIEF_MIN_COS, MaterialConfig
from neumip.training.model.material import NeuMIPMaterial
from neumip.training.model.relief import (
    march_direction,
    relief_depth,
    relief_heights,
    relief_resolution,
    relief_shift,
)

from .geometry import geometry


def pyramid_of(height: np.ndarray) -> tuple[torch.Tensor, MaterialConfig]:
    size = height.shape[0]
    levels = relief_heights(geometry(height), size)
    return torch.from_numpy(np.concatenate([lvl.reshape(-1, 1) for lvl in levels])), MaterialConfig(
        resolution=size, channels=1, offset=False)


def rays(n: int, seed: int, zenith_max: float = 70.0) -> tuple[torch.Tensor, ...]:
    rng = np.random.default_rng(seed)
    theta, phi = np.radians(rng.uniform(0, zenith_max, n)), rng.uniform(0, 2 * np.pi, n)
    wo = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi)], 1)
    u, v = rng.uniform(0, 1, (2, n))
    as_tensor = lambda a: torch.tensor(a, dtype=torch.float32)
    return as_tensor(u), as_tensor(v), torch.zeros(n), as_tensor(wo)


def test_the_height_pyramid_is_the_map_averaged_level_by_level():
    height = -np.random.default_rng(0).uniform(0, 0.1, (16, 16))
    levels = relief_heights(geometry(height), 16)
    assert [lvl.shape for lvl in levels] == [(s, s, 1) for s in (16, 8, 4, 2, 1)]
    np.testing.assert_allclose(levels[0][..., 0], height, rtol=1e-6)
    np.testing.assert_allclose(levels[-1][0, 0, 0], height.mean(), rtol=1e-5)
    assert relief_resolution(geometry(np.zeros((12, 12)))) == 16
    assert relief_resolution(geometry(np.zeros((1, 1)))) == 0  # a flat material: nothing to march


def test_a_ray_meets_a_flat_floor_at_its_depth_and_a_zenith_ray_does_not_move():
    heights, pyramid = pyramid_of(np.full((8, 8), -0.05))
    u, v, sigma, wo = rays(2000, 1)
    t = relief_depth(heights, pyramid, u, v, sigma, wo, steps=4)
    torch.testing.assert_close(t, torch.full_like(t, 0.05), atol=1e-7, rtol=0)
    config = MaterialConfig(resolution=8, relief=8, offset=False)
    du, dv = relief_shift(heights, config, u, v, sigma, torch.zeros_like(wo))
    assert not du.any() and not dv.any()
    du, dv = relief_shift(heights, config, u, v, sigma, wo)  # the floor's parallax: -0.05 wo_xy / wo_z
    wo_z = torch.sqrt(1 - (wo * wo).sum(1))
    torch.testing.assert_close(du, -0.05 * wo[:, 0] / wo_z, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(dv, -0.05 * wo[:, 1] / wo_z, atol=1e-6, rtol=1e-5)


def test_the_march_agrees_with_a_fine_march_and_grazing_rays_are_clamped():
    x = (np.arange(64) + 0.5) / 64
    height = 0.02 * (np.cos(2 * np.pi * x)[None, :] * np.cos(4 * np.pi * x)[:, None] - 1)  # smooth, 0.04 deep
    heights, pyramid = pyramid_of(height)
    u, v, sigma, wo = rays(4000, 2)
    fine = relief_depth(heights, pyramid, u, v, sigma, wo, steps=256)
    coarse = relief_depth(heights, pyramid, u, v, sigma, wo, steps=16)
    assert (coarse - fine).abs().mean() < 2e-4 and (coarse - fine).abs().max() < 0.01
    assert ((fine >= 0) & (fine <= 0.04 + 1e-6)).all()
    grazing = torch.tensor([[0.9999, 0.0]])
    assert march_direction(grazing)[0, 0] == pytest.approx(0.9999 / RELIEF_MIN_COS, rel=1e-6)


def test_a_ridge_hides_what_lies_behind_it():
    """A ray aimed just before a full-height ridge meets the ridge's side, not the floor behind it."""
    height = np.full((64, 64), -0.1)
    height[:, 32:36] = 0.0  # a wall 4 texels thick along v
    heights, pyramid = pyramid_of(height)
    wo = torch.tensor([[-0.7071, 0.0]])  # the ray runs towards +u as it descends
    u = torch.tensor([30.0 / 64])
    t = relief_depth(heights, pyramid, u, torch.tensor([0.5]), torch.zeros(1), wo, steps=32)
    assert float(u + t * 1.0) < 36 / 64  # it stopped at the wall (t d_x = t), not past it on the floor
    open_ = relief_depth(heights, pyramid, torch.tensor([10.0 / 64]), torch.tensor([0.5]), torch.zeros(1), wo, steps=32)
    assert float(open_) == pytest.approx(0.1, abs=0.1 / 32)  # no wall in the way: the floor


def test_a_material_with_a_relief_reads_where_the_ray_lands():
    torch.manual_seed(0)
    height = 0.05 * (np.random.default_rng(3).standard_normal((16, 16)) - 3)
    height -= height.max()
    config = MaterialConfig(resolution=8, relief=16, offset=False)
    material, flat = NeuMIPMaterial(config), NeuMIPMaterial(MaterialConfig(resolution=8, offset=False))
    material.set_maps(W.RELIEF, relief_heights(geometry(height), 16))
    flat.load_state_dict({k: v for k, v in material.state_dict().items() if k != W.RELIEF})
    q = torch.from_numpy(C.random_queries(500, seed=2))
    du, dv = relief_shift(material.relief_heights, config, q[:, C.U], q[:, C.V], q[:, C.SIGMA], q[:, C.WO_X:C.WO_Y + 1])
    moved = q.clone()
    moved[:, C.U] += du
    moved[:, C.V] += dv
    with torch.no_grad():
        torch.testing.assert_close(material(q), flat(moved))
        assert not torch.equal(material(q), flat(q))
    with pytest.raises(ValueError, match="relief_heights of"):
        material.set_maps(W.RELIEF, relief_heights(geometry(height[:8, :8]), 8))


def test_a_batch_marched_once_answers_as_the_material_marching_it():
    """Training marches each data row once (`landed_positions`, its heights are fixed) and evaluates the
    batch with `landed=True`: the same answers, bit for bit, as the material's own march."""
    from neumip.training.model.relief import landed_positions

    torch.manual_seed(1)
    height = 0.05 * (np.random.default_rng(4).standard_normal((16, 16)) - 3)
    height -= height.max()
    config = MaterialConfig(resolution=8, relief=16)
    levels = relief_heights(geometry(height), 16)
    material = NeuMIPMaterial(config)
    material.set_maps(W.RELIEF, levels)
    q = C.random_queries(3000, seed=6)
    moved = q.copy()
    moved[:, C.U:C.V + 1] = landed_positions(levels, config, q, chunk=1000)
    with torch.no_grad():
        assert torch.equal(material(torch.from_numpy(moved), landed=True), material(torch.from_numpy(q)))
