"""Training: a tiny material learns the analytic plane, resumes exactly, stops on NaN, exports with parity."""

import json
import shutil
from dataclasses import replace

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from neumip.core import contract as C
from neumip.training.loop import checkpoint
from neumip.training.loop import train as train_mod
from neumip.training.loop.blur import blur_sigma, effective_textures
from neumip.core.config import MaterialConfig
from neumip.training.loop.outputs import write_outputs
from neumip.training.loop.train import Trainer, TrainingDiverged, TrainingError
from neumip.training.loop.config import TEST
from neumip.core.contract import random_queries

TINY = MaterialConfig(resolution=16)
FAST = replace(TEST, steps=60, batch=1024, checkpoint_every=20, log_every=10)

REL_L1_BOUND = 0.06
"""Validation relative L1 error the 16 x 16 material must reach on the analytic plane (measured:
0.030 after the fixture's 300 steps of 1 024; the constant-colour start is 0.38)."""


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def data(tmp_path_factory, plane_data):
    return plane_data(tmp_path_factory.mktemp("plane") / "data", 40_000, seed=3)


@pytest.fixture(scope="module")
def trained(data, tmp_path_factory):
    """A 16 x 16 material with offset trained for the TEST preset's 300 steps (batch 1024)."""
    ckpt = tmp_path_factory.mktemp("run") / "checkpoint.pt"
    trainer = Trainer(data.path, ckpt, TINY, replace(TEST, batch=1024))
    before = trainer.validate()
    table = trainer.run()
    return trainer, before, table


def test_tiny_material_learns_the_plane(trained):
    _, before, table = trained
    assert table["overall"]["rel_l1"] < REL_L1_BOUND, table["overall"]
    assert table["overall"]["rel_l1"] < 0.5 * before["overall"]["rel_l1"]
    assert [row["level"] for row in table["levels"]] == [0, 1, 2, 3, 4]
    assert sum(row["n"] for row in table["levels"]) == table["overall"]["n"] == 2000
    assert table["steps"] == 300


def test_held_out_split_is_disjoint_and_seeded(data):
    tr, val = train_mod.split_indices(len(data), TEST)
    assert len(np.intersect1d(tr, val)) == 0 and len(tr) + len(val) == len(data)
    tr2, val2 = train_mod.split_indices(len(data), TEST)
    np.testing.assert_array_equal(val, val2)


def test_export_passes_parity_and_carries_the_table(trained, tmp_path, assert_parity):
    """write_outputs exports the material in memory: the same file `neumip export` makes of the
    final checkpoint, within the parity contract of the trained material."""
    from neumip.training.loop.outputs import export_checkpoint

    trainer, _, table = trained
    paths = write_outputs(trainer, table, tmp_path / "tiny.onnx")
    model = onnx.load(paths["onnx"])
    meta = {p.key: p.value for p in model.metadata_props}
    assert json.loads(meta[C.META_VALIDATION]) == json.loads(json.dumps(table))
    assert trainer.sampling is None and C.META_SAMPLING not in meta  # an analytic plane: no maps to read
    assert json.loads(paths["json"].read_text())["validation"]["overall"] == pytest.approx(table["overall"])
    assert paths["png"].stat().st_size > 1000
    session = ort.InferenceSession(str(paths["onnx"]), providers=["CPUExecutionProvider"])
    q = random_queries(5000, seed=9)
    got = session.run(None, {C.ONNX_INPUT: q})[0]
    material, _ = checkpoint.load(trainer.checkpoint_path)
    with torch.no_grad():
        want = material(torch.from_numpy(q)).numpy()
    assert_parity(got, want)
    again = export_checkpoint(trainer.checkpoint_path, tmp_path / "again.onnx")
    assert again.read_bytes() == paths["onnx"].read_bytes()


class Interrupt(Exception):
    """Stands in for a kill: raised from the step callback."""


@pytest.mark.parametrize("config", [FAST, replace(FAST, distil=4, distil_level=2.0, distil_start=0.5)],
                         ids=["plain", "distil"])
def test_interrupted_run_resumes_exactly(data, tmp_path, config):
    """Kill a run at step 50 (checkpoint at 40); the resumed run replays steps 41.. exactly (distilled targets
    included: their aim points are drawn from the batches' generator, which the checkpoint keeps)."""
    seen = {}

    def spy_then_kill(step, loss):
        if step == 41:
            seen["weights"] = {k: v.clone() for k, v in part.material.state_dict().items()}
            seen["loss"] = loss
        if step == 50:
            raise Interrupt

    part = Trainer(data.path, tmp_path / "part.pt", TINY, config)
    with pytest.raises(Interrupt):
        part.run(spy_then_kill)
    resumed = Trainer(data.path, tmp_path / "part.pt", TINY, config)
    assert resumed.state.step == 40  # the last checkpoint before the interruption
    assert resumed.step() == pytest.approx(seen["loss"], rel=1e-6)
    got = resumed.material.state_dict()
    diffs = {name: float((got[name] - w).abs().max()) for name, w in seen["weights"].items()}
    assert max(diffs.values()) < 1e-6, diffs
    resumed.run()
    assert resumed.state.step == 60
    assert [h[0] for h in resumed.state.history] == [10, 20, 30, 40, 50, 60]


