"""`neumip trim`: answers above the cut are bit-identical (level boundaries and the offset included),
finer queries read the finest level kept, and what was cut travels in the metadata."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest

from neumip.core import contract as C
from neumip.client.cli import main
from neumip.engines.local import load_material, run_chunked
from neumip.core.config import MaterialConfig
from neumip.core.modelfile import ModelError
from neumip.training.export.graph import build_onnx, random_weights, save_onnx
from neumip.training.export.lod import clip_node
from neumip.training.export.trim import TrimError, current_trim, trim_model

RES = 16


def queries(n: int, seed: int, levels: np.ndarray) -> np.ndarray:
    """(n, 7) queries at continuous `levels` (of a RES^2 model), spread positions and directions."""
    rng = np.random.default_rng(seed)
    q = np.zeros((n, C.QUERY_DIM), np.float32)
    q[:, [C.U, C.V]] = rng.uniform(-3, 4, (n, 2))
    q[:, C.SIGMA] = (2.0 ** levels / RES).astype(np.float32)
    for cols in ([C.WI_X, C.WI_Y], [C.WO_X, C.WO_Y]):
        angle, radius = rng.uniform(0, 2 * np.pi, n), np.sqrt(rng.uniform(0, 0.98, n))
        q[:, cols] = np.stack([radius * np.cos(angle), radius * np.sin(angle)], 1)
    return q


def boundary_sigmas(k: int) -> np.ndarray:
    """Footprints on and one float32 either side of every level boundary from k to log2(RES)."""
    exact = np.asarray([2.0**j / RES for j in range(k, int(np.log2(RES)) + 1)], np.float32)
    return np.concatenate([exact, np.nextafter(exact, np.float32(np.inf)), np.nextafter(exact, np.float32(0))])


def session(model: onnx.ModelProto, path):
    save_onnx(model, path)
    return load_material(path).run


@pytest.fixture(scope="module", params=[(True, 0, 0), (False, 0, 0), (True, 2 * RES, 0), (True, 2 * RES, 2 * RES)],
                ids=["offset", "no-offset", "base", "relief-base"])
def untrimmed(request, tmp_path_factory):
    config = MaterialConfig(resolution=RES, offset=request.param[0], base=request.param[1], relief=request.param[2])
    return build_onnx(config, random_weights(config, seed=4), "trim test"), config


@pytest.mark.parametrize("k", [1, 2, 4])
def test_bit_identical_above_the_cut_and_clamped_below(untrimmed, tmp_path, k):
    model, config = untrimmed
    full, trimmed = session(model, tmp_path / "full.onnx"), session(trim_model(model, k), tmp_path / "trim.onnx")
    q = queries(6000, k, np.random.default_rng(k).uniform(-2, config.levels + 1, 6000))
    edges = queries(3 * (config.levels - k + 1), 9, np.zeros(3 * (config.levels - k + 1)))
    edges[:, C.SIGMA] = boundary_sigmas(k)
    q = np.concatenate([q, edges])
    level = C.level_of_detail(q[:, C.SIGMA].astype(np.float64), RES)
    above = (q[:, C.SIGMA].astype(np.float64) * RES >= 2.0**k)  # the graph's own test, in float
    assert above.sum() > 500 and (~above).sum() > 500
    a, b = run_chunked(full, q), run_chunked(trimmed, q)
    np.testing.assert_array_equal(b[above], a[above])
    assert not np.array_equal(b[~above & (level < k - 0.5)], a[~above & (level < k - 0.5)])  # finer levels gone
    if config.base or config.relief:
        return  # the base maps' and the relief's lookups read the query's own footprint, not level k's
    clamped = q[~above].copy()
    clamped[:, C.SIGMA] = np.float32(2.0**k / RES)  # what they read instead: level k
    np.testing.assert_array_equal(b[~above], run_chunked(full, clamped))


def test_trim_equals_an_export_at_that_level_and_trims_again(untrimmed, tmp_path):
    """The writer with `finest_level` and the reader-side edit make the same graph; trimming a trimmed
    model further is the same as trimming once, and the record keeps the original size."""
    model, config = untrimmed
    weights = random_weights(config, seed=4)
    weights["pyramid"] = weights["pyramid"][config.level_starts()[2]:]
    built = session(build_onnx(config, weights, "trim test", finest_level=2), tmp_path / "built.onnx")
    twice = trim_model(trim_model(model, 1), 2)
    q = queries(4000, 7, np.random.default_rng(7).uniform(-1, 5, 4000))
    np.testing.assert_array_equal(run_chunked(session(twice, tmp_path / "t.onnx"), q), run_chunked(built, q))
    record = current_trim(twice)
    assert (record.finest_level, record.finest_resolution, record.levels_cut) == (2, 4, [16, 8])
    assert record.texels_cut == 16 * 16 + 8 * 8 and record.bytes_before == model.ByteSize()
    assert twice.ByteSize() < model.ByteSize() - 4 * config.channels * record.texels_cut
    # nothing to cut: the same model, bit for bit
    assert trim_model(twice, 2).SerializeToString() == twice.SerializeToString()
    assert trim_model(model, 0).SerializeToString() == model.SerializeToString()
    with pytest.raises(TrimError, match=r"finest level must be in \[2, 4\]"):
        trim_model(twice, 1)
    with pytest.raises(TrimError, match="finest level"):
        trim_model(model, config.levels + 1)


def test_refuses_a_graph_of_another_layout(untrimmed):
    model, config = untrimmed
    tampered = onnx.ModelProto()
    tampered.CopyFrom(model)
    clip = clip_node(tampered.graph, config)
    init = next(i for i in tampered.graph.initializer if i.name == clip.input[1])
    init.CopyFrom(onnx.numpy_helper.from_array(np.asarray(0.5, np.float32), init.name))
    with pytest.raises(TrimError, match="not what this export writes"):
        trim_model(tampered, 1)
    no_meta = onnx.ModelProto()
    no_meta.CopyFrom(model)
    del no_meta.metadata_props[:]
    with pytest.raises(ModelError, match="no neumip metadata"):  # the model-file reader's one error
        trim_model(no_meta, 1)


def test_cli_from_a_budget_and_the_listing(tmp_path, capsys, model_dir):
    budget = tmp_path / "budget.json"
    budget.write_text(json.dumps({"materials": [{"material": "rand16", "finest_level": 2}]}))
    out = tmp_path / "rand16.onnx"
    assert main(["trim", str(model_dir / "rand16.onnx"), "--budget", str(budget), "-o", str(out)]) == 0
    assert "finest level 2" in capsys.readouterr().out
    info = load_material(out).info()
    assert info["trim"]["finest_level"] == 2 and info["trim"]["levels_cut"] == [16, 8]
    assert info["bytes"] < (model_dir / "rand16.onnx").stat().st_size
    assert load_material(model_dir / "rand16.onnx").info()["trim"] is None
    assert main(["trim", str(model_dir / "rand16.onnx"), "--budget", str(budget), "-o", str(out)]) != 0
    assert "exists" in capsys.readouterr().err
    assert main(["trim", str(model_dir / "flat16.onnx"), "--budget", str(budget), "-o",
                 str(tmp_path / "x.onnx")]) != 0
    assert "no material 'flat16'" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()


def test_train_takes_its_resolution_from_a_budget(tmp_path, capsys):
    import argparse

    from neumip.training.commands import _budget_resolution
    from neumip.training.export.trim import TrimError

    budget = tmp_path / "budget.json"
    budget.write_text(json.dumps({"materials": [
        {"material": "rock", "finest_level": 1, "recommended_resolution": 32},
        {"material": "yarn", "finest_level": 0, "recommended_resolution": 512}]}))
    data = tmp_path / "data"
    data.mkdir()
    (data / "meta.json").write_text(json.dumps({"generator": {"resolution": 64}}))

    def args(**kw):
        return argparse.Namespace(**{"budget": budget, "material": None, "data": str(data), **kw})

    assert _budget_resolution(args(), tmp_path / "rock.onnx") == 32
    assert "regenerate" not in capsys.readouterr().out
    assert _budget_resolution(args(material="yarn"), tmp_path / "out.onnx") == 512
    assert "neumip generate --resolution 512" in capsys.readouterr().out
    assert _budget_resolution(args(budget=None), tmp_path / "rock.onnx") is None
    with pytest.raises(TrimError, match="no material 'foam'"):
        _budget_resolution(args(), tmp_path / "foam.onnx")
