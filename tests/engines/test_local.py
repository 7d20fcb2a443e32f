"""In-process evaluator: loading a folder, chunking, validation, bad files (no torch: tests/test_layers.py)."""

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest

from neumip.core import contract as C
from neumip.engines.local import LocalMaterials, ModelError, UnknownMaterial, load_material
from neumip.core.contract import random_queries


def test_loads_folder_and_matches_direct_onnxruntime(model_dir):
    mats = LocalMaterials(model_dir, chunk=1000)
    assert mats.materials() == ["flat16", "lambert", "rand16"]
    q = random_queries(4321, seed=3)
    direct = ort.InferenceSession(str(model_dir / "rand16.onnx")).run(None, {C.ONNX_INPUT: q})[0]
    np.testing.assert_allclose(mats.evaluate("rand16", q), direct, atol=1e-6)


def test_lambert_answers_albedo_over_pi(model_dir):
    out = LocalMaterials(model_dir).evaluate("lambert", random_queries(100))
    np.testing.assert_allclose(out, 0.5 / np.pi, rtol=1e-6)


def test_bad_queries_and_unknown_material(model_dir):
    mats = LocalMaterials(model_dir)
    with pytest.raises(UnknownMaterial, match="unknown material 'nope'"):
        mats.evaluate("nope", random_queries(3))
    bad = random_queries(3)
    bad[1, C.SIGMA] = np.nan
    with pytest.raises(C.QueryError, match="finite"):
        mats.evaluate("rand16", bad)
    with pytest.raises(C.QueryError, match="shape"):
        mats.evaluate("rand16", np.zeros((3, 5), np.float32))


