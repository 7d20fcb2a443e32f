"""The classical base: its maps' pyramid, its BSDF's known answers, the horizon's shadow, and a new
material answering the base."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.config import BASE_CHANNELS, BASE_HORIZONS, MaterialConfig
from neumip.training.model.base import (base_answer, base_maps, base_resolution, energy_pairs, frame_inputs,
                                        keep_energy, light_visibility, visibility)
from neumip.training.model.material import NeuMIPMaterial
from .geometry import geometry


def test_a_flat_material_s_maps_are_its_colours_and_no_slopes_or_horizons():
    levels = base_maps(geometry(np.zeros((8, 8))), 8)
    assert [lvl.shape for lvl in levels] == [(s, s, BASE_CHANNELS) for s in (8, 4, 2, 1)]
    for lvl in levels:
        np.testing.assert_allclose(lvl[..., 0:3], np.broadcast_to([0.6, 0.4, 0.2], lvl.shape[:2] + (3,)), rtol=1e-6)
        np.testing.assert_allclose(lvl[..., 3:6], 0.04, rtol=1e-6)  # 0.08 x specular 0.5
        np.testing.assert_allclose(lvl[..., 8], 0.5**4, rtol=1e-5)
        assert not lvl[..., 6:8].any() and not lvl[..., 9:].any()
    metal = base_maps(geometry(np.zeros((4, 4)), metallic=1.0), 4)[0]
    assert not metal[..., 0:3].any()
    np.testing.assert_allclose(metal[..., 3:6], np.broadcast_to([0.6, 0.4, 0.2], (4, 4, 3)), rtol=1e-6)


def test_bumps_widen_the_coarse_lobe_and_cast_horizons():
    """A coarse texel over bumps keeps their slopes' variance in alpha^2 (LEAN), and a ridge raises the
    horizon seen from beside it."""
    x = np.arange(16) / 16
    height = 0.05 * np.sin(2 * np.pi * 4 * x)[None, :].repeat(16, 0)  # ridges along v
    levels = base_maps(geometry(height), 16)
    assert levels[-1][0, 0, 8] > levels[0][..., 8].max() + 0.1  # the 1 x 1 level: a wider lobe
    assert levels[0][..., 9:].max() > 0.3 and base_resolution(geometry(height)) == 16


def _energy(levels: list[np.ndarray], level: int, pairs: int = 64) -> np.ndarray:
    """Per texel of `level`: its summed answer, over the sum of its finest texels' (the same random pairs)."""
    res, size = levels[0].shape[0], levels[level].shape[0]
    wi, wo = energy_pairs(res * res * pairs, seed=1)  # other pairs than keep_energy's, drawn alike
    def sums(lv):
        f = res // lv.shape[0]
        rows = np.repeat(np.repeat(lv.astype(np.float64), f, 0), f, 1).reshape(res * res, -1)
        out = base_answer(torch.from_numpy(rows).repeat_interleave(pairs, 0), wi, wo, "none").sum(1)
        return out.reshape(size, res // size, size, res // size, pairs).sum((1, 3, 4)).numpy()
    return sums(levels[level]) / sums(levels[0])


def test_keeping_energy_brings_a_glossy_bumpy_coarse_level_to_its_texels_mean_and_leaves_a_flat_one():
    """`MaterialConfig.base_energy`: glossy bumps change energy when prefiltered (mean slopes, LEAN widening); the
    rescaled coarse levels answer about as their finest texels do on average; level 0 and a flat material stay."""
    x = np.arange(32) / 32
    bumps = 0.03 * np.sin(2 * np.pi * 4 * x)[None, :] * np.cos(2 * np.pi * 4 * x)[:, None]
    geo = geometry(bumps, roughness=0.3)  # at 0.15 (alpha^2 5e-4) 8 pairs a texel are too few to tell
    plain, kept = base_maps(geo, 32), base_maps(geo, 32, energy=True)
    np.testing.assert_array_equal(kept[0], plain[0])
    for level in (3, 4, 5):  # 512 to 8192 of its pairs a texel
        np.testing.assert_array_equal(kept[level][..., 6:], plain[level][..., 6:])  # slopes, lobe, horizons stay
        before, after = _energy(plain, level), _energy(kept, level)
        assert abs(before.mean() - 1) > 0.03, before.mean()  # prefiltering moved its energy
        assert abs(after.mean() - 1) < 0.5 * abs(before.mean() - 1), (before.mean(), after.mean())
    flat = geometry(np.zeros((8, 8)))
    for a, b in zip(base_maps(flat, 8), base_maps(flat, 8, energy=True)):
        np.testing.assert_allclose(b, a, rtol=1e-6)
    assert len(keep_energy(plain[:1])) == 1
    with pytest.raises(ValueError, match="base_energy needs a base"):
        MaterialConfig(resolution=16, base_energy=True)


def test_a_homogeneous_bsdf_material_has_no_base():
    with pytest.raises(ValueError, match="principled maps"):
        base_resolution(geometry(np.zeros((4, 4)), bsdf={"type": "diffuse"}))


def test_at_normal_incidence_a_dielectric_base_answers_albedo_over_pi_plus_its_lobe():
    maps = torch.tensor([[0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.25] + [0.0] * BASE_HORIZONS])
    zero = torch.zeros(1, 2)
    torch.testing.assert_close(base_answer(maps, zero, zero), torch.full((1, 3), 0.5 / math.pi))  # F0 = 0: no lobe
    maps[0, 3:6] = 0.04
    want = 0.5 / math.pi + 1 / (math.pi * 0.25) * 0.04 / 4  # + D G F / (4 cos_o): D = 1 / (pi alpha^2), G = 1
    assert float(base_answer(maps, zero, zero)[0, 0]) == pytest.approx(want, rel=1e-5)


def test_a_light_below_the_horizon_of_its_azimuth_is_shadowed():
    horizons = torch.zeros(2, BASE_HORIZONS)
    horizons[:, 0] = 0.8  # a wall towards +u only
    wi = torch.tensor([[0.85, 0.0], [0.0, 0.85]])  # towards +u, towards +v; wi_z = 0.527
    wi_z = torch.sqrt(1 - (wi * wi).sum(1, keepdim=True))
    lit = visibility(horizons, wi, wi_z)
    assert float(lit[0]) == 0.0 and float(lit[1]) == 1.0
    zenith = visibility(torch.full((1, BASE_HORIZONS), 0.9), torch.zeros(1, 2), torch.ones(1, 1))
    assert float(zenith[0]) == 1.0  # straight above clears every horizon


def test_without_the_terminator_a_facet_facing_a_grazing_light_answers_its_own_irradiance():
    """`MaterialConfig.terminator` off: a lit facet tilted towards a light 85 degrees from the plane's normal
    answers cos(n, wi) / wi_z times a flat texel's diffuse answer, as the real geometry's lit faces do; with S(g) it
    answers about 1 / n_z times it (the soft normal map's bound), a quarter of that here."""
    tilt = math.radians(20.0)
    maps = torch.zeros(2, BASE_CHANNELS)
    maps[:, 0:3] = 0.5
    maps[:, 8] = 1.0  # alpha^2 = 1: a lobe too wide to matter
    maps[1, 6] = -math.tan(tilt)  # slopes dh/du < 0: the normal leans towards +u
    zenith = math.radians(85.0)
    wi = torch.tensor([[math.sin(zenith), 0.0]] * 2)
    wo = torch.zeros(2, 2)
    maps[:, 3:6] = 0.0  # F0 = 0: the diffuse part alone
    flat, tilted = base_answer(maps, wi, wo, terminator="none")[:, 0]
    irradiance = math.cos(zenith - tilt) / math.cos(zenith)
    assert float(tilted / flat) == pytest.approx(irradiance, rel=1e-3)  # (float32 near the horizon)
    soft = base_answer(maps, wi, wo)[:, 0]
    assert float(soft[0]) == pytest.approx(float(flat), rel=1e-6)  # a flat texel: g = 1, S(g) = 1
    assert float(soft[1] / flat) < 0.3 * irradiance
    assert float(base_answer(maps, wi, wo, terminator="specular")[1, 0] / flat) == pytest.approx(irradiance, rel=1e-3)
    maps[:, 3:6] = 0.04  # a lobe: "specular" softens it as "all" does and leaves the diffuse term as "none" does
    no_colour = maps.clone()
    no_colour[:, 0:3] = 0.0  # the lobe alone
    answer = {kind: base_answer(maps, wi, wo, terminator=kind) for kind in ("all", "specular", "none")}
    lobe = {kind: base_answer(no_colour, wi, wo, terminator=kind) for kind in ("all", "specular", "none")}
    torch.testing.assert_close(lobe["specular"], lobe["all"])
    assert float(lobe["none"][1, 0]) > 2 * float(lobe["all"][1, 0])
    torch.testing.assert_close(answer["specular"] - lobe["specular"], answer["none"] - lobe["none"])
    assert "terminator" not in MaterialConfig(base=8).to_json()
    with pytest.raises(ValueError, match="needs a base"):
        MaterialConfig(terminator="none")
    assert MaterialConfig.from_json(MaterialConfig(base=8, terminator="specular").to_json()).terminator == "specular"
    with pytest.raises(ValueError, match="terminator must be one of"):
        MaterialConfig(base=8, terminator="off")


def test_a_new_material_with_a_base_answers_the_base():
    """The decoder's last layer starts at zero: exp(0) times the base, plus 0."""
    from neumip.training.model.pyramid import pyramid_lookup

    torch.manual_seed(0)
    height = 0.03 * np.random.default_rng(0).standard_normal((16, 16))
    config = MaterialConfig(resolution=8, base=16, offset=False)
    material = NeuMIPMaterial(config)
    material.set_maps(W.BASE, base_maps(geometry(height), 16))
    q = torch.from_numpy(C.random_queries(500, seed=2))
    with torch.no_grad():
        got = material(q)
        maps = pyramid_lookup(material.base_maps, config.base_pyramid(), q[:, C.U], q[:, C.V], q[:, C.SIGMA])
        want = torch.relu(base_answer(maps, q[:, C.WI_X:C.WI_Y + 1], q[:, C.WO_X:C.WO_Y + 1]))
    assert torch.isfinite(got).all() and got.std() > 0
    torch.testing.assert_close(got, want)
    with pytest.raises(ValueError, match="base_maps of"):
        material.set_maps(W.BASE, base_maps(geometry(height), 8))


def test_the_local_frame_is_the_plane_s_on_a_flat_texel_and_turns_with_the_normal():
    """`MaterialConfig.local_frame`'s inputs: on a flat texel wi and wo as they are (z from the unit length); on a
    tilted one an orthonormal frame whose z is the normal, so a direction along the normal reads (0, 0, 1), and
    lengths and the angle between wi and wo are kept."""
    features = torch.zeros(3, BASE_CHANNELS)
    features[1, 6:8] = torch.tensor([0.5, -0.3])  # slopes: n = normalize(-0.5, 0.3, 1)
    features[2, 6:8] = torch.tensor([-2.0, 1.5])
    wi = torch.tensor([[0.3, -0.4], [0.1, 0.2], [-0.6, 0.5]])
    wo = torch.tensor([[-0.2, 0.1], [0.5, 0.5], [0.0, -0.7]])
    out = frame_inputs(features, wi, wo)
    z = lambda w: torch.sqrt(1 - (w * w).sum(1, keepdim=True))
    wi3, wo3 = torch.cat([wi, z(wi)], 1), torch.cat([wo, z(wo)], 1)
    torch.testing.assert_close(out[0], torch.cat([wi3[0], wo3[0]]))
    li, lo = out[:, :3], out[:, 3:]
    torch.testing.assert_close(li.norm(dim=1), torch.ones(3))
    torch.testing.assert_close(lo.norm(dim=1), torch.ones(3))
    torch.testing.assert_close((li * lo).sum(1), (wi3 * wo3).sum(1))
    n = torch.tensor([[-0.5, 0.3, 1.0]]) / math.sqrt(0.25 + 0.09 + 1.0)
    along = frame_inputs(features[1:2], n[:, :2], n[:, :2])
    torch.testing.assert_close(along, torch.tensor([[0.0, 0.0, 1.0, 0.0, 0.0, 1.0]]), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="needs a base"):
        MaterialConfig(local_frame=True)


def test_the_visibility_input_is_the_base_s_own_shadow_test():
    """`MaterialConfig.visibility_input`: the decoder reads V(wi), 0 for a light below its azimuth's horizon, 1 above
    it, as the base's answer is shadowed; a material with it answers the base until trained."""
    features = torch.zeros(2, BASE_CHANNELS)
    features[:, 9] = 0.8  # a wall towards +u only
    wi = torch.tensor([[0.85, 0.0], [0.0, 0.85]])
    torch.testing.assert_close(light_visibility(features, wi), torch.tensor([[0.0], [1.0]]))
    config = MaterialConfig(resolution=8, base=16, offset=False, visibility_input=True, local_frame=True)
    assert W.mlps(config)[W.DECODER][0] == W.mlps(replace(config, visibility_input=False))[W.DECODER][0] + 1
    material = NeuMIPMaterial(config)
    material.set_maps(W.BASE, base_maps(geometry(np.zeros((16, 16))), 16))
    queries = torch.tensor([[0.3, 0.6, 0.0, 0.2, 0.1, -0.3, 0.2]])
    want = base_answer(material.base_maps[:1].expand(1, -1), queries[:, 3:5], queries[:, 5:7], "all")
    torch.testing.assert_close(material(queries), want)
    with pytest.raises(ValueError, match="needs a base"):
        MaterialConfig(visibility_input=True)
