"""`neumip trim`: answers above the cut are bit-identical (level boundaries and the offset included) in every
pyramid (the latents, the base maps, the relief's heights, the offset's with `offset_mip`, at resolutions finer, equal or coarser than the
latents'), finer queries read the finest level kept, what was cut travels in the metadata, and no quad table is
stored (the graph computes each from a few kilobytes)."""

from __future__ import annotations

import json

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.client.cli import main
from neumip.engines.local import load_material, run_chunked
from neumip.core.config import MaterialConfig
from neumip.core.modelfile import ModelError
from neumip.training.export.graph import build_onnx, random_weights, save_onnx
from neumip.training.export.lod import pyramids
from neumip.training.export.lookup import quad_vectors
from neumip.training.export.trim import TrimError, current_trim, trim_model, trimmed_weights

RES = 16


def queries(n: int, seed: int, levels: np.ndarray, lod_bias: int = 0) -> np.ndarray:
    """(n, 7) queries at continuous `levels` (of a RES^2 model of `lod_bias`), spread positions and directions."""
    rng = np.random.default_rng(seed)
    q = np.zeros((n, C.QUERY_DIM), np.float32)
    q[:, [C.U, C.V]] = rng.uniform(-3, 4, (n, 2))
    q[:, C.SIGMA] = (2.0 ** (levels - lod_bias) / RES).astype(np.float32)
    for cols in ([C.WI_X, C.WI_Y], [C.WO_X, C.WO_Y]):
        angle, radius = rng.uniform(0, 2 * np.pi, n), np.sqrt(rng.uniform(0, 0.98, n))
        q[:, cols] = np.stack([radius * np.cos(angle), radius * np.sin(angle)], 1)
    return q


def boundary_sigmas(k: int, lod_bias: int = 0) -> np.ndarray:
    """Footprints on and one float32 either side of every level boundary from k to log2(RES)."""
    exact = np.asarray([2.0 ** (j - lod_bias) / RES for j in range(k, int(np.log2(RES)) + 1)], np.float32)
    return np.concatenate([exact, np.nextafter(exact, np.float32(np.inf)), np.nextafter(exact, np.float32(0))])


def session(model: onnx.ModelProto, path):
    save_onnx(model, path)
    return load_material(path).run


