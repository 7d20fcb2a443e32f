"""Data set generation: complete, seeded, resumable after an interruption, metadata, shipped materials."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neumip.groundtruth.dataset import DatasetError, open_dataset
from neumip.groundtruth.description import find_description, library_names
from neumip.groundtruth.generate import GenerateSettings, generate


def small(name: str, resolution: int = 16):
    desc = find_description(name)
    desc.resolution = resolution
    return desc


SETTINGS = dict(queries=2500, spp=2, seed=7, chunk=1000)


class Interrupt(Exception):
    pass


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    return generate(small("turtle"), tmp_path_factory.mktemp("ref") / "data", GenerateSettings(**SETTINGS))


def test_generated_data_set_is_complete_with_metadata(reference):
    data = open_dataset(reference.path)
    assert len(data) == 2500 and data.queries.shape == (2500, 7) and data.rgb.shape == (2500, 3)
    assert data.meta["material"]["name"] == "turtle" and data.meta["material"]["procedural"]["generator"] == "turtle"
    gen = data.meta["generator"]
    assert (gen["spp"], gen["seed"], gen["queries"], gen["resolution"]) == (2, 7, 2500, 16)
    assert gen["tracer"]["max_depth"] == 4 and "lanes" not in gen["tracer"]
    assert np.isfinite(data.rgb).all() and data.rgb.min() >= 0 and data.rgb.mean() > 0.01
    assert not (reference.path / "progress.json").exists()


def test_same_seed_same_data_and_resume_after_interruption(tmp_path, reference):
    out = tmp_path / "data"
    calls = []

    def stop_after_two_chunks(done: int, total: int) -> None:
        calls.append(done)
        if done >= 2000:
            raise Interrupt

    with pytest.raises(Interrupt):
        generate(small("turtle"), out, GenerateSettings(**SETTINGS), stop_after_two_chunks)
    with pytest.raises(DatasetError, match="incomplete|not a data set"):
        open_dataset(out)  # the partial data set never looks complete
    resumed = []
    data = generate(small("turtle"), out, GenerateSettings(**SETTINGS), lambda d, t: resumed.append(d))
    assert resumed[0] == 2000 and resumed[-1] == 2500  # started at the first unfinished chunk
    np.testing.assert_array_equal(data.queries, reference.queries)
    np.testing.assert_array_equal(data.rgb, reference.rgb)


def test_resuming_with_other_settings_is_refused(tmp_path):
    out = tmp_path / "data"
    with pytest.raises(Interrupt):
        generate(small("foam"), out, GenerateSettings(**SETTINGS), lambda d, t: (_ for _ in ()).throw(Interrupt))
    with pytest.raises(DatasetError, match="other settings"):
        generate(small("foam"), out, GenerateSettings(**{**SETTINGS, "spp": 4}))


def test_other_seed_other_data(tmp_path, reference):
    data = generate(small("turtle"), tmp_path / "d", GenerateSettings(**{**SETTINGS, "seed": 8}))
    assert not np.array_equal(data.queries, reference.queries)


@pytest.mark.parametrize("name", library_names())
def test_every_shipped_material_generates(tmp_path, name):
    data = generate(small(name, 32), tmp_path / name, GenerateSettings(queries=500, spp=2, chunk=500))
    assert len(data) == 500 and np.isfinite(data.rgb).all() and data.rgb.min() >= 0
    if name == "flat":
        np.testing.assert_allclose(data.rgb, 0.5 / math.pi, rtol=2e-4)


def test_default_query_count_follows_texels():
    settings = GenerateSettings()
    assert settings.query_count(small("yarn", 64)) == 256 * 64 * 64
    assert GenerateSettings(resolution=32).query_count(small("yarn", 64)) == 256 * 32 * 32


def test_default_directions_keep_older_data_sets_valid():
    """Data sets made before `directions` existed identify themselves without it: the default
    ('disk') leaves it out of the metadata, another kind names itself."""
    from neumip.groundtruth.sampling import QuerySampling

    desc = find_description("flat")
    disk = GenerateSettings(queries=64, seed=0).to_meta(desc)
    assert "directions" not in disk["sampling"]
    solid = GenerateSettings(queries=64, seed=0, sampling=QuerySampling(directions="solid_angle")).to_meta(desc)
    assert solid["sampling"]["directions"] == "solid_angle"
    assert {k: v for k, v in solid["sampling"].items() if k != "directions"} == disk["sampling"]
    assert "sub_texel_levels" not in disk["sampling"]  # likewise the footprints' reach (a lod-biased model's data)
    finer = GenerateSettings(queries=64, seed=0, sampling=QuerySampling(sub_texel_levels=2)).to_meta(desc)
    assert finer["sampling"] == {**disk["sampling"], "sub_texel_levels": 2}


def test_tiled_margin_follows_the_sampled_directions():
    """Directions sampled beyond the tiling's zenith widen its margin (a shadow ray towards an 88-degree light must
    cross the neighbouring tiles' geometry, not leave it); the default sampling keeps the default margin, so older
    data sets' metadata are unchanged."""
    from neumip.groundtruth.mesh import TilingConfig, margin_tiles
    from neumip.groundtruth.sampling import QuerySampling

    assert GenerateSettings().tiling == TilingConfig()
    grazing = GenerateSettings(sampling=QuerySampling(max_zenith_deg=88.0))
    assert grazing.tiling.max_zenith_deg == 88.0
    assert margin_tiles(0.12, 256, grazing.tiling) == pytest.approx(0.12 * math.tan(math.radians(88.0)))
    assert margin_tiles(0.12, 256, grazing.tiling) > 2.5 * margin_tiles(0.12, 256, TilingConfig())