AVERAGED = replace(FAST, blur_start=0.0, average_fraction=0.25)
"""FAST without a blur schedule, its weights averaged over the last 15 of its 60 steps."""


def test_the_weights_are_the_mean_of_the_last_steps_and_an_interrupted_average_resumes(data, tmp_path):
    snapshots = []

    def record(step, loss):
        if step > 45:
            snapshots.append({k: p.detach().clone() for k, p in whole.material.named_parameters()})

    whole = Trainer(data.path, tmp_path / "whole.pt", TINY, AVERAGED)
    whole.run(record)
    assert len(snapshots) == 15 and whole.state.averaged == 15 and whole.state.average_applied
    for name, p in whole.material.named_parameters():
        mean = torch.stack([s[name] for s in snapshots]).mean(0)
        assert torch.allclose(p.detach(), mean, atol=1e-6), name
        assert not p.requires_grad or not torch.equal(p.detach(), snapshots[-1][name])  # not the last step's
    # killed inside the window (checkpoint at 50: 5 steps averaged), then resumed: the same mean
    part = Trainer(data.path, tmp_path / "part.pt", TINY, AVERAGED)
    with pytest.raises(KeyboardInterrupt):
        part.run(ctrl_c_at(53))
    resumed = Trainer(data.path, tmp_path / "part.pt", TINY, AVERAGED)
    assert resumed.state.averaged == 8  # the interrupted run's checkpoint at step 53
    resumed.run()
    for name, p in whole.material.named_parameters():
        assert torch.allclose(dict(resumed.material.named_parameters())[name], p, atol=1e-6), name


def ctrl_c_at(stop: int):
    """A step callback that raises KeyboardInterrupt (a Ctrl-C) after step `stop`."""
    def callback(step, loss):
        if step == stop:
            raise KeyboardInterrupt
    return callback


def test_ctrl_c_writes_a_checkpoint_of_the_steps_done(data, tmp_path):
    """KeyboardInterrupt at step 27 (periodic checkpoints every 20): the checkpoint holds step 27."""
    trainer = Trainer(data.path, tmp_path / "k.pt", TINY, FAST)
    with pytest.raises(KeyboardInterrupt):
        trainer.run(ctrl_c_at(27))
    assert Trainer(data.path, tmp_path / "k.pt", TINY, FAST).state.step == 27


@pytest.fixture
def ctrl_c_handled():
    """Python's own Ctrl-C handler while the test runs. A process that a non-interactive shell starts in the
    background inherits SIGINT ignored, and the trainer then rightly leaves SIGINT alone: a SIGINT these tests send
    would be lost, and they would fail by how pytest was started."""
    import signal

    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def ctrl_c_inside_step(trainer: Trainer, step: int) -> Trainer:
    """`trainer`, sent a SIGINT (a Ctrl-C) inside step `step` (1-based), just after it draws its batch."""
    import os
    import signal

    draw = trainer.sampler.draw

    def draw_then_ctrl_c(*args, **kwargs):
        batch = draw(*args, **kwargs)
        if trainer.state.step == step - 1:
            os.kill(os.getpid(), signal.SIGINT)
        return batch

    trainer.sampler.draw = draw_then_ctrl_c
    return trainer


def test_ctrl_c_inside_a_step_ends_the_run_after_it_and_resumes_exactly(data, tmp_path, ctrl_c_handled):
    """A SIGINT that arrives while a step runs (here: its batch just drawn) ends the run once that step is done:
    the checkpoint holds whole steps, and the resumed run ends with an uninterrupted run's weights."""
    import signal

    whole = Trainer(data.path, tmp_path / "whole.pt", TINY, FAST)
    whole.run()
    part = ctrl_c_inside_step(Trainer(data.path, tmp_path / "part.pt", TINY, FAST), 34)
    with pytest.raises(KeyboardInterrupt):
        part.run()
    resumed = Trainer(data.path, tmp_path / "part.pt", TINY, FAST)
    assert resumed.state.step == 34
    resumed.run()
    want, got = whole.material.state_dict(), resumed.material.state_dict()
    diffs = {name: float((got[name] - w).abs().max()) for name, w in want.items()}
    assert max(diffs.values()) < 1e-6, diffs
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # put back


