"""Several model folders as one, as PATH joins folders: the first that holds a name serves it."""

from __future__ import annotations

import os
import shutil

import pytest

from neumip.engines.folder import ModelFolder, list_models, model_folders


def test_the_first_folder_holding_a_name_serves_it(model_dir, tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    shutil.copy(model_dir / "lambert.onnx", mine / "rand16.onnx")  # mine/rand16 hides the other folder's
    shutil.copy(model_dir / "flat16.onnx", mine / "only_mine.onnx")
    spec = f"{mine}{os.pathsep}{model_dir}"
    assert model_folders(spec) == [mine, model_dir]
    named, _ = list_models(spec)
    assert named["rand16"] == mine / "rand16.onnx" and named["flat16"] == model_dir / "flat16.onnx"
    for lazy in (False, True):
        folder = ModelFolder(spec, lambda path, data: path, lazy=lazy)
        assert folder.get("rand16") == mine / "rand16.onnx" and folder.get("only_mine") == mine / "only_mine.onnx"
        assert folder.get("lambert") == model_dir / "lambert.onnx"


def test_a_missing_folder_among_several_is_named(model_dir, tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere"):
        ModelFolder(f"{model_dir}{os.pathsep}{tmp_path / 'nowhere'}", lambda path, data: path)
