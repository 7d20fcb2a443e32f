"""Query sampling: the contract's layout, the tile, the hemisphere cap, the level mixture, seeding."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.groundtruth.sampling import QuerySampling, sample_queries

N, RES = 200_000, 256


@pytest.fixture(scope="module")
def queries():
    return sample_queries(N, np.random.default_rng(0), RES, QuerySampling())


def test_queries_follow_the_contract(queries):
    assert C.as_queries(queries) is not None and queries.shape == (N, 7)
    assert queries[:, [C.U, C.V]].min() >= 0 and queries[:, [C.U, C.V]].max() < 1


def test_directions_fill_the_projected_disk_up_to_the_cap(queries):
    cap = math.sin(math.radians(QuerySampling().max_zenith_deg))
    for x, y in ((C.WI_X, C.WI_Y), (C.WO_X, C.WO_Y)):
        r2 = queries[:, x] ** 2 + queries[:, y] ** 2
        assert r2.max() <= cap**2 + 1e-6 and r2.max() > 0.98 * cap**2
        # uniform on the disk: r^2 / cap^2 is uniform, mean 1/2
        assert (r2 / cap**2).mean() == pytest.approx(0.5, abs=0.01)
        assert abs(queries[:, x].mean()) < 0.01 and abs(queries[:, y].mean()) < 0.01


def test_solid_angle_directions_are_uniform_in_cos_theta():
    cfg = QuerySampling(directions="solid_angle")
    q = sample_queries(N, np.random.default_rng(0), RES, cfg)
    cos_cap = math.cos(math.radians(cfg.max_zenith_deg))
    for x, y in ((C.WI_X, C.WI_Y), (C.WO_X, C.WO_Y)):
        cos = np.sqrt(1 - q[:, x].astype(np.float64) ** 2 - q[:, y] ** 2)
        assert cos.min() >= cos_cap - 1e-6 and cos.max() <= 1
        # cos theta uniform on [cos_cap, 1]: its CDF at the midpoint is 1/2
        assert (cos < (1 + cos_cap) / 2).mean() == pytest.approx(0.5, abs=0.01)
        # 4x the grazing queries of the projected disk beyond 80 degrees
        grazing = (cos < math.cos(math.radians(80))).mean()
        assert grazing == pytest.approx((math.cos(math.radians(80)) - cos_cap) / (1 - cos_cap), abs=0.005)
        assert abs(q[:, x].mean()) < 0.01 and abs(q[:, y].mean()) < 0.01


def test_sigma_mixture(queries):
    sigma = queries[:, C.SIGMA].astype(np.float64)
    cfg = QuerySampling()
    assert (sigma == 0).mean() == pytest.approx(1 - cfg.level_fraction - cfg.heavy_fraction, abs=0.01)
    lod = C.level_of_detail(sigma[sigma > 0], RES)
    assert lod.max() > 7.5  # every level is reached, up to the whole tile
    # mass near the finest level: the heavy tail puts P(sigma > 2 texels) = 1/4 of its share
    finest = (sigma > 0) & (sigma < 2.0 / RES)
    assert finest.mean() > cfg.heavy_fraction * 0.7


def test_seeded(queries):
    again = sample_queries(N, np.random.default_rng(0), RES, QuerySampling())
    np.testing.assert_array_equal(queries, again)


def test_bad_settings_are_rejected():
    with pytest.raises(ValueError, match="max_zenith"):
        QuerySampling(max_zenith_deg=90)
    with pytest.raises(ValueError, match="directions"):
        QuerySampling(directions="cosine")
    with pytest.raises(ValueError, match="sum"):
        QuerySampling(level_fraction=0.7, heavy_fraction=0.6)


def test_the_log_uniform_share_can_span_a_coarser_pyramids_levels():
    """levels_resolution 64 at resolution 256: the log-uniform share is over [1/64, 1] tile (a 64^2
    model's levels), the heavy tail still starts at one 256^2 texel."""
    cfg = QuerySampling(level_fraction=1.0, heavy_fraction=0.0, levels_resolution=64)
    sigma = sample_queries(20_000, np.random.default_rng(1), 256, cfg)[:, C.SIGMA].astype(np.float64)
    assert sigma.min() >= 1 / 64 * (1 - 1e-6) and sigma.max() <= 1.0
    assert np.median(np.log2(sigma * 64)) == pytest.approx(3.0, abs=0.1)  # uniform over 6 levels
    heavy = QuerySampling(level_fraction=0.0, heavy_fraction=1.0, levels_resolution=64)
    assert sample_queries(20_000, np.random.default_rng(1), 256, heavy)[:, C.SIGMA].min() < 1.01 / 256
    with pytest.raises(ValueError, match="levels_resolution"):
        QuerySampling(levels_resolution=0)


def test_sub_texel_levels_reach_finer_footprints(queries):
    """`sub_texel_levels` k (for a model with `MaterialConfig.lod_bias` k): both shares move k levels finer, so
    each level of the biased model gets the share the paper's sampling gives its own. 0 draws exactly the
    authors' queries."""
    assert QuerySampling().sub_texel_levels == 0
    k = 2
    q = sample_queries(N, np.random.default_rng(0), RES, QuerySampling(sub_texel_levels=k))
    sigma, before = q[:, C.SIGMA].astype(np.float64), queries[:, C.SIGMA].astype(np.float64)
    np.testing.assert_array_equal(q[:, [C.U, C.V, C.WI_X, C.WO_Y]], queries[:, [C.U, C.V, C.WI_X, C.WO_Y]])
    assert (sigma == 0).mean() == pytest.approx((before == 0).mean(), abs=1e-9)
    heavy = sigma[(sigma > 0) & (sigma < 2.0**-k * 1.01 / RES)]
    assert len(heavy) > 0 and sigma[sigma > 0].min() >= 2.0**-k / RES * (1 - 1e-6)
    # the biased levels of the new queries are distributed as the paper's levels of the old ones
    for lo, hi in ((0, 0.5), (0.5, 1), (1, 3), (3, 8)):
        new = ((l := C.level_of_detail(sigma[sigma > 0], RES, k)) >= lo) & (l < hi)
        old = ((m := C.level_of_detail(before[before > 0], RES)) >= lo) & (m < hi)
        assert new.mean() == pytest.approx(old.mean(), abs=0.01)
    with pytest.raises(ValueError, match="sub_texel_levels"):
        QuerySampling(sub_texel_levels=-1)