def test_ctrl_c_inside_the_last_step_still_ends_the_run(data, tmp_path, ctrl_c_handled):
    """...and is not lost when that step was the last: no export follows, the checkpoint holds every step, and the
    same run resumed finishes."""
    part = ctrl_c_inside_step(Trainer(data.path, tmp_path / "last.pt", TINY, FAST), FAST.steps)
    with pytest.raises(KeyboardInterrupt):
        part.run()
    resumed = Trainer(data.path, tmp_path / "last.pt", TINY, FAST)
    assert resumed.state.step == FAST.steps
    assert resumed.run()["steps"] == FAST.steps


def test_export_of_a_mid_run_checkpoint_computes_what_training_computed(data, tmp_path, assert_parity):
    """A checkpoint inside the blur schedule stores raw textures; its export must use the blurred ones."""
    from neumip.training.loop.outputs import export_checkpoint

    trainer = Trainer(data.path, tmp_path / "mid.pt", TINY, FAST)

    def stop(step, loss):
        if step == 20:
            raise Interrupt

    with pytest.raises(Interrupt):
        trainer.run(stop)
    assert blur_sigma(20, FAST) > 0, "the test needs a checkpoint inside the blur schedule"
    q = random_queries(2000, seed=4)
    sigma = blur_sigma(20, FAST)
    levels, otex = effective_textures(trainer.material, sigma, FAST, trainer.state.offset_frozen)
    with torch.no_grad():
        want = trainer.material(torch.from_numpy(q), levels, otex).numpy()
        raw = trainer.material(torch.from_numpy(q)).numpy()
    assert np.abs(want - raw).max() > 1e-4, "blur must matter for this check to mean anything"
    out = export_checkpoint(tmp_path / "mid.pt", tmp_path / "mid.onnx")
    got = ort.InferenceSession(str(out)).run(None, {C.ONNX_INPUT: q})[0]
    assert_parity(got, want)


def test_resume_refuses_other_settings(data, tmp_path, plane_data):
    done = Trainer(data.path, tmp_path / "c.pt", TINY, replace(FAST, steps=20))
    done.run()  # ends inside the blur schedule: the blurred textures are baked once
    again = Trainer(data.path, tmp_path / "c.pt", TINY, replace(FAST, steps=20))
    again.run()  # nothing left to do: same weights, not blurred twice
    for name, value in done.material.state_dict().items():
        torch.testing.assert_close(again.material.state_dict()[name], value)
    advice = r"\. To resume it, run with the checkpoint's values; to start a new run, pass another --checkpoint"
    with pytest.raises(TrainingError, match=r"material config: resolution: checkpoint 16, now 32" + advice):
        Trainer(data.path, tmp_path / "c.pt", MaterialConfig(resolution=32), FAST)
    with pytest.raises(TrainingError, match=r"training settings: lr: checkpoint 0\.001, now 0\.5" + advice):
        Trainer(data.path, tmp_path / "c.pt", TINY, replace(FAST, lr=0.5))
    Trainer(data.path, tmp_path / "c.pt", TINY, replace(FAST, steps=40, checkpoint_every=7))  # may change
    other = plane_data(tmp_path / "other", 5000)
    with pytest.raises(TrainingError, match=r"data: n: checkpoint 40000, now 5000"):
        Trainer(other.path, tmp_path / "c.pt", TINY, FAST)
    with pytest.raises(TrainingError, match="a material with a base or a relief needs the material's maps"):
        Trainer(data.path, tmp_path / "b.pt", replace(TINY, base=32), FAST)
    with pytest.raises(TrainingError, match="a material with a base or a relief needs the material's maps"):
        Trainer(data.path, tmp_path / "r.pt", replace(TINY, relief=32), FAST)


def test_nan_loss_stops_and_keeps_last_good_checkpoint(data, tmp_path, monkeypatch):
    real_loss = train_mod.training_loss
    calls = {"n": 0}

    def loss_turning_nan(pred, target, config, name=None):
        calls["n"] += 1
        loss = real_loss(pred, target, config, name)
        return loss * float("nan") if calls["n"] > 30 else loss

    monkeypatch.setattr(train_mod, "training_loss", loss_turning_nan)
    ckpt = tmp_path / "nan.pt"
    trainer = Trainer(data.path, ckpt, TINY, FAST)
    with pytest.raises(TrainingDiverged, match=r"NaN/Inf at step 31.*last good checkpoint"):
        trainer.run()
    material, extra = checkpoint.load(ckpt)
    assert extra["state"]["step"] == 20
    assert all(torch.isfinite(v).all() for v in material.state_dict().values())


