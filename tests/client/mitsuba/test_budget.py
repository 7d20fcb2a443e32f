"""`neumip budget`: the footprints it traces are those a real render sends, and the levels, finest
level that matters and recommended resolution follow from them."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.client.cli import main
from neumip.client.mitsuba.budget import material_budget, trace_footprints
from neumip.core.config import MaterialConfig
from neumip.training.export.graph import build_onnx, random_weights, save_onnx
from neumip.client.mitsuba.bsdf import mi
from neumip.client.mitsuba.render import RenderConfig, render_scene

from .recording import Recording
from .scenes import facing_plane


def test_footprints_are_those_of_a_render(model_dir):
    """The preview answers equal the `lambert` model's (albedo 0.5), so the paths and every query's
    sigma - first hits and bounces - are the render's, bit for bit (a dict scene)."""
    scene = facing_plane(uv_scale=3.0)
    scene["integrator"]["max_depth"] = 4
    scene["floor"] = {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, -1]).scale(4),
                      "bsdf": {"type": "neumip", "material": "lambert", "uv_scale": 0.5}}
    recording = Recording(model_dir)
    render_scene(mi.load_dict(scene), recording, RenderConfig(spp=4, seed=3))
    rendered = np.concatenate([q[:, C.SIGMA] for q in recording.calls])
    traced = trace_footprints(mi.load_dict(scene), spp=4, seed=3)
    assert list(traced) == ["lambert"]
    np.testing.assert_array_equal(traced["lambert"], rendered)
    assert len(np.unique(traced["lambert"])) > 100  # bounces and two uv scales: many footprints


def test_levels_finest_level_and_recommendation():
    resolution = 64
    # 0.05 % of queries at level 0.5, 10 % at 2.5, the rest at 4.25
    sigma = np.concatenate([np.full(5, C.sigma_for_level(0.5, resolution)),
                            np.full(1000, C.sigma_for_level(2.5, resolution)),
                            np.full(8995, C.sigma_for_level(4.25, resolution))])
    b = material_budget("m", sigma, resolution, coverage=0.999)
    assert b.queries == 10_000
    assert b.level_range == (0, 5)
    np.testing.assert_allclose(b.histogram, [0.0005, 0, 0.1, 0, 0.8995, 0, 0])
    assert b.finest_level == 2  # 99.95 % read level 2 or coarser; 10 % + ... do not make 3
    assert b.recommended_resolution == 16 and not b.too_coarse  # level 2.5 of 64: 1 / sigma = 11.3
    strict = material_budget("m", sigma, resolution, coverage=1.0)
    assert strict.finest_level == 0 and strict.recommended_resolution == 64 and not strict.too_coarse
    close = material_budget("m", np.full(100, 0.25 / 64), resolution)  # 4x magnified
    assert close.too_coarse and close.recommended_resolution == 256 and close.magnified == 1.0
    assert close.histogram[0] == 1.0 and close.finest_level == 0
    on_maps = material_budget("m", np.full(100, 0.25 / 64), resolution, maps_resolution=256)  # base / relief maps
    assert not on_maps.too_coarse and on_maps.recommended_resolution == 256 and on_maps.maps_resolution == 256
    assert material_budget("m", np.full(100, 0.25 / 64), resolution, maps_resolution=128).too_coarse
    # samples that each read 1/8 of their pixel: the levels read follow the queries, the resolution
    # needed follows the pixel footprint (8x the queries' sigma)
    shared = material_budget("m", sigma / 8, resolution, coverage=0.999, sample_share=1 / 8)
    assert shared.finest_level == 0 and shared.histogram[0] > 0.1
    assert shared.recommended_resolution == b.recommended_resolution and shared.magnified == b.magnified
    with pytest.raises(ValueError, match="coverage"):
        material_budget("m", sigma, resolution, coverage=0.0)


