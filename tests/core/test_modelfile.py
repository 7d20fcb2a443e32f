"""The one model-file reader (`core.modelfile`): what a file declares, and one ModelError naming the
file for anything wrong with it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from neumip.core import contract as C
from neumip.core.config import MaterialConfig
from neumip.core.errors import NeumipError
from neumip.core.modelfile import ModelError, TrimRecord, read_model_file

DATA = Path(__file__).parents[1] / "data"


def with_metadata(src: Path, dst: Path, changes: dict[str, str]) -> Path:
    """`src` saved as `dst` with the metadata `changes` made."""
    model = onnx.load(str(src))
    meta = {**{p.key: p.value for p in model.metadata_props}, **changes}
    del model.metadata_props[:]
    helper.set_model_props(model, meta)
    onnx.save(model, str(dst))
    return dst


def test_an_exported_file_reads_whole(model_dir):
    file = read_model_file(model_dir / "rand16.onnx", initializers=True)
    assert file.name == "rand16.onnx" and file.size == (model_dir / "rand16.onnx").stat().st_size
    assert file.config == MaterialConfig(resolution=16) and file.description == "random test material"
    assert file.trim is None and file.finest_level == 0 and file.sampling is None and file.version_problem is None
    assert file.metadata[C.META_CONTRACT] == C.CONTRACT_VERSION
    model = onnx.load(str(model_dir / "rand16.onnx"))
    assert file.metadata == {p.key: p.value for p in model.metadata_props}
    want = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    assert file.initializers.keys() == want.keys()
    for name, value in want.items():  # the same bits, dtype and shape as onnx's own reader
        got = file.initializers[name]
        assert got.dtype == value.dtype and got.shape == value.shape and got.tobytes() == value.tobytes(), name
    assert read_model_file(model_dir / "rand16.onnx").initializers is None  # only on request


@pytest.mark.parametrize("data, words", [
    (b"\x00\x01 not onnx", "cannot load ONNX model"),
    (b"not an onnx file", "cannot load ONNX model"),
    (None, "cannot load ONNX model"),  # truncated: half of a good file
])
def test_corrupt_bytes_are_one_error_naming_the_file(model_dir, data, words):
    good = (model_dir / "rand16.onnx").read_bytes()
    with pytest.raises(ModelError, match=f"^bad.onnx: {words}"):
        read_model_file("somewhere/bad.onnx", good[: len(good) // 2] if data is None else data)


def test_an_unreadable_file_is_the_same_error(tmp_path):
    with pytest.raises(ModelError, match="missing.onnx: cannot read"):
        read_model_file(tmp_path / "missing.onnx")
    assert issubclass(ModelError, NeumipError)


@pytest.mark.parametrize("key, value, words", [
    (C.META_CONFIG, "{not json", "bad neumip.config metadata"),
    (C.META_CONFIG, '{"resolution": 16, "colour": 3}', "bad neumip.config metadata"),  # no such field
    (C.META_CONFIG, "[16]", "bad neumip.config metadata: not a JSON object"),
    (C.META_TRIM, "{", "bad neumip.trim metadata"),
    (C.META_TRIM, '{"finest_level": 1}', "bad neumip.trim metadata"),  # fields missing
    (C.META_VALIDATION, "nan nan", "bad neumip.validation metadata"),
    (C.META_SAMPLING, '{"alpha": 2, "weight": 0.5}', "bad neumip.sampling metadata"),
])
def test_bad_metadata_is_one_error(model_dir, tmp_path, key, value, words):
    path = with_metadata(model_dir / "rand16.onnx", tmp_path / "meta.onnx", {key: value})
    with pytest.raises(ModelError, match=f"meta.onnx: {words}"):
        read_model_file(path)


def test_a_non_finite_weight_is_refused_naming_the_tensor(model_dir, tmp_path, write_nan_weight):
    write_nan_weight(model_dir / "rand16.onnx", tmp_path / "nan.onnx")
    with pytest.raises(ModelError, match=r"^nan.onnx: non-finite weights in pyramid$"):
        read_model_file(tmp_path / "nan.onnx")


def test_a_foreign_graph_reads_without_config_until_one_is_needed(tmp_path, checkerboard):
    onnx.save(checkerboard(), str(tmp_path / "checker.onnx"))
    file = read_model_file(tmp_path / "checker.onnx", initializers=True)
    assert file.config is None and file.metadata == {} and file.config_dict() == {}
    assert file.initializers["starts"].dtype == np.int64 and file.finest_level == 0
    with pytest.raises(ModelError, match=r"^checker.onnx has no neumip metadata \(a foreign graph\): the budget$"):
        file.require_config("the budget")


def test_another_contract_version_is_refused_naming_the_upgrade(model_dir, tmp_path):
    future = with_metadata(model_dir / "rand16.onnx", tmp_path / "future.onnx", {C.META_CONTRACT: "999"})
    with pytest.raises(ModelError, match="future.onnx: query contract version '999'"):
        read_model_file(future)
    old = DATA / "pre_groups_offset.onnx"
    with pytest.raises(ModelError, match=f"version 1 .*`neumip export {old} -o NEW.onnx`"):
        read_model_file(old)
    upgradable = read_model_file(old, any_version=True)  # as `neumip export` reads it
    assert "version 1" in upgradable.version_problem and upgradable.config is not None


def test_a_trimmed_file_declares_its_finest_level(model_dir):
    from neumip.training.export.trim import trim_model

    model = trim_model(onnx.load(str(model_dir / "rand16.onnx")), 2)
    file = read_model_file("trimmed.onnx", model.SerializeToString())
    assert isinstance(file.trim, TrimRecord) and file.finest_level == 2
    assert file.trim.levels_cut == [16, 8] and file.trim.finest_resolution == 4


def test_the_reader_needs_no_onnx_package(model_dir):
    """The base install has numpy and ONNX Runtime only: the reader imports no onnx, and reads a file."""
    code = ("import sys; sys.modules['onnx'] = None; from neumip.core.modelfile import read_model_file; "
            f"f = read_model_file({str(model_dir / 'rand16.onnx')!r}, initializers=True); "
            "print(f.config.resolution, len(f.initializers))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[0] == "16"