def test_the_last_steps_train_with_the_finish_loss(data, tmp_path, monkeypatch):
    real_loss, names = train_mod.training_loss, []

    def recording(pred, target, config, name=None):
        names.append(name)
        return real_loss(pred, target, config, name)

    monkeypatch.setattr(train_mod, "training_loss", recording)
    Trainer(data.path, tmp_path / "f.pt", TINY, replace(FAST, finish_loss="log_weighted", finish_fraction=0.25)).run()
    assert names == ["comb2"] * 45 + ["log_weighted"] * 15


def test_the_coarse_queries_train_with_the_coarse_loss(data, tmp_path, monkeypatch):
    """`coarse_loss`: each batch's queries whose level of detail is `coarse_level` or coarser are marked for it."""
    from neumip.core import contract as C

    real_loss, seen = train_mod.training_loss, []

    def recording(pred, target, config, name=None, coarse=None):
        seen.append((coarse, C.level_of_detail(recording.sigma, TINY.resolution, TINY.lod_bias)))
        return real_loss(pred, target, config, name, coarse)

    real_draw = train_mod.BatchSampler.draw

    def draw(self, device):
        queries, target = real_draw(self, device)
        recording.sigma = queries[:, C.SIGMA].numpy().astype(np.float64)
        return queries, target

    monkeypatch.setattr(train_mod, "training_loss", recording)
    monkeypatch.setattr(train_mod.BatchSampler, "draw", draw)
    Trainer(data.path, tmp_path / "c.pt", TINY, replace(FAST, coarse_loss="log_weighted", coarse_level=2.0)).run()
    assert len(seen) == FAST.steps
    for coarse, level in seen:
        np.testing.assert_array_equal(coarse.numpy(), level >= 2.0)
    assert any(c.any() for c, _ in seen) and any((~c).any() for c, _ in seen)


