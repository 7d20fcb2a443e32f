"""Reading an exported model's weights back (`training.export.read`): re-exporting a model this version wrote
gives the same bytes, the shipped models are in this version's layout, `neumip export MODEL.onnx`
rewrites a model file and refuses what it cannot read, and upgrades files of contract version 1
(`upgrade`) that every engine refuses."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import onnx
import pytest

from neumip.core import contract as C
from neumip.client.cli import main
from neumip.engines.local import ModelError, load_material, run_chunked
from neumip.core import weights as W
from neumip.core.config import MaterialConfig
from neumip.training.export.graph import build_onnx, random_weights, save_onnx
from neumip.training.export.read import ModelLayoutError, metadata, read_model
from neumip.training.export.upgrade import answer_difference, reexport
from neumip.training.export.trim import trim_model

BASE = MaterialConfig(resolution=16)
CONFIGS = {
    "offset": BASE,
    "no-offset": replace(BASE, offset=False),
    "one-layer": replace(BASE, layers=1),
    "yuv": replace(BASE, head="yuv", channels=5, hidden=9, offset_scale=0.37),
    "half-vector": replace(BASE, half_vector=True, channels=5),
    "base": replace(BASE, base=32),
    "relief": replace(BASE, relief=32, relief_steps=4),
    "local-frame": replace(BASE, base=32, local_frame=True, half_vector=True),
    "no-terminator": replace(BASE, base=32, terminator="none"),
    "visibility-input": replace(BASE, base=32, local_frame=True, half_vector=True, visibility_input=True),
    "coarse-decoder": replace(BASE, half_vector=True, coarse_decoder=2),
}
SHIPPED = sorted(Path("models").glob("*.onnx"))


@pytest.mark.parametrize("name", list(CONFIGS))
def test_reexport_of_an_export_is_the_same_bytes(name):
    config = CONFIGS[name]
    model = build_onnx(config, random_weights(config, seed=3), "round trip", {"neumip.validation": "{}"})
    assert reexport(model).SerializeToString() == model.SerializeToString()
    for trimmed in (trim_model(model, 2), trim_model(trim_model(model, 1), 3)):
        assert reexport(trimmed).SerializeToString() == trimmed.SerializeToString()


@pytest.mark.parametrize("name", ["offset", "coarse-decoder"])
def test_weights_read_back_are_the_weights_written(name):
    """Every weight exactly (both decoders' too), but the offset MLP's last layer: stored times offset_scale, it is
    read back as weights that scale to the same float32 bits."""
    config = CONFIGS[name]
    weights = random_weights(config, seed=5)
    got_config, got, meta, finest = read_model(build_onnx(config, weights, "w"))
    assert got_config == config and finest == 0 and meta["neumip.description"] == "w"
    assert set(got) == set(weights)
    last = f"offset_mlp.{config.layers - 1}"
    for name, value in weights.items():
        if name.startswith(last):
            assert np.array_equal(got[name] * np.float32(config.offset_scale), value * np.float32(config.offset_scale))
        else:
            assert np.array_equal(got[name], value), name


@pytest.mark.skipif(not SHIPPED, reason="no shipped models")
@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_models_are_in_this_versions_layout(path):
    """So `neumip trim` and everything that reads the graph's constants works on them."""
    model = onnx.load(str(path))
    assert reexport(model).SerializeToString() == model.SerializeToString()


def test_a_graph_of_another_layout_is_refused_by_name():
    config = CONFIGS["offset"]
    model = build_onnx(config, random_weights(config, seed=1))
    init = next(i for i in model.graph.initializer if i.name == W.half_weight(W.DECODER, 0, "query"))
    init.name = "decoder.0.weight"  # as an older export named its layers
    with pytest.raises(ModelLayoutError, match="no initializer 'decoder.0.half_weight.query'"):
        read_model(model)
    model = build_onnx(config, random_weights(config, seed=1))
    init = next(i for i in model.graph.initializer if i.name == W.bias(W.DECODER, 2))
    init.CopyFrom(onnx.numpy_helper.from_array(np.zeros((24, 1), np.float32), init.name))
    with pytest.raises(ModelLayoutError, match=r"'decoder.2.bias' of shape \(24, 1\), this export writes \(25, 1\)"):
        read_model(model)
    del model.metadata_props[:]
    with pytest.raises(ModelLayoutError, match="no neumip metadata"):
        read_model(model)


def test_initializer_shapes_are_what_the_export_writes():
    """`core.weights` states the stored weights' names and shapes: exactly the graph's initializers of
    those names, for every config and a trimmed pyramid."""
    for config in CONFIGS.values():
        model = build_onnx(config, random_weights(config, seed=4))
        for finest, m in ((0, model), (2, trim_model(model, 2))):
            stored = {i.name: tuple(i.dims) for i in m.graph.initializer}
            want = W.initializer_shapes(config, finest)
            assert {name: stored.get(name) for name in want} == want


def test_cli_rewrites_a_model_and_refuses_bad_input(tmp_path, capsys):
    config = CONFIGS["offset"]
    source = save_onnx(build_onnx(config, random_weights(config, seed=2), "cli"), tmp_path / "m.onnx")
    out = tmp_path / "new.onnx"
    assert main(["export", str(source), "-o", str(out)]) == 0
    assert "largest answer difference" in capsys.readouterr().out
    assert out.read_bytes() == source.read_bytes()
    assert main(["export", str(source), "-o", str(out)]) != 0  # exists, no --force
    assert "exists" in capsys.readouterr().err
    broken = tmp_path / "broken.onnx"
    broken.write_bytes(source.read_bytes()[: 1000])
    assert main(["export", str(broken), "-o", str(tmp_path / "x.onnx")]) != 0
    assert "cannot re-export" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()
    flipped = tmp_path / "flipped.onnx"  # whole, but a node's name is no longer UTF-8: its graph cannot run
    data = source.read_bytes()
    assert b"matmul" in data
    flipped.write_bytes(data.replace(b"matmul", b"m\xa0tmul", 1))
    assert main(["export", str(flipped), "-o", str(tmp_path / "y.onnx")]) != 0
    assert "cannot re-export" in capsys.readouterr().err
    assert not (tmp_path / "y.onnx").exists()  # nothing written, so the same command may run again


LAYOUTS = {
    "pre_issue12": "decoder.1.weight",  # row-major MLPs (commit 3a4acaa)
    "pre_groups": "decoder.1.half_weight",  # column-major, a fixed 7-column input (commit 5889f6e)
}


def groups_of_two(n: int) -> np.ndarray:
    return np.ascontiguousarray(np.concatenate([C.random_queries(n, seed=1), C.random_queries(n, seed=2)[:, 3:5]], 1))


@pytest.mark.parametrize("layout", list(LAYOUTS))
@pytest.mark.parametrize("name", ["offset", "nooffset"])
def test_a_version_1_file_of_an_older_layout_is_upgraded(layout, name, tmp_path, capsys):
    """Tiny models written by older exports under contract version 1 (kept as test data): the engines
    refuse them naming the upgrade; `neumip export OLD.onnx` rewrites them in this version and layout
    with the same answers up to rounding (query groups changed the order of the decoder's first sum),
    and the rewritten model takes query groups."""
    source = Path(__file__).parents[2] / "data" / f"{layout}_{name}.onnx"
    old = onnx.load(str(source))
    assert LAYOUTS[layout] in {i.name for i in old.graph.initializer}
    assert old.graph.input[0].type.tensor_type.shape.dim[1].dim_value == C.QUERY_DIM  # fixed width
    with pytest.raises(ModelError, match=f"`neumip export {source} -o NEW.onnx`"):
        load_material(source)
    with pytest.raises(ModelLayoutError, match="version 1"):
        read_model(old)
    new = reexport(old)
    assert answer_difference(old, new, n=1 << 15) < 1e-5
    assert reexport(new).SerializeToString() == new.SerializeToString()  # now in this layout
    out = tmp_path / "new.onnx"
    assert main(["export", str(source), "-o", str(out)]) == 0
    assert "largest answer difference" in capsys.readouterr().out
    trim_model(onnx.load(str(out)), 1)  # trim reads it now
    session = load_material(out).run
    groups = groups_of_two(64)
    np.testing.assert_array_equal(run_chunked(session, groups), run_chunked(session, C.ungroup(groups)).reshape(64, 6))


@pytest.mark.skipif(not SHIPPED, reason="no shipped models")
def test_a_version_1_file_made_from_a_shipped_model_is_refused_then_upgraded_to_the_same_bits(tmp_path, capsys):
    """The shipped rock as version 1 wrote it (the same graph, `neumip.contract_version` "1"): every
    loader refuses it naming `neumip export`, which gives back the shipped file, answering with the
    same bits (the graph is unchanged)."""
    model = onnx.load("models/rock.onnx")
    onnx.helper.set_model_props(model, {**{p.key: p.value for p in model.metadata_props}, C.META_CONTRACT: "1"})
    old = save_onnx(model, tmp_path / "old.onnx")
    with pytest.raises(ModelError, match="query contract version 1 .*this build reads version 2"):
        load_material(old)
    with pytest.raises(ModelLayoutError, match="neumip export"):
        read_model(model)
    new = tmp_path / "new.onnx"
    assert main(["export", str(old), "-o", str(new)]) == 0
    assert "largest answer difference from" in capsys.readouterr().out
    assert new.read_bytes() == Path("models/rock.onnx").read_bytes()
    assert answer_difference(model, onnx.load(str(new)), n=1 << 14) == 0.0


def test_cli_declares_a_materials_sampling_lobe(tmp_path, capsys):
    """`neumip export M.onnx -o NEW.onnx --material NAME` writes the lobe of NAME's maps (or removes the
    file's own where NAME's maps have none); the answers stay the same."""
    from neumip.groundtruth.lobe import material_lobe

    config = CONFIGS["offset"]
    source = save_onnx(build_onnx(config, random_weights(config, seed=2), "cli"), tmp_path / "m.onnx")
    glossy, matte = tmp_path / "glossy.onnx", tmp_path / "matte.onnx"
    assert main(["export", str(source), "-o", str(glossy), "--material", "turtle"]) == 0
    assert "sampling lobe of turtle: SamplingLobe(alpha=" in capsys.readouterr().out
    lobe = C.sampling_lobe(metadata(onnx.load(str(glossy))))
    assert lobe is not None and lobe == material_lobe("turtle")
    assert main(["export", str(glossy), "-o", str(matte), "--material", "flat"]) == 0
    assert C.META_SAMPLING not in metadata(onnx.load(str(matte)))
    assert main(["export", str(glossy), "-o", str(tmp_path / "x.onnx"), "--material", "no-such-material"]) != 0
    assert "--material no-such-material" in capsys.readouterr().err
