"""The energy table: its cells' weights, its gains by level and half vector, and its fit."""

import math

import numpy as np
import pytest
import torch

from neumip.core import contract as C
from neumip.core.config import MaterialConfig
from neumip.core.contract import random_queries
from neumip.training.model.base import half_direction, lift
from neumip.core.weights import energy_rows
from neumip.training.model.energy import ENERGY_RANGE, azimuth_coordinate, corners, energy_gain, fit_energy

CFG = MaterialConfig(resolution=16, lod_bias=1, energy_bins=5)


def columns(q: np.ndarray):
    t = torch.from_numpy(q)
    return t[:, C.SIGMA], t[:, C.WI_X:C.WI_Y + 1], t[:, C.WO_X:C.WO_Y + 1]


def test_a_querys_weights_over_the_cells_sum_to_one_and_at_most_eight_are_not_zero():
    index, weight = corners(CFG, *columns(random_queries(5000, seed=1)))
    assert index.shape == weight.shape == (5000, 8)
    assert index.min() >= 0 and index.max() < (CFG.levels + 1) * 25
    assert torch.allclose(weight.sum(1), torch.ones(5000)) and (weight >= 0).all()


def test_the_gain_is_the_cell_of_the_querys_level_half_vector_and_light_elevation():
    """A query at level l exactly reads row l; wi = wo = the normal (h_z = 1, the light overhead) reads the cell of
    the first half-vector bin and the last elevation bin; grazing wi and wo side by side (h 90 degrees from the
    normal, the light at the horizon) the last half-vector bin and the first elevation bin; in between the gains
    interpolate."""
    bins = CFG.energy_bins
    table = torch.arange((CFG.levels + 1) * bins**2 * 3, dtype=torch.float32).view(-1, 3)
    for level in range(CFG.levels + 1):
        sigma = torch.tensor([2.0 ** (level - CFG.lod_bias) / CFG.resolution] * 2)
        w = torch.tensor([[0.0, 0.0], [1.0, 0.0]])
        got = energy_gain(table, CFG, sigma, w, w)
        overhead, grazing = level * bins**2 + bins - 1, level * bins**2 + (bins - 1) * bins  # (l, 0, B - 1), (l, B - 1, 0)
        assert torch.allclose(got[0], table[overhead]), (level, got)
        assert torch.allclose(got[1], table[grazing], atol=1e-3), (level, got)
    half = torch.tensor([2.0 ** (1.5 - CFG.lod_bias) / CFG.resolution])  # between levels 1 and 2: their mean
    got = energy_gain(table, CFG, half, torch.zeros(1, 2), torch.zeros(1, 2))
    assert torch.allclose(got[0], (table[bins**2 + bins - 1] + table[2 * bins**2 + bins - 1]) / 2, atol=1e-3)


def test_a_fit_gives_back_a_gain_that_is_the_same_everywhere_and_one_where_no_query_reaches():
    q = random_queries(20000, seed=2)
    q[:, C.SIGMA] = 2.0 ** (2 - CFG.lod_bias) / CFG.resolution  # every query at level 2
    answers = torch.rand(20000, 3, dtype=torch.float64) + 0.1
    gain = torch.tensor([1.3, 0.8, 1.1], dtype=torch.float64)
    table = fit_energy(CFG, torch.from_numpy(q), answers, answers * gain, prior=0.0)
    level = table.view(CFG.levels + 1, 25, 3)
    reached = fit_energy(CFG, torch.from_numpy(q), answers, torch.ones_like(answers), prior=0.0).view_as(level)[2] != 1
    got = level[2][reached[:, 0]]  # the cells the queries reach
    assert len(got) >= 10 and torch.allclose(got, gain.float().expand(len(got), 3), atol=1e-5)
    assert torch.isnan(table).sum() == 0 and torch.all(level[[0, 4]] == 1.0)  # levels none reach: 1
    prior = fit_energy(CFG, torch.from_numpy(q), answers, answers * gain)  # the prior pulls towards 1
    prior = prior.view_as(level)[2]
    assert torch.all((prior - 1) * (level[2] - 1) >= 0) and torch.all((prior - 1).abs() <= (level[2] - 1).abs())


def test_a_fit_is_bounded_and_leaves_out_non_finite_rows():
    q = torch.from_numpy(random_queries(4000, seed=3))
    answers = torch.full((4000, 3), 0.01, dtype=torch.float64)
    targets = torch.full((4000, 3), 100.0, dtype=torch.float64)
    targets[::7] = math.nan
    table = fit_energy(CFG, q, answers, targets, prior=0.0)
    assert torch.isfinite(table).all() and float(table.max()) == pytest.approx(ENERGY_RANGE[1])


def test_energy_bins_needs_two_bins_and_the_relu_head():
    for bad in (dict(energy_bins=1), dict(energy_bins=-2), dict(energy_bins=4, head="yuv")):
        with pytest.raises(ValueError, match="energy_bins"):
            MaterialConfig(**bad)
    assert "energy_bins" not in MaterialConfig().to_json() and '"energy_bins": 4' in MaterialConfig(energy_bins=4).to_json()


AZ = MaterialConfig(resolution=16, lod_bias=1, energy_bins=5, energy_azimuths=8)


def test_with_azimuths_a_query_reads_sixteen_cells_whose_weights_sum_to_one():
    index, weight = corners(AZ, *columns(random_queries(5000, seed=4)))
    assert index.shape == weight.shape == (5000, 16)
    assert index.min() >= 0 and index.max() < (AZ.levels + 1) * 25 * 8
    assert torch.allclose(weight.sum(1), torch.ones(5000)) and (weight >= 0).all()


