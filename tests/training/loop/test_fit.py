"""`neumip fit` and texture-map materials run from another folder: a real 8^2 material from PNG maps,
path-traced with Mitsuba, trained a few steps, exported; interrupted fits resume to the same model."""

from __future__ import annotations

import json
import logging
from dataclasses import replace

import numpy as np
import pytest

from neumip.client.cli import main
from neumip.core.config import MaterialConfig
from neumip.training.loop.config import TEST

pytest.importorskip("mitsuba")
Image = pytest.importorskip("PIL.Image")

STEPS = 30
FAST = replace(TEST, steps=STEPS, batch=512, checkpoint_every=10, validate_every=10, log_every=5)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_train_views_find_the_maps_of_data_made_in_another_folder(material, tmp_path, monkeypatch, caplog):
    """The progress grid's ground truth of a texture-map material: meta.json's map paths are relative
    to the description file, so training run from another folder used to lose them (and the grid
    showed the model only)."""
    data = tmp_path / "data"
    monkeypatch.chdir(material.parent)  # generated beside the maps, with a relative path
    assert main(["generate", material.name, "-o", str(data), "--queries", "2048", "--spp", "2"]) == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    caplog.set_level(logging.WARNING)
    argv = ["train", str(data), "-o", str(tmp_path / "my.onnx"), "--preset", "test", "--steps", "10",
            "--batch", "256", "--checkpoint", str(tmp_path / "run" / "ck.pt"), "--threads", "1", "--base",
            "--terminator", "specular", "--visibility-input"]
    assert main(argv) == 0
    assert "no ground truth for the progress grid" not in caplog.text
    record = json.loads((tmp_path / "my.json").read_text())
    assert record["material_config"]["base"] == 8  # the data's material's maps make the base
    assert record["material_config"]["terminator"] == "specular" and record["material_config"]["visibility_input"]
    views = json.loads((tmp_path / "run" / "views" / "meta.json").read_text())
    assert views["complete"] and views["material"]["name"] == "my"


def test_train_checkpoint_defaults_beside_the_output(material, tmp_path, monkeypatch, plane_data):
    """Without --checkpoint, `neumip train` keeps its run in NAME.run/ beside the model, not in ./runs."""
    data = plane_data(tmp_path / "plane", 2048)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "models" / "plane.onnx"
    assert main(["train", str(data.path), "-o", str(out), "--preset", "test", "--steps", "5",
                 "--batch", "256", "--resolution", "8", "--threads", "1"]) == 0
    assert (tmp_path / "models" / "plane.run" / "checkpoint.pt").is_file()
    assert not (tmp_path / "runs").exists()