def test_corrupt_and_foreign_models_are_skipped_not_fatal(model_dir, tmp_path):
    shutil.copy(model_dir / "rand16.onnx", tmp_path / "good.onnx")
    data = (model_dir / "rand16.onnx").read_bytes()
    (tmp_path / "truncated.onnx").write_bytes(data[: len(data) // 2])
    (tmp_path / "garbage.onnx").write_bytes(b"\x00\x01 not onnx")
    shutil.copy(model_dir / "rand16.onnx", tmp_path / ".hidden.onnx")  # not a material name
    mats = LocalMaterials(tmp_path)
    assert mats.materials() == ["good"]
    assert set(mats.errors) == {"truncated", "garbage", ".hidden"}
    with pytest.raises(ModelError, match="truncated.onnx"):
        load_material(tmp_path / "truncated.onnx")


def test_model_of_another_contract_version_is_refused(tmp_path):
    import onnx
    from onnx import helper

    from neumip.core.config import MaterialConfig
    from neumip.training.export.graph import build_onnx, random_weights, save_onnx

    cfg = MaterialConfig(resolution=4)
    model = build_onnx(cfg, random_weights(cfg))
    helper.set_model_props(model, {C.META_CONTRACT: "999"})
    save_onnx(model, tmp_path / "future.onnx")
    with pytest.raises(ModelError, match="contract version '999'"):
        load_material(tmp_path / "future.onnx")
    assert onnx.load(str(tmp_path / "future.onnx"))


def test_cli_query_prints_rgb(model_dir):
    out = subprocess.run(
        [sys.executable, "-m", "neumip.client.cli", "query", str(model_dir / "lambert.onnx"),
         "0.5", "0.5", "0.01", "0", "0", "0.3", "0.2"],
        check=True, capture_output=True, text=True,
    ).stdout.split()
    np.testing.assert_allclose([float(x) for x in out], [0.5 / np.pi] * 3, rtol=1e-5)


def test_cli_query_bad_direction_is_a_clear_error(model_dir):
    res = subprocess.run(
        [sys.executable, "-m", "neumip.client.cli", "query", str(model_dir / "lambert.onnx"),
         "0.5", "0.5", "0.01", "0.9", "0.9", "0", "0"],
        capture_output=True, text=True,
    )
    assert res.returncode == 2 and "wi must be" in res.stderr


def test_a_version_1_file_is_refused_naming_its_upgrade_and_the_others_serve(model_dir, tmp_path):
    """A file exported before query groups were part of the contract (version 1) fails to load with
    the command that upgrades it; the folder's other materials answer query groups with the bits of
    their single queries."""
    shutil.copy(Path(__file__).parents[1] / "data" / "pre_groups_offset.onnx", tmp_path / "old.onnx")
    shutil.copy(model_dir / "rand16.onnx", tmp_path / "rand16.onnx")
    with pytest.raises(ModelError, match=f"version 1 .* `neumip export {tmp_path / 'old.onnx'} -o NEW.onnx`"):
        load_material(tmp_path / "old.onnx")
    mats = LocalMaterials(tmp_path, threads=2)
    assert mats.materials() == ["rand16"] and "neumip export" in mats.errors["old"]
    groups = np.ascontiguousarray(np.hstack([random_queries(5000, seed=1), random_queries(5000, seed=2)[:, 3:5]]))
    np.testing.assert_array_equal(mats.evaluate("rand16", groups),
                                  mats.evaluate("rand16", C.ungroup(groups)).reshape(5000, 6))



def test_sampling_lobe_is_read_and_a_malformed_one_refused(tmp_path):
    """Both engines read the model's sampling lobe; a malformed one refuses the file with its key named."""
    from onnx import helper

    from neumip.engines.kernel import KernelMaterials
    from neumip.core.config import MaterialConfig
    from neumip.training.export.graph import build_onnx, random_weights, save_onnx

    cfg = MaterialConfig(resolution=4)
    lobe = C.SamplingLobe(0.15, 0.4)
    save_onnx(build_onnx(cfg, random_weights(cfg), extra_metadata={C.META_SAMPLING: lobe.to_json()}),
              tmp_path / "glossy.onnx")
    model = build_onnx(cfg, random_weights(cfg))
    helper.set_model_props(model, {C.META_CONTRACT: C.CONTRACT_VERSION, C.META_SAMPLING: '{"alpha": -1}'})
    save_onnx(model, tmp_path / "broken.onnx")
    local, kernel = LocalMaterials(tmp_path), KernelMaterials(tmp_path)
    assert local.sampling("glossy") == lobe == kernel.sampling("glossy")
    assert local.get("glossy").info()["sampling"] == {"alpha": 0.15, "weight": 0.4}
    assert "neumip.sampling" in local.errors["broken"]
    with pytest.raises(ModelError, match="neumip.sampling"):
        kernel.kernel("broken")


def test_a_non_finite_weight_is_refused_as_the_server_refuses_it(model_dir, tmp_path, write_nan_weight):
    """LocalMaterials loaded a file with a NaN weight and answered NaN for some queries, while the
    server refused it: both read it through the one model-file reader now, with the one error."""
    from neumip.core.modelfile import ModelError as ReaderError

    write_nan_weight(model_dir / "rand16.onnx", tmp_path / "nan.onnx")
    shutil.copy(model_dir / "flat16.onnx", tmp_path)
    mats = LocalMaterials(tmp_path)
    assert mats.materials() == ["flat16"]
    assert mats.errors["nan"] == "nan.onnx: non-finite weights in pyramid"
    with pytest.raises(ReaderError, match="^nan.onnx: non-finite weights in pyramid$"):
        load_material(tmp_path / "nan.onnx")
    assert ModelError is ReaderError
    with pytest.raises(ReaderError, match="nan.onnx: non-finite"):
        LocalMaterials(tmp_path, lazy=True).get("nan")


def test_sessions_share_one_arena_and_load_beside_another_registered_one(tmp_path):
    """Every session allocates from the process's one CPU arena (`SESSION_CONFIG`); where another library registered
    ONNX Runtime's shared arena first, materials still load and answer as in a process of their own."""
    from neumip.engines.local import SESSION_CONFIG
    from neumip.training.export.graph import build_onnx, random_weights, save_onnx
    from neumip.core.config import MaterialConfig

    assert SESSION_CONFIG["session.use_env_allocators"] == "1"
    cfg = MaterialConfig(resolution=16, half_textures=True)
    save_onnx(build_onnx(cfg, random_weights(cfg, seed=1)), tmp_path / "m.onnx")
    script = (
        "import sys, numpy as np, onnxruntime as ort\n"
        "if sys.argv[2] == 'first':\n"
        "    m = ort.OrtMemoryInfo('Cpu', ort.OrtAllocatorType.ORT_ARENA_ALLOCATOR, 0, ort.OrtMemType.DEFAULT)\n"
        "    ort.create_and_register_allocator(m, ort.OrtArenaCfg(0, -1, -1, -1))\n"
        "from neumip.engines.local import LocalMaterials\n"
        "from neumip.core.contract import random_queries\n"
        "sys.stdout.write(LocalMaterials(sys.argv[1]).evaluate('m', random_queries(1000, seed=2)).tobytes().hex())\n"
    )
    answers = [subprocess.run([sys.executable, "-c", script, str(tmp_path), who], capture_output=True, text=True,
                              check=True).stdout for who in ("first", "alone")]
    assert answers[0] and answers[0] == answers[1]