CONFIGS = {  # (offset, base, relief, lod_bias[, offset_mip[, coarse_decoder]]): maps finer than, as fine as and coarser than the latents
    "offset": (True, 0, 0, 0),
    "offset-mip": (True, 0, 0, 0, True),
    "offset-mip-maps": (True, RES, RES, 1, True),
    "no-offset": (False, 0, 0, 0),
    "base": (True, 2 * RES, 0, 0),
    "relief-base": (True, 2 * RES, 2 * RES, 0),
    "maps-as-fine-biased": (True, RES, RES, 1),
    "maps-coarser": (False, RES // 2, RES // 4, 0),
    "coarse-decoder": (True, RES, RES, 1, True, 2),
}


def make_config(offset: bool, base: int, relief: int, lod_bias: int, offset_mip: bool = False,
                coarse_decoder: int = 0) -> MaterialConfig:
    return MaterialConfig(resolution=RES, offset=offset, base=base, relief=relief, relief_steps=4, lod_bias=lod_bias,
                          local_frame=bool(base), visibility_input=bool(base), offset_mip=offset_mip,
                          coarse_decoder=coarse_decoder)


@pytest.fixture(scope="module", params=list(CONFIGS.values()), ids=list(CONFIGS))
def untrimmed(request, tmp_path_factory):
    config = make_config(*request.param)
    return build_onnx(config, random_weights(config, seed=4), "trim test"), config


@pytest.mark.parametrize("k", [1, 2, 4])
def test_bit_identical_above_the_cut_and_clamped_below(untrimmed, tmp_path, k):
    model, config = untrimmed
    b_ = config.lod_bias
    full, trimmed = session(model, tmp_path / "full.onnx"), session(trim_model(model, k), tmp_path / "trim.onnx")
    q = queries(6000, k, np.random.default_rng(k).uniform(-2, config.levels + 1, 6000), b_)
    edges = queries(3 * (config.levels - k + 1), 9, np.zeros(3 * (config.levels - k + 1)))
    edges[:, C.SIGMA] = boundary_sigmas(k, b_)
    q = np.concatenate([q, edges])
    level = C.level_of_detail(q[:, C.SIGMA].astype(np.float64), RES, b_)
    above = (q[:, C.SIGMA].astype(np.float64) * RES * 2.0**b_ >= 2.0**k)  # the graph's own test, in float
    assert above.sum() > 500 and (~above).sum() > 500
    a, b = run_chunked(full, q), run_chunked(trimmed, q)
    np.testing.assert_array_equal(b[above], a[above])
    assert not np.array_equal(b[~above & (level < k - 0.5)], a[~above & (level < k - 0.5)])  # finer levels gone
    if any(k + p.config.levels - config.levels < 0 for p in pyramids(config)):
        return  # maps coarser than level k's footprint keep their finest levels: they read the query's own
    clamped = q[~above].copy()
    clamped[:, C.SIGMA] = np.float32(2.0 ** (k - b_) / RES)  # what they read instead: level k (the maps': its footprint)
    np.testing.assert_array_equal(b[~above], run_chunked(full, clamped))


def test_every_pyramid_is_cut_and_no_quad_table_is_stored(untrimmed):
    model, config = untrimmed
    trimmed = trim_model(model, 2)
    for m, k in ((model, 0), (trimmed, 2)):
        inits = {i.name: i for i in m.graph.initializer}
        for p in pyramids(config):
            level = config.pyramid_finest_level(p.config, k)
            kept = p.config.atlas_rows() - p.config.level_starts()[level]  # texels of its levels kept
            if p.texture == W.OFFSET_TEXTURE and level == 0:
                kept = p.config.resolution**2  # the finest level alone: the graph derives the others
            assert inits[p.texture].dims[0] == kept == W.initializer_shapes(config, k)[p.texture][0], p.texture
            for name, value in quad_vectors(p.config.level_sizes(), level, p.prefix).items():
                np.testing.assert_array_equal(numpy_helper.to_array(inits[name]), value)
        ints = [i for i in m.graph.initializer if i.data_type == onnx.TensorProto.INT32]
        assert all(i.name.split("quad.")[0] in ("", "base.", "relief.", "offset.") for i in ints)
        assert sum(numpy_helper.to_array(i).size for i in ints) < 8 * sum(p.config.resolution for p in pyramids(config)) + 4 * RES
    if config.base or config.relief:
        maps = {p.texture for p in pyramids(config)} - {"pyramid"}
        sizes = {i.name: i.ByteSize() for i in model.graph.initializer}
        assert trimmed.ByteSize() < model.ByteSize() - 0.5 * sum(sizes[t] for t in maps) * (
            1 - 4.0 ** -min(config.pyramid_finest_level(p.config, 2) for p in pyramids(config) if p.texture in maps))


def test_trim_equals_an_export_at_that_level_and_trims_again(untrimmed, tmp_path):
    """The writer with `finest_level` and the reader-side edit make the same graph; trimming a trimmed
    model further is the same as trimming once, and the record keeps the original size."""
    model, config = untrimmed
    weights = random_weights(config, seed=4)
    built = build_onnx(config, trimmed_weights(config, weights, 2), "trim test", finest_level=2)
    twice = trim_model(trim_model(model, 1), 2)
    assert twice.graph.SerializeToString() == built.graph.SerializeToString()
    q = queries(4000, 7, np.random.default_rng(7).uniform(-1, 5, 4000))
    np.testing.assert_array_equal(run_chunked(session(twice, tmp_path / "t.onnx"), q),
                                  run_chunked(session(built, tmp_path / "built.onnx"), q))
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
    clips = [n for n in tampered.graph.node if n.op_type == "Clip"]  # one level-of-detail Clip per pyramid, in order
    clip = clips[[p.texture for p in pyramids(config)].index("pyramid")]  # the latents'
    init = next(i for i in tampered.graph.initializer if i.name == clip.input[1])
    init.CopyFrom(onnx.numpy_helper.from_array(np.asarray(0.5, np.float32), init.name))
    with pytest.raises(TrimError, match="not what this export writes"):
        trim_model(tampered, 1)
    for p in pyramids(config):  # the vectors of each pyramid's quad table: a wrong entry, or none
        level = config.pyramid_finest_level(p.config, 2)
        if level == 0:
            continue  # maps coarser than level 2's footprint: nothing of them is cut, nothing checked
        name = f"{p.prefix}quad.{level}.rows"
        for edit in ("entry", "none"):
            tampered.CopyFrom(model)
            if edit == "entry":
                vector = next(i for i in tampered.graph.initializer if i.name == name)
                rows = numpy_helper.to_array(vector).copy()
                rows[-1] += 1
                vector.CopyFrom(numpy_helper.from_array(rows, name))
            else:
                kept = [i for i in tampered.graph.initializer if i.name != name]
                del tampered.graph.initializer[:]
                tampered.graph.initializer.extend(kept)
            with pytest.raises(TrimError, match="not what this export writes|no initializer"):
                trim_model(tampered, 2)
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