def test_fit_from_another_folder(material, tmp_path, monkeypatch, capsys):
    """One command, run from an unrelated folder: ground truth, training, validation table, export."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "models" / "my.onnx"
    argv = ["fit", str(material), "-o", str(out), "--preset", "test", "--steps", "10", "--spp", "2",
            "--queries-per-texel", "32", "--threads", "1"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "query MSE x1e-3" in printed and "work folder" in printed
    assert "verdict: query MSE" in printed and "the ground truth's own noise" in printed
    for name in ("my.onnx", "my.json", "my.loss.png", "my.progress.png"):
        assert (out.parent / name).is_file(), name
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["validation"]["steps"] == 10 and record["material_config"]["resolution"] == 8
    config = record["material_config"]  # the maps recipe: lean textures, the offset read at the footprint
    assert config["base"] == 8 and config["half_textures"] and config["offset_mip"] and config["lod_bias"] == 1
    noise = record["validation"]["noise"]
    assert noise["noise_floor"] > 0 and noise["ratio"] == pytest.approx(noise["mse"] / noise["noise_floor"])
    assert (out.parent / "my.run" / "views" / "meta.json").is_file()  # the grid had its ground truth
    assert not list(out.parent.glob(".*.partial"))
    assert main(argv) == 2  # finished: replaced only with --force
    assert "pass --force" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "absent.toml"), "-o", str(tmp_path / "a.onnx")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_fit_the_ablation_without_offset_and_relief(material, tmp_path, capsys):
    """The README's parallax ablation: `fit --no-offset --relief 0` over the maps recipe (whose offset_mip then has
    nothing to read)."""
    out = tmp_path / "my_nooffset.onnx"
    argv = ["fit", str(material), "-o", str(out), "--preset", "test", "--steps", "3", "--spp", "2",
            "--queries-per-texel", "32", "--threads", "1", "--no-offset", "--relief", "0"]
    assert main(argv) == 0, capsys.readouterr().err
    config = json.loads(out.with_suffix(".json").read_text())["material_config"]
    assert not config["offset"] and "offset_mip" not in config and "relief" not in config and config["base"] == 8


def test_interrupted_fit_resumes_to_the_same_model(material, tmp_path):
    """Interrupted in the ground truth and again in training, a fit leaves no model under its name,
    and the same call then finishes the model an uninterrupted fit makes."""
    from neumip.engines.local import LocalMaterials
    from neumip.core.contract import random_queries
    from neumip.training.loop.fit import FitSettings, fit
    from neumip.training.loop.paths import fitted
    from neumip.groundtruth.description import load_description
    from neumip.groundtruth.generate import GenerateSettings

    desc = load_description(material)
    gen = GenerateSettings(queries=2048, spp=2, chunk=512)
    settings = FitSettings(MaterialConfig(resolution=8), FAST, gen)

    def interrupt_at(stage: str, count: int):
        def report(name: str, done: int, total: int | None) -> None:
            if name == stage and done >= count:
                raise KeyboardInterrupt
        return report

    out = tmp_path / "resumed" / "my.onnx"
    for stage, count in (("ground truth", 1024), ("training", 15)):
        with pytest.raises(KeyboardInterrupt):
            fit(desc, out, settings, interrupt_at(stage, count))
        assert not out.exists() and not fitted(out)
    progress = json.loads((out.parent / "my.run" / "data" / "meta.json").read_text())
    assert progress["complete"]  # the ground truth was finished by the second call
    table, paths = fit(desc, out, settings)
    assert fitted(out) and table["steps"] == STEPS
    whole = tmp_path / "whole" / "my.onnx"
    fit(desc, whole, settings)
    queries = random_queries(4096, seed=3)
    answers = [LocalMaterials(path.parent, threads=1).evaluate("my", queries) for path in (out, whole)]
    np.testing.assert_array_equal(*answers)


def test_fit_command_imports_torch_only_after_setting_its_threads():
    """`neumip fit` and `neumip train` check their output before importing torch: torch's OpenMP threads read
    OMP_WAIT_POLICY once, and spinning threads made training ~20x slower on a busy machine."""
    import subprocess
    import sys

    code = ("import sys; from neumip.client.cli import build_parser; build_parser(); "
            "from neumip.training.loop.paths import cut_short, fitted, work_folder; fitted('m.onnx'); "
            "cut_short('m.onnx'); work_folder('m.onnx'); import neumip.training.loop.fit; "
            "sys.exit('torch' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


def test_fit_samples_the_maps_footprints_and_trains_a_map_model(material, tmp_path, capsys):
    """A model coarser than the maps: its queries (per model texel) have footprints sampled for the
    maps' resolution; --maps trains the map-informed model, with --base on the maps' base and --relief on
    their height, whose export answers as its checkpoint."""
    from neumip.engines.local import LocalMaterials, load_material
    from neumip.core.contract import random_queries
    from neumip.training.loop import checkpoint

    out = tmp_path / "my.onnx"
    argv = ["fit", str(material), "-o", str(out), "--preset", "test", "--steps", "10", "--spp", "2",
            "--queries-per-texel", "32", "--resolution", "4", "--maps", "--half-vector", "--base", "--relief", "3",
            "--threads", "1"]
    assert main(argv) == 0
    meta = json.loads((tmp_path / "my.run" / "data" / "meta.json").read_text())
    assert (meta["generator"]["resolution"], meta["generator"]["queries"]) == (8, 32 * 4 * 4)
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["material_config"]["resolution"] == 4 and record["material_config"]["half_vector"]
    assert record["material_config"]["base"] == 8  # the maps' resolution
    assert (record["material_config"]["relief"], record["material_config"]["relief_steps"]) == (8, 3)
    assert "map-informed" in load_material(out).info()["description"]
    assert "relief (3 steps)" in load_material(out).info()["description"]
    trained, _ = checkpoint.load(tmp_path / "my.run" / "checkpoint.pt")
    assert trained.maps is not None  # a MapMaterial
    queries = random_queries(2048, seed=4)
    import torch
    with torch.no_grad():
        want = trained(torch.from_numpy(queries)).numpy()
    np.testing.assert_allclose(LocalMaterials(tmp_path, threads=1).evaluate("my", queries), want, rtol=1e-4, atol=1e-5)



def test_fit_queries_lets_a_finer_model_share_a_coarser_models_data(material, tmp_path, capsys):
    """--queries fixes the ground truth's size whatever --resolution is: a model at the maps' resolution trains on
    the data set a coarser model made, which it finds complete and does not trace again."""
    data = tmp_path / "data"
    common = ["--preset", "test", "--steps", "5", "--spp", "2", "--queries-per-texel", "32", "--data", str(data),
              "--threads", "1"]
    assert main(["fit", str(material), "-o", str(tmp_path / "coarse.onnx"), "--resolution", "4", *common]) == 0
    traced = (data / "rgb.npy").stat().st_mtime_ns
    assert main(["fit", str(material), "-o", str(tmp_path / "fine.onnx"), "--resolution", "8", "--queries", "512",
                 *common]) == 0
    assert (data / "rgb.npy").stat().st_mtime_ns == traced
    assert json.loads((data / "meta.json").read_text())["generator"]["queries"] == 32 * 4 * 4
    assert json.loads((tmp_path / "fine.json").read_text())["material_config"]["resolution"] == 8


def test_fit_base_auto_keeps_the_base_only_where_it_lowers_the_reference_error(material, tmp_path, capsys):
    """--base auto trains without and with the classical base on the same data and keeps the base only where
    it lowers the MSE on a low-noise reference set by the margin; --local-frame, --terminator and --visibility-input
    go with the base (the model without it has no frame, no terminator to soften, no visibility to read)."""
    from neumip.engines.local import load_material

    out = tmp_path / "auto.onnx"
    argv = ["fit", str(material), "-o", str(out), "--preset", "test", "--steps", "10", "--spp", "2",
            "--queries-per-texel", "32", "--resolution", "4", "--base", "auto", "--local-frame", "--terminator", "none",
            "--visibility-input", "--threads", "1", "--coarse-spp", "4", "--coarse-loss", "log_weighted",
            "--coarse-level", "1"]
    assert main(argv) == 0
    record = json.loads(out.with_suffix(".json").read_text())
    choice = record["validation"]["base_choice"]
    with_base = choice["reference_log_mse_with"] < (1 - choice["margin"]) * choice["reference_log_mse_without"]
    assert choice["kept"] == ("with" if with_base else "without")
    assert record["material_config"].get("base", 0) == (8 if with_base else 0)
    assert record["material_config"].get("local_frame", False) == with_base
    assert record["material_config"].get("terminator", "all") == ("none" if with_base else "all")
    assert record["material_config"].get("visibility_input", False) == with_base
    run = tmp_path / "auto.run"
    assert (run / "checkpoint.pt").exists() and (run / "base" / "checkpoint.pt").exists()
    reference = json.loads((run / "reference" / "meta.json").read_text())
    assert reference["complete"] and reference["generator"]["spp"] == 256 and reference["n"] == 1 << 14
    assert "coarse_spp" not in reference["generator"]  # 256 samples everywhere already
    data = json.loads((run / "data" / "meta.json").read_text())["generator"]  # --coarse-spp: from level 1 of the 4^2
    bias = record["material_config"].get("lod_bias", 0)  # model, in texels of the 8^2 maps
    assert (data["coarse_spp"], data["coarse_texels"]) == (4, 2.0 ** (1 - bias) * 8 / 4)
    assert "classical base: reference log MSE" in capsys.readouterr().out
    assert (load_material(out).config.get("base", 0) == 8) == with_base  # the file is the kept model


def test_fit_seeds_keeps_the_initial_weights_with_the_lowest_reference_error(material, tmp_path, capsys):
    """--seeds 3 trains from seeds 0, 1 and 2 on the same data and exports the run with the lowest error on the
    reference set; the same command again (every run finished) resumes them and makes the same file."""
    import onnxruntime as ort

    from neumip.core.contract import random_queries
    from neumip.training.loop.outputs import export_checkpoint

    out = tmp_path / "seeds.onnx"
    argv = ["fit", str(material), "-o", str(out), "--preset", "test", "--steps", "10", "--spp", "2",
            "--queries-per-texel", "32", "--resolution", "4", "--seeds", "3", "--threads", "1"]
    assert main(argv) == 0
    choice = json.loads(out.with_suffix(".json").read_text())["validation"]["seed_choice"]
    errors = choice["reference_log_mse"]
    assert choice["seeds"] == [0, 1, 2] and len(set(errors)) == 3
    assert choice["kept"] == int(np.argmin(errors))
    assert "initial weights: reference log MSE" in capsys.readouterr().out
    run = tmp_path / "seeds.run"
    kept = run / "checkpoint.pt" if choice["kept"] == 0 else run / f"seed{choice['kept']}" / "checkpoint.pt"
    assert all((run / f"seed{k}" / "checkpoint.pt").exists() for k in (1, 2))
    export_checkpoint(kept, tmp_path / "kept.onnx")
    queries = random_queries(256, seed=3)
    answers = [ort.InferenceSession(str(p)).run(None, {"queries": queries})[0] for p in (out, tmp_path / "kept.onnx")]
    np.testing.assert_array_equal(*answers)
    first = out.read_bytes()
    assert main(argv + ["--force"]) == 0
    assert out.read_bytes() == first


def test_fit_refuses_fewer_than_one_seed_before_tracing_anything(material, tmp_path, capsys):
    out = tmp_path / "none.onnx"
    assert main(["fit", str(material), "-o", str(out), "--preset", "test", "--seeds", "0", "--threads", "1"]) == 2
    assert "seeds must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "none.run" / "data").exists() and not out.exists()


def test_a_1x1_model_gets_data_for_its_directions():
    """A material without maps gets a 1 x 1 model; its answer still varies with the footprint and both directions,
    so `fit` traces `MIN_QUERIES` for it, not 256 (the per-texel count everywhere else)."""
    from neumip.training.loop.fit import MIN_QUERIES, data_queries

    assert data_queries(256, 1) == MIN_QUERIES == 1 << 20
    assert data_queries(32, 4) == 512 and data_queries(256, 256) == 1 << 24


def test_coarse_spp_starts_where_the_coarse_loss_applies():
    """`fit --coarse-spp`'s footprint threshold is `TrainConfig.coarse_level` of the model's pyramid, in texels of the
    data's resolution; a model without that level gets none."""
    from neumip.training.loop.fit import coarse_texels

    train = replace(TEST, coarse_loss="log_weighted", coarse_level=3)
    assert coarse_texels(train, MaterialConfig(resolution=256, lod_bias=1), 256) == 4.0
    assert coarse_texels(train, MaterialConfig(resolution=64, lod_bias=1), 256) == 16.0
    assert coarse_texels(train, MaterialConfig(resolution=64), 64) == 8.0
    assert coarse_texels(train, MaterialConfig(resolution=4), 256) == 0.0