def test_coarse_footprints_get_their_own_samples(tmp_path, reference):
    """`coarse_spp`: the same queries; those of footprints from `coarse_texels` texels get more samples, the rest keep
    the bits they have without it; the metadata says so, and a data set without it stays valid."""
    settings = GenerateSettings(**{**SETTINGS, "coarse_spp": 8, "coarse_texels": 2.0})
    data = generate(small("turtle"), tmp_path / "d", settings)
    coarse = reference.queries[:, 2] * 16 >= 2.0
    assert 0.1 < coarse.mean() < 0.9
    np.testing.assert_array_equal(data.queries, reference.queries)
    np.testing.assert_array_equal(data.rgb[~coarse], reference.rgb[~coarse])
    assert not np.array_equal(data.rgb[coarse], reference.rgb[coarse]) and np.isfinite(data.rgb).all()
    gen = data.meta["generator"]
    assert (gen["spp"], gen["coarse_spp"], gen["coarse_texels"]) == (2, 8, 2.0)
    assert "coarse_spp" not in reference.meta["generator"]
    with pytest.raises(ValueError, match="coarse_spp"):
        GenerateSettings(spp=16, coarse_spp=16)


def test_coarse_samples_are_averaged_with_the_first_ones():
    """A coarse query's estimate is the mean of all its `coarse_spp` samples: its `spp` first ones (the bits it has
    without the option) and the `coarse_spp - spp` of a pass of their own."""
    from neumip.groundtruth.generate import trace_chunk

    class Tracer:  # each pass answers its sample count, so the mean says how the passes were weighed
        def estimate(self, queries, spp, seed):
            return np.full((len(queries), 3), float(spp), np.float32)

    settings = GenerateSettings(queries=4096, spp=2, coarse_spp=8, coarse_texels=2.0, chunk=4096)
    queries, rgb = trace_chunk(Tracer(), settings, 16, 0, 4096)
    coarse = queries[:, 2] * 16 >= 2.0
    assert 0 < coarse.sum() < len(coarse)
    np.testing.assert_array_equal(rgb[~coarse], 2.0)
    np.testing.assert_allclose(rgb[coarse], (2 * 2 + 6 * 6) / 8)
