"""`neumip export-repository`: every config.pbtxt parses against Triton's real ModelConfig schema, the
ONNX files travel unchanged, and bad input is refused without writing anything."""

from __future__ import annotations

import importlib.metadata
import shutil
from pathlib import Path

import pytest

from neumip.client.cli import main
from neumip.server import triton_python_model
from neumip.server.model_config import TritonOptions, model_config, to_pbtxt

pytest.importorskip("tritonclient.grpc", reason="needs tritonclient[grpc] (Triton's ModelConfig schema)")
from google.protobuf import text_format  # noqa: E402
from tritonclient.grpc import model_config_pb2 as pb  # noqa: E402


def parse(path) -> pb.ModelConfig:
    """Parse like Triton does: a field or value its schema lacks raises ParseError."""
    return text_format.Parse(path.read_text(), pb.ModelConfig())


@pytest.fixture(scope="module")
def repositories(model_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("repos")
    assert main(["export-repository", str(model_dir), "-o", str(out / "ort"), "--instances", "2", "--threads", "1"]) == 0
    assert main(["export-repository", str(model_dir), "-o", str(out / "py"), "--backend", "python"]) == 0
    return out


def test_onnxruntime_repository_is_a_valid_triton_repository(repositories, model_dir):
    repo = repositories / "ort"
    names = sorted(p.stem for p in model_dir.glob("*.onnx"))
    assert sorted(p.name for p in repo.iterdir() if p.is_dir()) == names
    for name in names:
        config = parse(repo / name / "config.pbtxt")
        assert config.name == name and config.platform == "onnxruntime_onnx" and config.backend == "onnxruntime"
        assert config.max_batch_size > 0
        # any width: (N, 7) queries or (N, 5 + 2 K) query groups -> (N, 3 K)
        assert [(t.name, list(t.dims), t.data_type) for t in config.input] == [("queries", [-1], pb.TYPE_FP32)]
        assert [(t.name, list(t.dims), t.data_type) for t in config.output] == [("rgb", [-1], pb.TYPE_FP32)]
        batching = config.dynamic_batching
        assert list(batching.preferred_batch_size) and batching.max_queue_delay_microseconds > 0
        assert max(batching.preferred_batch_size) <= config.max_batch_size
        assert [(g.kind, g.count) for g in config.instance_group] == [(pb.ModelInstanceGroup.KIND_CPU, 2)]
        assert config.parameters["intra_op_thread_count"].string_value == "1"
        assert list(config.version_policy.specific.versions) == [1]
        # the ONNX file (graph and metadata) is copied unchanged
        assert (repo / name / "1" / "model.onnx").read_bytes() == (model_dir / f"{name}.onnx").read_bytes()
        assert not (repo / name / "1" / "model.py").exists()
    readme = (repo / "README.md").read_text()
    assert f"neumip {importlib.metadata.version('neumip')}" in readme
    assert all(f"`{name}`" in readme for name in names)


def test_python_backend_repository(repositories, model_dir):
    repo = repositories / "py"
    for path in model_dir.glob("*.onnx"):
        config = parse(repo / path.stem / "config.pbtxt")
        assert config.backend == "python" and config.platform == "" and config.max_batch_size > 0
        model_py = repo / path.stem / "1" / "model.py"
        assert model_py.read_text() == open(triton_python_model.__file__).read()
    assert "backend `python`" in (repo / "README.md").read_text()


def test_a_model_file_of_contract_version_1_is_refused_naming_its_upgrade(tmp_path, capsys):
    """Exported before query groups were part of the contract: no repository is written, and the error
    names the command that upgrades the file."""
    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(Path(__file__).parents[1] / "data" / "pre_issue12_offset.onnx", models / "old.onnx")
    assert main(["export-repository", str(models), "-o", str(tmp_path / "repo")]) != 0
    assert f"neumip export {models / 'old.onnx'} -o NEW.onnx" in capsys.readouterr().err
    assert not (tmp_path / "repo").exists()


def test_batching_follows_the_server_settings(model_dir, tmp_path, monkeypatch):
    monkeypatch.setenv("NEUMIP_CHUNK_ROWS", "512")
    monkeypatch.setenv("NEUMIP_MAX_WAIT_MS", "0.5")
    monkeypatch.setenv("NEUMIP_MAX_ROWS", "4096")
    assert main(["export-repository", str(model_dir), "-o", str(tmp_path / "repo")]) == 0
    config = parse(tmp_path / "repo" / "rand16" / "config.pbtxt")
    assert config.max_batch_size == 4096
    assert list(config.dynamic_batching.preferred_batch_size) == [512]
    assert config.dynamic_batching.max_queue_delay_microseconds == 500


@pytest.mark.parametrize("text", [
    to_pbtxt({"name": "x", "max_batch_sizes": 8}),  # a field Triton does not know
    'name: "x"\nmax_batch_size: "many"\n',  # a string for an integer
    'name: "x"\ninstance_group [ { kind: CPU } ]\n',  # an enum value that does not exist
    'name: "x"\ninput [ { name: "q" dims: [ 7.5 ] } ]\n',  # a float for int64 dims
])
def test_a_field_triton_would_refuse_fails_to_parse(text, tmp_path):
    (tmp_path / "config.pbtxt").write_text(text)
    with pytest.raises(text_format.ParseError):
        parse(tmp_path / "config.pbtxt")


def test_options_are_checked():
    with pytest.raises(ValueError, match="backend"):
        TritonOptions(8, 8, 0, backend="tensorrt")
    with pytest.raises(ValueError, match=">= 1"):
        model_config("x", TritonOptions(0, 8, 0))


def test_corrupt_material_writes_nothing(model_dir, tmp_path, capsys):
    models = tmp_path / "models"
    models.mkdir()
    (models / "good.onnx").write_bytes((model_dir / "rand16.onnx").read_bytes())
    (models / "bad.onnx").write_bytes(b"\x08\x07 truncated")
    assert main(["export-repository", str(models), "-o", str(tmp_path / "repo")]) == 2
    assert "bad" in capsys.readouterr().err
    assert not (tmp_path / "repo").exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no staging left behind


def test_existing_repository_is_kept_unless_forced(model_dir, tmp_path, capsys):
    out = tmp_path / "repo"
    out.mkdir()
    (out / "mine.txt").write_text("keep me")
    assert main(["export-repository", str(model_dir), "-o", str(out)]) == 2
    assert "--force" in capsys.readouterr().err and (out / "mine.txt").read_text() == "keep me"
    assert main(["export-repository", str(model_dir), "-o", str(out), "--force"]) == 0
    assert not (out / "mine.txt").exists() and (out / "rand16" / "config.pbtxt").is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["repo"]
    assert main(["export-repository", str(tmp_path / "none"), "-o", str(tmp_path / "r2")]) == 2
