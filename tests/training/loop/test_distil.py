"""Distilled coarse targets: Gaussians compose, the pairs are antithetic, the finer answers read the finer footprint."""

import numpy as np
import pytest
import torch

from neumip.core import contract as C
from neumip.training.loop.distil import coarse_mask, distilled_targets, mix_targets


def queries(n: int, sigma: float, seed: int = 0) -> torch.Tensor:
    q = torch.from_numpy(C.random_queries(n, seed=seed)).float()
    q[:, C.SIGMA] = sigma
    return q


def filtered_wave(q: torch.Tensor, k: int = 3) -> torch.Tensor:
    """(M, 7) -> (M, 3): cos(2 pi k u) filtered by a Gaussian of std sigma: exp(-2 pi^2 k^2 sigma^2) cos(2 pi k u)."""
    u, sigma = q[:, C.U].double(), q[:, C.SIGMA].double()
    value = torch.exp(-2 * np.pi**2 * k**2 * sigma**2) * torch.cos(2 * np.pi * k * u)
    return value[:, None].expand(-1, 3).float()


def test_the_mean_of_the_finer_filtered_answers_is_the_coarse_filtered_one():
    """A wave filtered at sigma / 4 and jittered by the rest averages to the wave filtered at sigma: 0.45 of its
    amplitude here, where the finer answers keep 0.95 and a jitter of the whole sigma would give 0.43."""
    q = queries(64, sigma=0.05)
    got = distilled_targets(lambda s: filtered_wave(s, k=4), q, samples=40_000,
                            generator=torch.Generator().manual_seed(0), finer=0.05 / 4)
    np.testing.assert_allclose(got.numpy(), filtered_wave(q, k=4).numpy(), atol=0.008)


def test_pairs_are_antithetic_so_a_linear_answer_comes_back_exactly():
    seen = []

    def linear(q):
        seen.append(q.clone())
        return torch.stack([q[:, C.U], q[:, C.V], q[:, C.SIGMA]], dim=1)

    q = queries(16, sigma=0.01)
    q[:, C.U:C.V + 1] = 0.5  # far from the tile's edge: no wrap
    got = distilled_targets(linear, q, samples=4, generator=torch.Generator().manual_seed(1), finer=0.0025)
    np.testing.assert_allclose(got[:, :2].numpy(), 0.5, atol=1e-6)
    np.testing.assert_allclose(got[:, 2].numpy(), 0.0025, rtol=1e-6)
    sub = seen[0].reshape(16, 4, C.QUERY_DIM)
    np.testing.assert_array_equal(sub[:, :, C.WI_X:].numpy(), q[:, None, C.WI_X:].expand(-1, 4, -1).numpy())
    assert float(sub[:, :, C.U].std()) > 0.003  # spread over the footprint


def test_jittered_aims_wrap_into_the_tile():
    q = queries(256, sigma=0.2)
    aims = []
    distilled_targets(lambda s: aims.append(s) or s[:, :3], q, samples=8, generator=torch.Generator().manual_seed(2),
                      finer=0.01)
    uv = aims[0][:, C.U:C.V + 1]
    assert float(uv.min()) >= 0.0 and float(uv.max()) < 1.0


@pytest.mark.parametrize("samples", [0, 3, -2])
def test_an_odd_or_empty_sample_count_is_refused(samples):
    with pytest.raises(ValueError, match="even"):
        distilled_targets(lambda s: s[:, :3], queries(4, 0.1), samples, torch.Generator(), finer=0.01)


def test_only_the_coarse_rows_change_by_their_weight():
    q = queries(6, 0.0)
    q[:, C.SIGMA] = torch.tensor([0.0, 1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4])
    coarse = coarse_mask(q, resolution=64, lod_bias=1, level=3.0)  # log2(sigma 64) + 1 >= 3
    assert coarse.tolist() == [False, False, False, True, True, True]
    target = torch.ones(6, 3)
    out = mix_targets(target, torch.full((3, 3), 3.0), coarse, weight=0.75)
    np.testing.assert_array_equal(out[:, 0].numpy(), [1, 1, 1, 2.5, 2.5, 2.5])
    assert float(target.sum()) == 18  # the data's targets are left as they were


def test_a_footprint_finer_than_the_teachers_is_answered_as_it_is():
    """sigma below `finer`: the answers read sigma itself, at the query's own aim point (in the tile)."""
    q = queries(8, sigma=0.001)
    got = distilled_targets(lambda s: s[:, :3], q, samples=2, generator=torch.Generator(), finer=0.01)
    np.testing.assert_allclose(got[:, :2].numpy(), np.mod(q[:, :2].numpy(), 1.0), atol=1e-6)
    np.testing.assert_array_equal(got[:, 2].numpy(), q[:, C.SIGMA].numpy())


def test_the_config_names_the_steps_that_distil_and_refuses_bad_settings():
    from neumip.training.loop.config import TrainConfig

    config = TrainConfig(steps=100, distil=8, distil_start=0.25)
    assert [config.distilling(s) for s in (0, 24, 25, 99)] == [False, False, True, True]
    assert not TrainConfig(steps=100).distilling(99)
    for bad in ({"distil": 3}, {"distil": -2}, {"distil": 8, "distil_start": 1.0}, {"distil": 8, "distil_weight": 0.0},
                {"distil": 8, "distil_texels": 0.0}):
        with pytest.raises(ValueError, match="distil"):
            TrainConfig(steps=100, **bad)
