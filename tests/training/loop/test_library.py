"""Training a material library (`neumip train-many`): in this process and as Ray tasks, skipping
finished materials, resuming interrupted ones, outputs in place only when whole."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from neumip.client.cli import main
from neumip.core.contract import random_queries
from neumip.engines.local import LocalMaterials
from neumip.core.cluster import ClusterError, RayConfig
from neumip.core.config import MaterialConfig
from neumip.training.loop.library import LibrarySettings, MaterialJob, finished, train_library, train_material
from neumip.training.loop.config import TEST

CONFIG = replace(TEST, steps=40, batch=512, checkpoint_every=20)


@pytest.fixture(scope="module")
def data(tmp_path_factory, plane_data):
    return plane_data(tmp_path_factory.mktemp("plane") / "plane", 6000, seed=5).path


def settings(tmp_path: Path, **fields) -> LibrarySettings:
    return LibrarySettings(tmp_path / "models", tmp_path / "runs", replace(CONFIG, **fields))


def job(name: str, data, offset: bool = True) -> MaterialJob:
    return MaterialJob(name, str(data), MaterialConfig(resolution=8, offset=offset), f"{name} test")


def test_cli_trains_a_library_then_skips_it(data, tmp_path, capsys):
    models = tmp_path / "models"
    argv = ["train-many", str(data), f"flat={data}", "--no-offset", "flat", "-o", str(models),
            "--runs", str(tmp_path / "runs"), "--preset", "test", "--steps", "30", "--resolution", "8", "--hidden", "9"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "2 trained, 0 skipped, 0 failed" in out and "MSE x1e-3" in out
    materials = LocalMaterials(models)
    assert materials.materials() == ["flat", "plane"] and not list(models.glob(".*"))
    assert materials.get("plane").info()["description"] == "plane, 8^2, neural offset, MLP width 9, test preset"
    flat = json.loads((models / "flat.json").read_text())["material_config"]
    assert flat["offset"] is False and flat["hidden"] == 9
    stamp = (models / "plane.onnx").stat().st_mtime_ns
    assert main(argv) == 0  # everything finished: nothing is retrained
    assert "0 trained, 2 skipped, 0 failed" in capsys.readouterr().out
    assert (models / "plane.onnx").stat().st_mtime_ns == stamp


def test_cli_reports_failed_materials_and_bad_names(data, tmp_path, capsys):
    argv = ["train-many", str(data), str(tmp_path / "missing"), "-o", str(tmp_path / "m"),
            "--runs", str(tmp_path / "runs"), "--preset", "test", "--steps", "10", "--resolution", "8"]
    assert main(argv) == 1
    out = capsys.readouterr().out
    assert "missing: failed:" in out and "1 trained, 0 skipped, 1 failed: missing" in out
    assert main([*argv[:3], "--no-offset", "nobody", *argv[3:]]) == 2
    assert "--no-offset names no material: nobody" in capsys.readouterr().err


def test_interrupted_materials_resume_and_half_moved_outputs_are_redone(data, tmp_path):
    lib = settings(tmp_path)
    train_material(job("a", data), settings(tmp_path, steps=20))  # stopped half-way: a checkpoint at 20
    (lib.models / "a.json").unlink()  # as if interrupted before the record was moved into place
    (lib.models / ".b.partial").mkdir()  # an export interrupted mid-way
    (lib.models / ".b.partial" / "b.onnx").write_bytes(b"half")
    assert not finished(job("a", data), lib)
    results = train_library([job("a", data), job("b", data)], lib)
    assert results["a"]["steps"] == results["b"]["steps"] == 40
    record = json.loads((lib.models / "a.json").read_text())
    assert record["validation"]["steps"] == 40 and record["train_config"]["steps"] == 40
    assert LocalMaterials(lib.models).materials() == ["a", "b"] and not list(lib.models.glob(".*"))


def test_library_as_ray_tasks(local_ray, data, tmp_path):
    lib = settings(tmp_path)
    done = []
    jobs = [job("a", data), job("b", data, offset=False), job("c", tmp_path / "missing")]
    results = train_library(jobs, lib, RayConfig(), on_done=lambda j, r: done.append(j.name))
    assert sorted(done) == ["a", "b", "c"]
    assert results["a"]["steps"] == results["b"]["steps"] == 40
    assert isinstance(results["c"], ClusterError) and "missing" in str(results["c"])
    assert LocalMaterials(lib.models).materials() == ["a", "b"]
    # the same material trained in this process answers the same: tasks change where, not what
    local = settings(tmp_path / "local")
    train_library([job("a", data)], local)
    queries = random_queries(500, seed=2)
    np.testing.assert_array_equal(LocalMaterials(local.models).evaluate("a", queries),
                                  LocalMaterials(lib.models).evaluate("a", queries))


def test_cli_with_ray(local_ray, data, tmp_path, capsys):
    argv = ["train-many", f"x={data}", "-o", str(tmp_path / "m"), "--runs", str(tmp_path / "runs"),
            "--preset", "test", "--steps", "10", "--resolution", "8", "--threads", "1", "--ray"]
    assert main(argv) == 0
    assert "1 trained, 0 skipped, 0 failed" in capsys.readouterr().out
    assert LocalMaterials(tmp_path / "m").materials() == ["x"]


@pytest.mark.slow  # ~20 s: the retried task starts a fresh worker, which imports torch again
@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds Ray's worker processes in /proc")
def test_a_training_task_killed_after_a_checkpoint_resumes_to_the_same_model(local_ray, data, tmp_path, killing_the_first_busy_worker):
    lib = settings(tmp_path)
    checkpoint = lib.runs / "a" / "checkpoint.pt"  # written at step 20 of 40
    with killing_the_first_busy_worker(local_ray, "_material_task", when=checkpoint.exists) as killed:
        results = train_library([job("a", data)], lib, RayConfig())
    assert killed, "the task finished before it could be killed"
    assert results["a"]["steps"] == 40  # Ray's retry resumed from the checkpoint and finished
    local = settings(tmp_path / "local")
    train_library([job("a", data)], local)
    queries = random_queries(500, seed=3)
    np.testing.assert_array_equal(LocalMaterials(local.models).evaluate("a", queries),
                                  LocalMaterials(lib.models).evaluate("a", queries))


def test_cli_relief_marches_each_material_s_own_height_map(material, tmp_path, monkeypatch):
    """--relief: a material whose data come from a description with a height map gets the relief stage at
    its map's resolution; one trained --no-offset gets neither parallax stage."""
    data = tmp_path / "my"
    monkeypatch.chdir(material.parent)
    assert main(["generate", material.name, "-o", str(data), "--queries", "4096", "--spp", "2"]) == 0
    models = tmp_path / "models"
    argv = ["train-many", str(data), f"plain={data}", "--no-offset", "plain", "-o", str(models), "--runs",
            str(tmp_path / "runs"), "--preset", "test", "--steps", "10", "--resolution", "4", "--relief", "2"]
    assert main(argv) == 0
    config = json.loads((models / "my.json").read_text())["material_config"]
    assert (config["relief"], config["relief_steps"]) == (8, 2)
    assert "relief" not in json.loads((models / "plain.json").read_text())["material_config"]
    assert LocalMaterials(models).get("my").info()["description"].startswith("my, 4^2, relief, neural offset")
