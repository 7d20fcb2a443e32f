"""Writing a file atomically (`core.files`): a failed write leaves the old file and no temporary file."""

from __future__ import annotations

import pytest

from neumip.core.files import atomic_write, write_bytes_atomic, write_text_atomic


def test_a_write_replaces_the_file_and_leaves_nothing_else(tmp_path):
    path = tmp_path / "model.onnx"
    path.write_bytes(b"old")
    assert write_bytes_atomic(path, b"new") == path
    assert path.read_bytes() == b"new"
    write_text_atomic(tmp_path / "meta.json", "{}\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["meta.json", "model.onnx"]


@pytest.mark.parametrize("error", [OSError("disk full"), KeyboardInterrupt()])
def test_a_failed_write_leaves_the_old_file_and_no_temporary_file(tmp_path, error):
    path = tmp_path / "model.onnx"
    path.write_bytes(b"old")
    seen = []

    def write(tmp):
        seen.append(tmp)
        tmp.write_bytes(b"half")  # part written, then the failure
        raise error

    with pytest.raises(type(error)):
        atomic_write(path, write)
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["model.onnx"]
    assert seen[0].parent == tmp_path and seen[0].name.startswith(".model.onnx.")  # beside it, hidden
    assert not seen[0].name.endswith(".onnx")  # a folder listed by suffix never shows it


def test_a_failed_first_write_leaves_no_file(tmp_path):
    with pytest.raises(ValueError):
        atomic_write(tmp_path / "new.png", lambda tmp: (tmp.write_bytes(b"x"), int("bad")), keep_suffix=True)
    assert list(tmp_path.iterdir()) == []


def test_keep_suffix_names_the_temporary_file_by_the_target_suffix(tmp_path):
    names = []
    atomic_write(tmp_path / "image.exr", lambda tmp: (names.append(tmp.name), tmp.write_bytes(b"x")), keep_suffix=True)
    assert names[0].endswith(".exr") and (tmp_path / "image.exr").read_bytes() == b"x"
    temporary = []
    atomic_write(tmp_path / "a.onnx", lambda tmp: (temporary.append(tmp.name), tmp.write_bytes(b"1")))
    atomic_write(tmp_path / "a.onnx", lambda tmp: (temporary.append(tmp.name), tmp.write_bytes(b"2")))
    assert temporary[0] != temporary[1]  # unique per call: concurrent writers do not collide
