"""Model loading: corrupt and incompatible files are reported and the others still serve."""

from __future__ import annotations

import shutil

import onnx
import pytest
from fastapi.testclient import TestClient

from neumip.core import contract as C
from neumip.core import wire
from neumip.server.app import create_app
from neumip.server.registry import Registry
from neumip.server.settings import Settings
from neumip.core.contract import random_queries


@pytest.fixture(scope="module")
def mixed_dir(model_dir, tmp_path_factory):
    """rand16 (good), corrupt.onnx (random bytes), future.onnx (contract version 99), .hidden.onnx."""
    folder = tmp_path_factory.mktemp("mixed")
    shutil.copy(model_dir / "rand16.onnx", folder / "rand16.onnx")
    (folder / "corrupt.onnx").write_bytes(b"\x08\x07not an onnx file" * 100)
    model = onnx.load(model_dir / "flat16.onnx")
    for prop in model.metadata_props:
        if prop.key == C.META_CONTRACT:
            prop.value = "99"
    onnx.save(model, folder / "future.onnx")
    shutil.copy(model_dir / "rand16.onnx", folder / ".hidden.onnx")
    (folder / "notes.txt").write_text("not a model")
    return folder


def test_registry_reports_failures_and_keeps_the_rest(mixed_dir):
    registry = Registry.load(mixed_dir, warmup_rows=32)
    assert registry.names() == ["rand16"]
    assert set(registry.failed) == {"corrupt", "future", ".hidden"}
    assert "contract version '99'" in registry.failed["future"]
    assert "cannot load" in registry.failed["corrupt"]
    assert "corrupt.onnx" in registry.failed["corrupt"]  # the file name, but not where the server keeps it
    assert not any(str(mixed_dir.resolve()) in reason or str(mixed_dir) in reason for reason in registry.failed.values())


def test_missing_folder_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        Registry.load(tmp_path / "nope", warmup_rows=0)


def test_server_with_a_bad_model_serves_the_others(mixed_dir):
    with TestClient(create_app(Settings(model_dir=mixed_dir, warmup_rows=16))) as client:
        assert client.get("/v2/health/ready").status_code == 200
        assert client.get("/v2/models/rand16/ready").status_code == 200
        not_ready = client.get("/v2/models/future/ready")
        assert not_ready.status_code == 400 and not_ready.content == b""
        listing = client.get(wire.MATERIALS_PATH).json()
        assert [m["name"] for m in listing["materials"]] == ["rand16"]
        assert {f["name"] for f in listing["failed"]} == {"corrupt", "future", ".hidden"}
        resp = client.post(wire.EVALUATE_PATH.format(name="corrupt"), content=wire.encode_request(random_queries(4)),
                           headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
        assert resp.status_code == 400 and "failed to load" in resp.json()["error"]
        assert "corrupt.onnx" in resp.json()["error"] and str(mixed_dir) not in resp.text
        assert str(mixed_dir) not in client.get(wire.MATERIALS_PATH).text
        ok = client.post(wire.EVALUATE_PATH.format(name="rand16"), content=wire.encode_request(random_queries(4)),
                         headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
        assert ok.status_code == 200


def test_server_without_models_is_live_but_not_ready(tmp_path):
    with TestClient(create_app(Settings(model_dir=tmp_path))) as client:
        assert client.get("/v2/health/live").status_code == 200
        assert client.get("/v2/health/ready").status_code == 400
        assert client.get(wire.MATERIALS_PATH).json()["materials"] == []


def test_a_material_kept_over_the_budget_while_busy_goes_when_its_request_ends(model_dir, tmp_path):
    """Budget for one model: a second one loading while the first has a request in flight exceeds it
    (the busy one is never unloaded); when that request ends, the registry is back within budget at
    once, not only at the next load."""
    import asyncio

    for name in ("a", "b"):
        shutil.copy(model_dir / "rand16.onnx", tmp_path / f"{name}.onnx")
    size = (tmp_path / "a.onnx").stat().st_size
    registry = Registry.load(tmp_path, warmup_rows=0, lazy=True, memory_budget_bytes=int(1.5 * size))

    async def run() -> tuple[int, int]:
        async with registry.using("a"):
            async with registry.using("b"):
                busy = registry.resident_bytes()
        return busy, registry.resident_bytes()

    busy, idle = asyncio.run(run())
    assert busy == 2 * size  # both in flight: over the budget
    assert idle <= 1.5 * size and registry.names() == ["a", "b"]  # one unloaded, both still servable


def test_both_engines_refuse_non_finite_weights_at_load(model_dir, tmp_path, write_nan_weight):
    """Issue 27: the engines' NaN policies differed - the kernel engine refused a file with a NaN weight
    at load, ONNX Runtime served it and answered 500 for the rows that touched it. Both refuse it now,
    with the kernel engine's message (its test: tests/server/test_engine.py)."""
    from neumip.server.engine import Engine

    write_nan_weight(model_dir / "rand16.onnx", tmp_path / "nan.onnx")
    shutil.copy(model_dir / "flat16.onnx", tmp_path)
    registry = Registry.load(tmp_path, Engine.onnxruntime(), warmup_rows=16)
    assert sorted(registry.materials) == ["flat16"]
    assert registry.failed["nan"] == "nan.onnx: non-finite weights in pyramid"

    from neumip.core.modelfile import read_model_file

    assert read_model_file(model_dir / "rand16.onnx").config is not None  # the same reader accepts the good file
