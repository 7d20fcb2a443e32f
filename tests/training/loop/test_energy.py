"""Fitting the energy table: at a run's end (and again when the run is continued), and for a model file made
without one (`neumip calibrate`)."""

import json
from dataclasses import replace

import numpy as np
import onnx
import pytest
import torch

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.config import MaterialConfig
from neumip.engines.local import load_material
from neumip.training.export.trim import trim_file
from neumip.training.loop.config import TEST
from neumip.training.loop.calibrate import ENERGY_AZIMUTHS, calibrate_file
from neumip.training.loop.outputs import export_checkpoint
from neumip.training.loop.train import Trainer, split_indices

pytestmark = pytest.mark.usefixtures("one_torch_thread")

TINY = MaterialConfig(resolution=16, energy_bins=4)
FAST = replace(TEST, steps=60, batch=1024, checkpoint_every=20, log_every=10)


@pytest.fixture(scope="module")
def data(tmp_path_factory, plane_data):
    return plane_data(tmp_path_factory.mktemp("plane") / "data", 40_000, seed=5)


def darkness(table: dict) -> float:
    """The held-out data's mean over the answers' mean, all levels."""
    return table["overall"]["target_mean"] / table["overall"]["answer_mean"]


def test_a_run_fits_its_table_at_its_end_and_again_when_it_is_continued(data, tmp_path, assert_parity):
    run = Trainer(data.path, tmp_path / "run.pt", TINY, FAST)
    table = run.run()
    gains = getattr(run.material, W.ENERGY).clone()
    assert run.state.energy_fitted and not torch.all(gains == 1.0)
    with torch.no_grad():
        getattr(run.material, W.ENERGY).fill_(1.0)
    without = run.validate()  # the same weights without the table: darker (the log loss's bias)
    assert abs(darkness(table) - 1) < 0.5 * abs(darkness(without) - 1), (table["overall"], without["overall"])
    resumed = Trainer(data.path, tmp_path / "run.pt", TINY, FAST)  # the table travels in the checkpoint
    assert resumed.state.energy_fitted and torch.equal(getattr(resumed.material, W.ENERGY), gains)
    longer = Trainer(data.path, tmp_path / "run.pt", TINY, replace(FAST, steps=80))
    seen = []
    longer.run(lambda step, loss: seen.append(bool(torch.all(getattr(longer.material, W.ENERGY) == 1.0))))
    assert all(seen) and longer.state.energy_fitted  # it trained with no table, then fitted a new one
    assert not torch.equal(getattr(longer.material, W.ENERGY), gains)
    path = export_checkpoint(tmp_path / "run.pt", tmp_path / "m.onnx")
    q = data.queries[:4000]
    with torch.no_grad():
        want = longer.material.eval()(torch.from_numpy(np.asarray(q))).numpy()
    assert_parity(load_material(path).run(np.asarray(q)), want)


@pytest.fixture(scope="module")
def plain_model(data, tmp_path_factory):
    """A model trained without a table, exported."""
    folder = tmp_path_factory.mktemp("plain")
    Trainer(data.path, folder / "run.pt", replace(TINY, energy_bins=0), FAST).run()
    return export_checkpoint(folder / "run.pt", folder / "plain.onnx")


def test_calibrating_a_file_fits_its_table_on_the_training_split_and_validates_it_held_out(data, plain_model, tmp_path):
    out = tmp_path / "calibrated.onnx"
    validation = calibrate_file(plain_model, data.path, out, bins=3)
    model = onnx.load(out)
    meta = {p.key: p.value for p in model.metadata_props}
    assert json.loads(meta[C.META_CONFIG])["energy_bins"] == 3
    assert json.loads(meta[C.META_VALIDATION]) == validation
    before = json.loads({p.key: p.value for p in onnx.load(plain_model).metadata_props}[C.META_VALIDATION])
    assert validation["steps"] == before["steps"] == FAST.steps and validation["batch"] == before["batch"]
    assert validation["overall"]["n"] == len(split_indices(len(data), TEST)[1])
    assert abs(darkness(validation) - 1) < 0.5 * abs(darkness(before) - 1), (validation["overall"], before["overall"])
    assert validation["overall"]["mse"] < before["overall"]["mse"]
    table = next(onnx.numpy_helper.to_array(t) for t in model.graph.initializer if t.name == W.ENERGY)
    assert table.shape == (5 * 9 * ENERGY_AZIMUTHS, 3) and not np.all(table == 1.0)  # the recipe's azimuths
    again = tmp_path / "again.onnx"  # a model with a table refits from its answers without one: the same table
    calibrate_file(out, data.path, again)
    table2 = next(onnx.numpy_helper.to_array(t) for t in onnx.load(again).graph.initializer if t.name == W.ENERGY)
    np.testing.assert_allclose(table2, table, rtol=1e-5)