def test_cli_closeup_is_too_coarse_and_far_view_trims(tmp_path, capsys):
    models = "models"
    plain = tmp_path / "plain"  # a 64^2 model that reads no maps
    config = MaterialConfig(resolution=64)
    save_onnx(build_onnx(config, random_weights(config)), plain / "yarn.onnx")
    assert main(["budget", "scenes/closeup.xml", "--models", str(plain), "--spp", "1", "-D", "resx=128",
                 "-D", "resy=128", "--json"]) == 0
    close = json.loads(capsys.readouterr().out)["materials"]
    assert [m["material"] for m in close] == ["yarn"]
    assert close[0]["too_coarse"] and close[0]["recommended_resolution"] > 64 and close[0]["maps_resolution"] == 0
    plot = tmp_path / "budget.png"
    assert main(["budget", "scenes/demo.xml", "--models", models, "--spp", "2", "-D", "resx=64",
                 "-D", "resy=64", "--plot", str(plot)]) == 0
    out = capsys.readouterr().out
    assert plot.stat().st_size > 1000 and "finest level that matters" in out
    # a small image at 1 spp reads coarse levels; at the scene's 64 spp each sample reads 1/8 of the
    # pixel footprint: 3 levels finer
    levels = {}
    for render_spp in ("1", "64"):
        assert main(["budget", "scenes/demo.xml", "--models", models, "--spp", "2", "-D", "resx=64",
                     "-D", "resy=64", "--render-spp", render_spp, "--json"]) == 0
        levels[render_spp] = {m["material"]: m for m in json.loads(capsys.readouterr().out)["materials"]}
    far = levels["1"]
    assert sorted(far) == ["foam", "rock", "turtle", "yarn"]
    for name, m in far.items():
        assert m["finest_level"] >= 1 and not m["too_coarse"]
        assert m["trimmed_bytes"] < m["model_bytes"]
        assert m["pyramid_levels"]["pyramid"] == m["finest_level"] and m["offset_bytes"] == 0  # nothing kept whole
        for pyramid in ("base_maps", "relief_heights", "offset_texture"):  # the shipped maps: 256^2, as the latents
            assert m["pyramid_levels"][pyramid] == m["finest_level"], pyramid
        assert math.isclose(sum(m["histogram"]), 1.0, rel_tol=1e-9)
        assert levels["64"][name]["finest_level"] == max(0, m["finest_level"] - 3)


@pytest.mark.parametrize("maps", [(0, 0, False), (32, 32, False), (16, 16, False), (8, 0, False), (16, 16, True),
                                  (32, 32, True, True)],
                         ids=["latents", "finer", "as-fine", "coarser", "offset-mip", "lean"])
def test_trimmed_bytes_count_every_pyramid(tmp_path, maps):
    """The budget's estimate of a trimmed model (every pyramid cut at the same footprint, the tables shared by
    pyramids of one resolution) is the size `neumip trim` writes, to a few hundred bytes of protobuf framing."""
    from neumip.client.mitsuba.budget import model_facts, offset_size, pyramid_levels, trimmed_size
    from neumip.training.export.lod import pyramids
    from neumip.training.export.trim import trim_model

    lean = len(maps) > 3  # float16 textures, a base whose F0 is the same in every texel (stored once)
    config = MaterialConfig(resolution=16, base=maps[0], relief=maps[1], relief_steps=2, offset_mip=maps[2],
                            half_textures=lean)
    weights = random_weights(config)
    if lean:
        weights[W.BASE][:, 3:6] = 0.04
    model = build_onnx(config, weights)
    facts = model_facts(save_onnx(model, tmp_path / "m.onnx"))
    offset = next(i for i in model.graph.initializer if i.name == "offset_texture")
    if config.offset_mip:  # a pyramid: trimmed as the others, nothing kept whole
        assert offset_size(facts) == 0
    else:
        assert 0 < offset.ByteSize() < offset_size(facts) < 2 * offset.ByteSize()  # the texture and its table
    for k in (1, 2, 4):
        trimmed = trim_model(model, k)
        assert abs(trimmed_size(facts, k) - trimmed.ByteSize()) < 400
        assert pyramid_levels(facts, k) == {p.texture: config.pyramid_finest_level(p.config, k) for p in pyramids(config)}
        again = model_facts(save_onnx(trimmed, tmp_path / f"t{k}.onnx"))
        assert abs(trimmed_size(again, 4) - trim_model(model, 4).ByteSize()) < 400  # from a trimmed model on


def test_cli_refuses_bad_input(capsys):
    assert main(["budget", "scenes/demo.xml", "--coverage", "1.5"]) != 0
    assert "--coverage" in capsys.readouterr().err
    assert main(["budget", "scenes/demo.xml", "--render-spp", "0"]) != 0
    assert "--render-spp" in capsys.readouterr().err
    assert main(["budget", "scenes", "--spp", "1"]) != 0
    assert "directory" in capsys.readouterr().err


def test_a_foreign_graph_is_a_clean_row_not_a_traceback(tmp_path, capsys, checkerboard):
    """A graph without neumip metadata (allowed by the contract: scenes/checkerboard.py) has no pyramid:
    its row says so and refers to the default resolution, as for a material without a model file (it
    ended in a bare KeyError: 'resolution'). A corrupt model file is one line (the model-file reader's)."""
    import onnx

    onnx.save(checkerboard(), str(tmp_path / "checker.onnx"))
    args = ["budget", "scenes/closeup.xml", "-D", "material=checker", "--models", str(tmp_path), "--spp", "1",
            "-D", "resx=32", "-D", "resy=32"]
    assert main(args) == 0
    assert "a foreign graph of" in capsys.readouterr().out
    assert main([*args, "--json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)["materials"]
    assert row["foreign_graph"] and row["trimmed_bytes"] is None and row["resolution"] == 64
    assert row["model_bytes"] == (tmp_path / "checker.onnx").stat().st_size
    (tmp_path / "checker.onnx").write_bytes(b"not an onnx file")
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "checker.onnx: cannot load ONNX model" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
