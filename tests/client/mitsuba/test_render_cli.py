"""`neumip render`: writes PNG/EXR, several materials in one scene, clear errors, no partial files."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from neumip.client import cli
from neumip.engines.local import LocalMaterials
from neumip.client.mitsuba.bsdf import mi
from neumip.client.mitsuba.render import RenderConfig, RenderError, load_scene, pass_plan, pass_seed, render_scene

from .scenes import write_xml


def test_pass_seeds_of_nearby_renders_are_disjoint():
    """Renders of seeds 0, 1, ... share no pass (the report's two seeds of a view estimate its noise from their
    difference); the first pass keeps the render's own seed."""
    seeds = {s: [pass_seed(s, i) for i in range(8)] for s in range(64)}
    assert all(passes[0] == s for s, passes in seeds.items())
    every = [x for passes in seeds.values() for x in passes]
    assert len(set(every)) == len(every)
    assert all(0 <= x < 2**32 for x in every)


def test_pass_plan_bounds_lanes_and_sums_to_spp():
    assert pass_plan(100, 64, 10_000) == [64]
    plan = pass_plan(512 * 512, 64, 2**21)
    assert sum(plan) == 64 and max(plan) * 512 * 512 <= 2**21 and len(plan) == 8
    assert pass_plan(10**9, 3, 10) == [1, 1, 1]
    with pytest.raises(ValueError):
        pass_plan(10, 0, 10)


@pytest.mark.parametrize("suffix", [".png", ".exr"])
def test_cli_renders_two_materials_in_passes(model_dir, tmp_path, capsys, suffix):
    out = tmp_path / f"out{suffix}"
    rc = cli.main(["render", write_xml(tmp_path), "-o", str(out), "--models", str(model_dir),
                   "--spp", "8", "--max-lanes", str(32 * 32 * 4)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert f"wrote {out.resolve()}" in printed and "2 pass(es)" in printed and "queries" in printed
    image = np.array(mi.Bitmap(str(out)))
    assert image.shape[:2] == (32, 32) and image.mean() > 0


def test_each_material_gets_at_most_two_calls_per_bounce(model_dir, tmp_path):
    scene = load_scene(write_xml(tmp_path), spp="4")
    result = render_scene(scene, LocalMaterials(model_dir), RenderConfig(spp=4))
    stats = result.stats
    assert set(stats.per_material) == {"lambert", "rand16"}
    assert stats.calls <= 2 * 2 * 5  # two materials, groups and single queries per bounce (max_depth 6)
    assert stats.queries == sum(stats.per_material.values()) > 32 * 32


def test_unknown_material_is_a_clear_error(model_dir, tmp_path, capsys):
    out = tmp_path / "out.png"
    rc = cli.main(["render", write_xml(tmp_path, b="velvet"), "-o", str(out), "--models", str(model_dir)])
    assert rc == 2
    assert "velvet" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("engine", ["kernel", "onnxruntime"])
def test_corrupt_models_are_reported_as_failed_before_rendering(model_dir, tmp_path, capsys, monkeypatch, engine):
    """A scene's corrupt model file fails the render at its start, named with its reason (as the
    server reports it at start-up), not as a failed pass mid-render; nothing is written."""
    import shutil

    from neumip.client.mitsuba import render as R

    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(model_dir / "lambert.onnx", models / "lambert.onnx")
    (models / "rand16.onnx").write_bytes((model_dir / "rand16.onnx").read_bytes()[:500])  # truncated
    passes = []
    monkeypatch.setattr(R, "_render_pass", lambda *args: passes.append(args))
    out = tmp_path / "out.png"
    rc = cli.main(["render", write_xml(tmp_path), "-o", str(out), "--models", str(models), "--engine", engine])
    assert rc == 2 and not out.exists() and not passes
    err = capsys.readouterr().err
    assert f"1 of the scene's materials failed to load from {models} (rand16: rand16.onnx" in err


def test_unreachable_server_is_a_clear_error(tmp_path, capsys):
    out = tmp_path / "out.png"
    with socket.socket() as bound:  # a port that is bound but not listening: connections are refused
        bound.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{bound.getsockname()[1]}"
        rc = cli.main(["render", write_xml(tmp_path), "-o", str(out), "--server", url])
    assert rc == 2
    assert "unreachable" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == [tmp_path / "scene.xml"]


def test_evaluator_failure_mid_render_writes_nothing(model_dir, tmp_path):
    class Failing(LocalMaterials):
        calls = 0

        def evaluate(self, material, queries):
            Failing.calls += 1
            if Failing.calls == 3:
                raise RuntimeError("evaluator died")
            return super().evaluate(material, queries)

    with pytest.raises(RenderError, match="evaluator died") as info:
        render_scene(load_scene(write_xml(tmp_path)), Failing(model_dir), RenderConfig(spp=4))
    assert isinstance(info.value.__cause__, RuntimeError)


def test_renders_of_nearby_seeds_share_no_pass(model_dir, tmp_path, monkeypatch):
    """Renders of seeds 0 and 1, four passes each, draw on eight different pass seeds (`pass_seed`): with
    ``seed + i`` they shared three, and the difference of two such renders saw a quarter of their noise."""
    from neumip.client.mitsuba import render as R

    real, seeds = R._render_pass, []

    def recording(scene, integrator, spp, seed):
        seeds.append(seed)
        return real(scene, integrator, spp, seed)

    monkeypatch.setattr(R, "_render_pass", recording)
    scene = load_scene(write_xml(tmp_path))
    for seed in (0, 1):
        assert render_scene(scene, LocalMaterials(model_dir), RenderConfig(spp=4, seed=seed, max_lanes=1)).passes == 4
    assert seeds[0] == 0 and seeds[4] == 1 and len(set(seeds)) == 8


def test_neural_scene_needs_neumip_path(model_dir, tmp_path):
    scene = load_scene(write_xml(tmp_path))
    with pytest.raises(RenderError, match="neumip_path"):
        render_scene(scene, LocalMaterials(model_dir), integrator=mi.load_dict({"type": "path"}))


def test_bad_output_suffix(tmp_path, capsys):
    assert cli.main(["render", write_xml(tmp_path), "-o", str(tmp_path / "a.jpg")]) == 2
    assert ".png or .exr, got a.jpg" in capsys.readouterr().err


def test_a_folder_as_scene_says_so(tmp_path, capsys):
    write_xml(tmp_path)
    assert cli.main(["render", str(tmp_path), "-o", str(tmp_path / "a.png")]) == 2
    assert f"{tmp_path} is a directory: give a Mitsuba XML scene file (XML files there: scene.xml)" in \
        capsys.readouterr().err


def test_bsdf_validates_properties():
    with pytest.raises(Exception, match="'material' property"):
        mi.load_dict({"type": "neumip"})
    with pytest.raises(Exception, match="uv_scale must be > 0"):
        mi.load_dict({"type": "neumip", "material": "m", "uv_scale": -1.0})


def test_bad_server_url_and_fallback_without_server(tmp_path, capsys):
    scene = write_xml(tmp_path)
    assert cli.main(["render", scene, "-o", str(tmp_path / "a.png"), "--server", "localhost:8000"]) == 2
    assert "http://" in capsys.readouterr().err
    assert cli.main(["render", scene, "-o", str(tmp_path / "a.png"), "--fallback"]) == 2
    assert "--fallback needs --server" in capsys.readouterr().err