def test_the_azimuth_turns_with_the_half_vector_and_wraps_without_a_jump():
    """The pseudo-angle is 0, 1, 2, 3 (times A / 4) along +x, +y, -x, -y, grows with the angle, and the gain is
    continuous across +x, where it wraps from A to 0."""
    angles = torch.linspace(-math.pi + 1e-3, math.pi - 1e-3, 721)
    wi = 0.6 * torch.stack([torch.cos(angles), torch.sin(angles)], 1)  # wi = wo: h along wi
    a = azimuth_coordinate(half_direction(lift(wi), lift(wi)), 8)
    quarter = {0.0: 0.0, math.pi / 2: 2.0, math.pi - 1e-3: 4.0, -math.pi / 2: 6.0}
    for angle, want in quarter.items():
        w = 0.6 * torch.tensor([[math.cos(angle), math.sin(angle)]])
        assert float(azimuth_coordinate(half_direction(lift(w), lift(w)), 8)) == pytest.approx(want, abs=1e-2), angle
    turned = torch.remainder(a - a[0], 8.0)  # from -pi on: increasing by the angle
    assert torch.all(turned[1:] >= turned[:-1])
    table = torch.rand((AZ.levels + 1) * 25 * 8, 3) + 0.5
    sigma = torch.full((len(wi),), 2.0 ** (3 - AZ.lod_bias) / AZ.resolution)
    gain = energy_gain(table, AZ, sigma, wi, wi)
    assert (gain[1:] - gain[:-1]).abs().max() < 0.05  # 721 steps around the circle: no jump, +x included
    assert gain.std(0).min() > 0.05  # and it does change with the azimuth


def test_a_fit_gives_back_a_gain_that_changes_with_the_azimuth_and_one_gain_at_the_normal():
    q = random_queries(200000, seed=5)
    q[:, C.SIGMA] = 2.0 ** (3 - AZ.lod_bias) / AZ.resolution  # level 3
    sig, wi, wo = columns(q)
    h_y = (wi[:, 1] + wo[:, 1]).double()  # the half vector's y has the sign of wi_y + wo_y
    answers = torch.rand(len(q), 3, dtype=torch.float64) + 0.1
    gain = torch.where(h_y >= 0, 1.5, 0.7)[:, None]
    table = fit_energy(AZ, torch.from_numpy(q), answers, answers * gain, prior=0.0).view(AZ.levels + 1, 5, 5, 8, 3)
    # node 2 (+y) reads only queries with y >= 0 and node 6 (-y) only y < 0, in every half-vector bin but the first
    assert torch.allclose(table[3, 1:, 1:, 2], torch.tensor(1.5), atol=1e-4)
    assert torch.allclose(table[3, 1:, 1:, 6], torch.tensor(0.7), atol=1e-4)
    normal = table[3, 0]  # the first half-vector bin: one gain for every azimuth, between the two
    assert torch.equal(normal, normal[:, :1].expand_as(normal))
    assert torch.all((normal[1:] > 0.7) & (normal[1:] < 1.5))


def test_energy_azimuths_needs_a_table_and_two_bins():
    for bad in (dict(energy_azimuths=4), dict(energy_bins=4, energy_azimuths=1), dict(energy_bins=4, energy_azimuths=-2)):
        with pytest.raises(ValueError, match="energy_azimuths"):
            MaterialConfig(**bad)
    assert "energy_azimuths" not in MaterialConfig(energy_bins=4).to_json()
    assert '"energy_azimuths": 8' in AZ.to_json()


def test_a_fit_in_chunks_gives_the_table_of_one_pass(monkeypatch):
    from neumip.training.model import energy

    q = torch.from_numpy(random_queries(5000, seed=7))
    answers = torch.rand(5000, 3, dtype=torch.float64) + 0.1
    targets = answers * (torch.rand(5000, 3, dtype=torch.float64) + 0.5)
    whole = fit_energy(AZ, q, answers, targets)
    monkeypatch.setattr(energy, "FIT_CHUNK", 999)
    assert torch.allclose(fit_energy(AZ, q, answers, targets), whole, rtol=1e-6)


def test_a_luminance_table_holds_one_gain_a_cell_the_luminances_ratio():
    lum_cfg = MaterialConfig(resolution=16, lod_bias=1, energy_bins=5, energy_azimuths=8, energy_luminance=True)
    q = torch.from_numpy(random_queries(20000, seed=8))
    answers = torch.rand(20000, 3, dtype=torch.float64) + 0.1
    gain = torch.tensor([1.5, 1.0, 0.5], dtype=torch.float64)  # the channels' gains differ; their luminance is one
    table = fit_energy(lum_cfg, q, answers, answers * gain, prior=0.0)
    assert table.shape == (energy_rows(lum_cfg), 1)
    lum = torch.tensor(C.LUMINANCE, dtype=torch.float64)
    want = (answers * gain) @ lum / (answers @ lum)  # each query's luminance ratio: the cells' lie between its extremes
    reached = table[:, 0] != 1
    assert reached.sum() > 10 and bool(((table[reached, 0] >= want.min() - 1e-5) & (table[reached, 0] <= want.max() + 1e-5)).all())
    assert energy_gain(table, lum_cfg, *columns(q.numpy())).shape == (20000, 1)
    with pytest.raises(ValueError, match="energy_luminance"):
        MaterialConfig(energy_luminance=True)
    assert '"energy_luminance": true' in lum_cfg.to_json() and "energy_luminance" not in AZ.to_json()