def test_the_coarse_queries_train_on_distilled_targets_from_distil_start(data, tmp_path, monkeypatch):
    """`distil`: from `distil_start` of the run, the coarse queries' targets are the model's own finer answers'
    mean; the other queries keep the data's."""
    real_loss, seen = train_mod.training_loss, []

    def recording(pred, target, config, name=None, coarse=None):
        seen.append(target.clone())
        return real_loss(pred, target, config, name, coarse)

    real_draw = train_mod.BatchSampler.draw

    def draw(self, device, aims=False):
        out = real_draw(self, device, aims)
        draw.drawn.append(out)
        return out

    draw.drawn = []
    monkeypatch.setattr(train_mod, "training_loss", recording)
    monkeypatch.setattr(train_mod.BatchSampler, "draw", draw)
    config = replace(FAST, distil=4, distil_level=2.0, distil_start=0.5)
    Trainer(data.path, tmp_path / "d.pt", TINY, config).run()
    assert len(seen) == len(draw.drawn) == FAST.steps
    for step, (target, drawn) in enumerate(zip(seen, draw.drawn)):
        queries, data_target = drawn[0], drawn[1]
        coarse = C.level_of_detail(queries[:, C.SIGMA].numpy(), TINY.resolution, TINY.lod_bias) >= 2.0
        assert (len(drawn) == 3) == (step >= FAST.steps // 2)
        np.testing.assert_array_equal(target[~coarse].numpy(), data_target[~coarse].numpy())
        changed = (target[coarse] != data_target[coarse]).any(dim=1).numpy()
        assert changed.all() if step >= FAST.steps // 2 else not changed.any()


def test_cli_train_writes_model_table_and_curve(data, tmp_path, capsys):
    from neumip.client.cli import main

    out = tmp_path / "models" / "plane.onnx"
    (tmp_path / "progress.json").write_text('{"validate_every": 10}')  # drawn mid-run, before models/ exists
    argv = ["train", str(data.path), "-o", str(out), "--preset", "test", "--resolution", "8",
            "--steps", "20", "--batch", "512", "--checkpoint", str(tmp_path / "ck.pt"),
            "--config", str(tmp_path / "progress.json"), "--hidden", "9", "--half-vector"]
    assert main(argv) == 0
    assert out.exists() and out.with_suffix(".json").exists() and (out.parent / "plane.loss.png").exists()
    assert (out.parent / "plane.progress.png").exists() and not list(out.parent.glob("*.tmp.png"))
    printed = capsys.readouterr().out
    assert "step 10: held-out MSE" in printed and "MSE x1e-3" in printed
    config = json.loads(out.with_suffix(".json").read_text())["material_config"]
    assert config["resolution"] == 8 and config["hidden"] == 9 and config["half_vector"]
    assert main(["train", str(data.path), "-o", str(tmp_path / "x.txt")]) == 2
    assert main(["train", str(tmp_path / "missing"), "-o", str(tmp_path / "new.onnx")]) == 2
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    junk = ["--checkpoint", str(tmp_path / "junk.pt")]
    assert main(["train", str(data.path), "-o", str(tmp_path / "new.onnx"), *junk]) == 2
    assert "not a readable checkpoint" in capsys.readouterr().err
    # an existing model is replaced only with --force (the finished run's checkpoint is reused)
    model = out.read_bytes()
    assert main(argv) == 2
    assert f"{out} exists: pass --force" in capsys.readouterr().err
    assert out.read_bytes() == model
    assert main([*argv, "--force", "--description", "again"]) == 0
    assert out.read_bytes() != model  # rewritten with the new description
    # killed as the files were moved into place (the model in, its record not): the same command finishes it
    record = out.with_suffix(".json")
    staging = out.with_name(".plane.partial")
    staging.mkdir()
    record.rename(staging / record.name)
    assert main(argv) == 0
    assert record.exists() and not staging.exists()
    # killed while writing (nothing moved in yet), then another model put there: it is someone's, kept
    staging.mkdir()
    (staging / "plane.onnx").write_bytes(b"half")
    record.unlink()
    assert main(argv) == 2 and "pass --force" in capsys.readouterr().err
    shutil.rmtree(staging)
    assert main(["export", str(tmp_path / "ck.pt"), "-o", str(out)]) == 2
    assert main(["export", str(tmp_path / "ck.pt"), "-o", str(out), "--force"]) == 0


def test_cli_default_resolution_is_the_datas(tmp_path):
    from neumip.training.commands import _data_resolution

    (tmp_path / "meta.json").write_text(json.dumps({"generator": {"resolution": 64}}))
    assert _data_resolution(str(tmp_path)) == 64
    (tmp_path / "meta.json").write_text(json.dumps({"generator": "converted measured BTF"}))
    assert _data_resolution(str(tmp_path)) == 128


@pytest.mark.slow
def test_compiled_step_matches_eager(data, tmp_path):
    """torch.compile (TrainConfig.compile) computes the same steps as eager."""
    cfg = replace(FAST, steps=10)
    eager = Trainer(data.path, tmp_path / "e.pt", TINY, cfg)
    compiled = Trainer(data.path, tmp_path / "c.pt", TINY, replace(cfg, compile=True))
    for _ in range(10):
        assert compiled.step() == pytest.approx(eager.step(), rel=1e-4)
    assert compiled._loss != compiled._batch_loss  # it did not fall back to eager


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_a_run_on_the_gpu_learns_resumes_on_the_cpu_and_exports_what_it_computed(data, tmp_path, assert_parity):
    """`--device cuda`: the steps run on the GPU, the checkpoint resumes on the CPU, and the export answers
    what the GPU-trained material answers."""
    gpu = Trainer(data.path, tmp_path / "g.pt", TINY, replace(FAST, device="cuda"))
    first = gpu.step()
    table = gpu.run()
    assert next(gpu.material.parameters()).is_cuda and table["steps"] == 60
    assert table["overall"]["rel_l1"] < 0.5 and gpu.state.history[-1][1] < first
    cpu = Trainer(data.path, tmp_path / "g.pt", TINY, replace(FAST, steps=70, device="cpu"))
    assert cpu.state.step == 60 and not next(cpu.material.parameters()).is_cuda
    for name, value in gpu.material.state_dict().items():
        torch.testing.assert_close(cpu.material.state_dict()[name], value.cpu())
    cpu.run()
    paths = write_outputs(gpu, table, tmp_path / "g.onnx")
    q = random_queries(5000, seed=2)
    session = ort.InferenceSession(str(paths["onnx"]), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        want = gpu.material(torch.from_numpy(q).to("cuda")).cpu().numpy()
    assert_parity(session.run(None, {C.ONNX_INPUT: q})[0], want)


def test_cosine_schedule_falls_from_lr_to_its_final_fraction():
    from neumip.training.loop.train import learning_rate

    cfg = replace(TEST, steps=100, lr=1e-3, lr_schedule="cosine", lr_final=0.1)
    assert learning_rate(0, cfg) == pytest.approx(1e-3)
    assert learning_rate(50, cfg) == pytest.approx(0.55e-3)
    assert learning_rate(100, cfg) == pytest.approx(1e-4)
    assert learning_rate(50, replace(cfg, lr_schedule="constant")) == 1e-3
    with pytest.raises(ValueError, match="lr_schedule"):
        replace(cfg, lr_schedule="step")


def test_the_finish_steps_take_their_fraction_of_the_rate():
    from neumip.training.loop.train import learning_rate

    cfg = replace(TEST, steps=100, lr=1e-3, finish_loss="relative", finish_fraction=0.2, finish_lr_scale=0.1)
    assert [learning_rate(s, cfg) for s in (79, 80, 99)] == pytest.approx([1e-3, 1e-4, 1e-4])
    assert learning_rate(99, replace(cfg, lr_schedule="cosine", lr_final=0.1)) == pytest.approx(
        0.1 * learning_rate(99, replace(cfg, lr_schedule="cosine", lr_final=0.1, finish_lr_scale=1.0)))


def test_cosine_run_sets_the_optimiser_rate(data, tmp_path):
    cfg = replace(FAST, steps=20, lr_schedule="cosine", lr_final=0.0)
    trainer = Trainer(data.path, tmp_path / "c.pt", TINY, cfg)
    for _ in range(10):
        trainer.step()
    assert trainer.optimizer.param_groups[0]["lr"] == pytest.approx(cfg.lr * 0.5 * (1 + np.cos(np.pi * 9 / 20)))


def test_offset_freeze_off_keeps_training_the_offset_texture(data, tmp_path):
    cfg = replace(FAST, steps=40, blur_half_life=5.0)  # the blur schedule ends at step ~17
    frozen = Trainer(data.path, tmp_path / "f.pt", TINY, cfg)
    free = Trainer(data.path, tmp_path / "n.pt", TINY, replace(cfg, offset_freeze=False))
    for trainer in (frozen, free):
        trainer.run()
    assert frozen.state.offset_frozen and not frozen.material.offset_texture.requires_grad
    assert not free.state.offset_frozen and free.material.offset_texture.requires_grad


def test_progress_validations_are_recorded_and_drawn(data, tmp_path, plane_mbtf):
    """Every validate_every steps the held-out MSE per level is recorded (kept across resume) and
    the progress PNG shows ground truth beside the model for the view grid."""
    from neumip.groundtruth.dataset import write_dataset
    from neumip.training.loop.outputs import write_progress
    from neumip.training.loop.views import ViewGrid, view_queries

    cfg = replace(FAST, steps=30, validate_every=10, checkpoint_every=10)
    drawn = []
    trainer = Trainer(data.path, tmp_path / "c.pt", TINY, replace(cfg, steps=20))
    trainer.run(on_progress=lambda t: drawn.append(t.state.step))
    assert drawn == [10, 20]
    resumed = Trainer(data.path, tmp_path / "c.pt", TINY, cfg)
    table = resumed.run()
    steps = [record[0] for record in resumed.state.progress]
    assert steps == [10, 20, 30]
    levels, overall = resumed.state.progress[-1][1:]
    assert [lvl for lvl, _ in levels] == [r["level"] for r in table["levels"]]
    assert overall == pytest.approx(table["overall"]["mse"], rel=1e-5)  # the same split, the same function

    grid = ViewGrid(pixels=8, levels=(0, 2, 9))
    queries = view_queries(grid, TINY.resolution)
    assert queries.shape == (3 * 3 * 64, 7)  # level 9 is clamped to the 16^2 pyramid's top (4)
    views = write_dataset(tmp_path / "views", queries, plane_mbtf(queries), {"material": "analytic-plane"})
    for kind, truth in (("with truth", views), ("model only", None)):
        path = write_progress(resumed, tmp_path / f"{kind}.png", truth, grid)
        image = plt_image(path)
        assert image.shape[1] > image.shape[0] > 200, kind
    assert plt_image(tmp_path / "with truth.png").shape[1] > plt_image(tmp_path / "model only.png").shape[1]


def plt_image(path):
    from PIL import Image

    return np.asarray(Image.open(path))


def test_progress_views_ground_truth_of_the_flat_plane(tmp_path):
    """trace_views path-traces the view grid once (the flat plane: exactly albedo / pi) and reuses it;
    a material whose map files changed since the data was made gets no ground truth."""
    from neumip.groundtruth.description import find_description
    from neumip.training.loop.views import ViewGrid, clear_stale_views, trace_views, view_queries

    grid = ViewGrid(pixels=4, levels=(1,), spp=4)
    meta = find_description("flat").to_dict()
    views = trace_views(meta, grid, 16, tmp_path / "views")
    np.testing.assert_allclose(np.asarray(views.rgb), 0.5 / np.pi, rtol=1e-4)
    stamp = (tmp_path / "views" / "meta.json").stat().st_mtime_ns
    assert trace_views(meta, grid, 16, tmp_path / "views") is not None
    assert (tmp_path / "views" / "meta.json").stat().st_mtime_ns == stamp  # reused, not traced again
    finer = trace_views(meta, grid, 32, tmp_path / "views")  # a model of another resolution: traced anew there
    assert np.array_equal(np.asarray(finer.queries), view_queries(grid, 32))
    assert not np.array_equal(view_queries(grid, 32), view_queries(grid, 16))
    mine = tmp_path / "mine"  # a folder that holds something else is not emptied
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    (mine / "meta.json").write_text('{"generator": {"name": "my data"}}')
    clear_stale_views(mine)
    assert sorted(p.name for p in mine.iterdir()) == ["meta.json", "notes.txt"]
    assert trace_views({**meta, "map_sha256": {"height": "0" * 64}}, grid, 16, tmp_path / "v2") is None
    assert trace_views("analytic-plane", grid, 16, tmp_path / "v3") is None


def test_checkpoint_from_before_the_new_settings_resumes(data, tmp_path):
    """A checkpoint written without the newer TrainConfig fields resumes with their defaults."""
    cfg = replace(FAST, steps=20)
    trainer = Trainer(data.path, tmp_path / "c.pt", TINY, replace(cfg, steps=10))
    trainer.run()
    material, extra = checkpoint.load(tmp_path / "c.pt")
    for name in ("lr_schedule", "lr_final", "offset_freeze", "validate_every"):
        del extra["train_config"][name]
    del extra["state"]["progress"]
    checkpoint.save(tmp_path / "c.pt", material, extra)
    assert Trainer(data.path, tmp_path / "c.pt", TINY, cfg).run()["steps"] == 20


def test_the_ceiling_is_the_datas_largest_target_and_a_run_keeps_the_one_it_began_with(data, tmp_path):
    """`MaterialConfig.ceiling` 0 asks for the data's largest target; a resumed run keeps its checkpoint's (none
    for a run begun before the ceiling existed); a ceiling given is kept."""
    cfg = replace(FAST, steps=10)
    trainer = Trainer(data.path, tmp_path / "c.pt", TINY, cfg)
    assert trainer.material.config.ceiling == float(np.max(data.rgb)) > 0
    trainer.run()
    assert Trainer(data.path, tmp_path / "c.pt", TINY, replace(cfg, steps=20)).material.config.ceiling == \
        trainer.material.config.ceiling
    material, extra = checkpoint.load(tmp_path / "c.pt")
    material.config = replace(material.config, ceiling=0.0)  # as written before the ceiling existed
    checkpoint.save(tmp_path / "c.pt", material, extra)
    old = Trainer(data.path, tmp_path / "c.pt", TINY, replace(cfg, steps=20))
    assert old.material.config.ceiling == 0.0 and old.run()["steps"] == 20
    low = Trainer(data.path, tmp_path / "low.pt", replace(TINY, ceiling=0.01), cfg)  # below every target
    assert low.material.config.ceiling == 0.01
    with torch.no_grad():
        assert (low.material(torch.from_numpy(random_queries(100, seed=1))) == 0.01).all()
    before = [w.detach().clone() for w in low.material.decoder.parameters()]
    losses = [low.step() for _ in range(10)]
    moved = max(float((w - b).abs().max()) for w, b in zip(low.material.decoder.parameters(), before))
    assert moved > 1e-3 and losses[-1] < losses[0], "the loss reads the answers unclamped: clamped, none would learn"


def test_a_second_process_training_into_the_same_checkpoint_is_refused(data, tmp_path):
    """Two processes resuming one checkpoint would overwrite each other's checkpoints and outputs; the same
    process may open it again (resuming), and the lock goes with the process that held it."""
    import subprocess
    import sys

    trainer = Trainer(data.path, tmp_path / "c.pt", TINY, FAST)
    other = [sys.executable, "-c", "import sys; from neumip.training.loop.train import Trainer, TrainingError; "
             "from neumip.training.loop.config import TEST; from neumip.core.config import MaterialConfig\n"
             "try: Trainer(sys.argv[1], sys.argv[2], MaterialConfig(resolution=16), TEST)\n"
             "except TrainingError as e: print(e); sys.exit(3)", str(data.path), str(tmp_path / "c.pt")]
    refused = subprocess.run(other, capture_output=True, text=True, timeout=120)
    assert refused.returncode == 3, refused.stderr
    assert f"another process is training into {tmp_path / 'c.pt'}" in refused.stdout
    Trainer(data.path, tmp_path / "c.pt", TINY, FAST)  # this process again: allowed
    trainer._claim.close()  # as when the process ends
    assert subprocess.run(other, capture_output=True, text=True, timeout=120).returncode == 0


@pytest.mark.parametrize("name", ["paper", "quality", "ship", "quick"])
def test_presets_scale_the_papers_schedule(name):
    """Every preset but `test` is the paper's blur schedule scaled to its step count: the blur halves
    every ~1/9 of the run and ends (offset frozen) at ~59 % of it, leaving 40 % unblurred training."""
    from neumip.training.loop.blur import schedule_end
    from neumip.training.loop.config import PRESETS

    cfg = PRESETS[name]
    assert cfg.blur_half_life / cfg.steps == pytest.approx(3333 / 30_000, rel=0.01)
    assert schedule_end(cfg) / cfg.steps == pytest.approx(0.59, abs=0.01)
    assert cfg.lr_schedule == "constant" and cfg.offset_freeze  # measured best: experiments/quality_levers/


def test_candidates_go_on_with_the_best_start_and_count_every_step(data, tmp_path):
    """Three starts train 20 steps each on the same batches; the one with the lowest held-out error
    goes on, exactly as a run from that start alone would; the callback counts all 100 steps once."""
    config = replace(FAST, candidates=3, candidate_steps=20)
    trainer = Trainer(data.path, tmp_path / "c.pt", TINY, config)
    counted = []
    trainer.run(lambda step, loss: counted.append(step))
    assert counted == list(range(1, config.total_steps + 1)) and config.total_steps == 100
    seeds, errors = zip(*trainer.state.candidates)
    assert seeds == (0, 1, 2) and len(set(errors)) == 3
    kept = seeds[int(np.argmin(errors))]
    assert (trainer.state.step, trainer.state.dropped_steps) == (60, 40)

    alone = Trainer(data.path, tmp_path / "alone.pt", TINY, FAST)  # the same split and batches
    alone.material = alone._new_material(kept)
    alone.optimizer = train_mod._make_optimizer(alone.material, FAST)
    alone.run()
    want, got = alone.material.state_dict(), trainer.material.state_dict()
    assert max(float((got[k] - want[k]).abs().max()) for k in want) < 1e-6
    resumed = Trainer(data.path, tmp_path / "c.pt", TINY, config)  # the comparison is in the checkpoint
    assert resumed.state.candidates == trainer.state.candidates and resumed.steps_done == 100


def test_a_run_interrupted_while_comparing_candidates_compares_them_again(data, tmp_path):
    config = replace(FAST, candidates=2, candidate_steps=20)
    with pytest.raises(KeyboardInterrupt):
        Trainer(data.path, tmp_path / "i.pt", TINY, config).run(ctrl_c_at(30))  # in the second start
    assert not (tmp_path / "i.pt").exists()  # no half-compared candidate passed off as the run
    again = Trainer(data.path, tmp_path / "i.pt", TINY, config)
    assert again.state.step == 0
    again.run()
    whole = Trainer(data.path, tmp_path / "w.pt", TINY, config)
    whole.run()
    assert again.state.candidates == whole.state.candidates


def test_a_diverging_start_is_dropped_and_an_interrupted_comparison_restarts_in_process(data, tmp_path, monkeypatch):
    """A candidate whose loss turns NaN loses the comparison instead of ending the run; a comparison
    interrupted in this process starts again from the first start when run() is called again."""
    config = replace(FAST, candidates=2, candidate_steps=20)
    real, calls = train_mod.training_loss, []

    def nan_first(pred, target, cfg, name=None):
        calls.append(1)
        loss = real(pred, target, cfg, name)
        return loss * float("nan") if len(calls) == 1 else loss

    monkeypatch.setattr(train_mod, "training_loss", nan_first)
    trainer = Trainer(data.path, tmp_path / "d.pt", TINY, config)
    trainer.run()
    assert trainer.state.candidates[0] == [0, float("inf")] and trainer.state.candidates[1][0] == 1
    assert trainer.state.step == 60
    monkeypatch.setattr(train_mod, "training_loss", real)
    again = Trainer(data.path, tmp_path / "i.pt", TINY, config)
    with pytest.raises(KeyboardInterrupt):
        again.run(ctrl_c_at(30))
    again.run()
    whole = Trainer(data.path, tmp_path / "w.pt", TINY, config)
    whole.run()
    assert again.state.candidates == whole.state.candidates and again.state.step == whole.state.step == 60


def test_a_lod_bias_the_data_were_not_drawn_for_is_named(tmp_path, plane_data, caplog):
    """A model whose finest level answers 2^-K texel (`MaterialConfig.lod_bias`) on generated data whose footprints do
    not reach it: the run goes on (the level mapping is the model's), with a warning naming the generate option."""
    data = plane_data(tmp_path / "data", 2_000, seed=1)
    meta_path = data.path / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["generator"] = {"name": "neumip.microgeometry/1", "sampling": {"sub_texel_levels": 1}}
    meta_path.write_text(json.dumps(meta))
    with caplog.at_level("WARNING", logger="neumip.training.loop.train"):
        Trainer(data.path, tmp_path / "a.pt", replace(TINY, lod_bias=1), FAST)
    assert not caplog.records
    Trainer(data.path, tmp_path / "b.pt", replace(TINY, lod_bias=2), FAST)
    assert "--sub-texel-levels 2" in caplog.text and "2^-1" in caplog.text