def test_a_trimmed_model_is_refused_and_the_command_says_why(data, plain_model, tmp_path, capsys):
    from neumip.client.cli import main

    trim_file(plain_model, tmp_path / "trimmed.onnx", 2)
    with pytest.raises(ValueError, match="trimmed"):
        calibrate_file(tmp_path / "trimmed.onnx", data.path, tmp_path / "out.onnx")
    assert main(["calibrate", str(tmp_path / "trimmed.onnx"), "--data", str(data.path), "-o",
                 str(tmp_path / "out.onnx")]) != 0
    assert "trimmed" in capsys.readouterr().err and not (tmp_path / "out.onnx").exists()
    assert main(["calibrate", str(plain_model), "--data", str(tmp_path), "-o", str(tmp_path / "out.onnx")]) != 0
    assert "not a data set" in capsys.readouterr().err
    assert main(["calibrate", str(plain_model), "--data", str(data.path), "-o", str(tmp_path / "out.onnx")]) == 0
    assert "held-out MSE" in capsys.readouterr().out
    assert main(["calibrate", str(plain_model), "--data", str(data.path), "-o", str(tmp_path / "out.onnx")]) != 0
    assert "--force" in capsys.readouterr().err


def test_calibrating_with_azimuths_adds_the_fourth_axis_and_the_files_answers_follow_it(data, plain_model, tmp_path):
    from neumip.client.cli import main

    out = tmp_path / "azimuths.onnx"
    assert main(["calibrate", str(plain_model), "--data", str(data.path), "-o", str(out), "--bins", "3",
                 "--azimuths", "4"]) == 0
    model = onnx.load(out)
    config = json.loads({p.key: p.value for p in model.metadata_props}[C.META_CONFIG])
    assert config["energy_bins"] == 3 and config["energy_azimuths"] == 4
    table = next(onnx.numpy_helper.to_array(t) for t in model.graph.initializer if t.name == W.ENERGY)
    cells = table.reshape(5, 3, 3, 4, 3)  # levels 0-4 of a 16^2 material
    assert np.array_equal(cells[:, 0], np.repeat(cells[:, 0, :, :1], 4, axis=2))  # one gain at the normal
    assert not np.allclose(cells[:, 1:], cells[:, 1:, :, :1])  # elsewhere the gains change with the azimuth
    plain = calibrate_file(out, data.path, tmp_path / "plain.onnx", azimuths=0)  # and back to three axes
    table3 = next(onnx.numpy_helper.to_array(t) for t in onnx.load(tmp_path / "plain.onnx").graph.initializer
                  if t.name == W.ENERGY)
    assert table3.shape == (5 * 9, 3) and plain["overall"]["n"] == len(split_indices(len(data), TEST)[1])


def test_calibrating_with_luminance_keeps_one_gain_a_cell_and_the_files_answers_stay_grey_scaled(data, plain_model,
                                                                                                tmp_path):
    """`--luminance`: one gain a cell; the file's answers are its answers without a table times one number each."""
    from neumip.client.cli import main
    from neumip.engines.local import load_material

    out = tmp_path / "luminance.onnx"
    assert main(["calibrate", str(plain_model), "--data", str(data.path), "-o", str(out), "--bins", "3",
                 "--azimuths", "4", "--luminance"]) == 0
    model = onnx.load(out)
    config = json.loads({p.key: p.value for p in model.metadata_props}[C.META_CONFIG])
    assert config["energy_luminance"] is True
    table = next(onnx.numpy_helper.to_array(t) for t in model.graph.initializer if t.name == W.ENERGY)
    assert table.shape == (5 * 9 * 4, 1) and not np.allclose(table, 1.0)
    calibrate_file(out, data.path, tmp_path / "again.onnx")  # calibrated again: the model's own option kept
    again = onnx.load(tmp_path / "again.onnx")
    assert json.loads({p.key: p.value for p in again.metadata_props}[C.META_CONFIG])["energy_luminance"] is True
    queries = np.asarray(data.queries[:2000], np.float32)
    with_table = load_material(out).run(queries)
    ratio = with_table / np.maximum(load_material(plain_model).run(queries), 1e-12)
    lit = (with_table > 1e-4).all(1)
    assert lit.sum() > 100 and np.allclose(ratio[lit], ratio[lit][:, :1], rtol=1e-4)  # one gain for the three
