"""The `neumip generate` and `neumip import-queries` commands, and the LLVM check before Mitsuba loads."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

from neumip.client.cli import main
from neumip.groundtruth.dataset import open_dataset
from neumip.core.contract import random_queries


def test_generate_writes_a_data_set_with_progress(tmp_path, capsys):
    out = tmp_path / "flat"
    assert main(["generate", "flat", "-o", str(out), "--queries", "300", "--spp", "2", "--seed", "1"]) == 0
    captured = capsys.readouterr()
    assert "300 queries of flat" in captured.out
    assert "300/300" in captured.err and "query/s" in captured.err  # tqdm bar with rate
    data = open_dataset(out)
    np.testing.assert_allclose(data.rgb, 0.5 / math.pi, rtol=2e-4)
    assert data.meta["generator"]["seed"] == 1


def test_generate_from_a_description_file(tmp_path, capsys):
    (tmp_path / "plate.toml").write_text(
        'summary = "glossy plate"\nresolution = 1\n[bsdf]\ntype = "roughconductor"\nalpha = 0.3\n'
    )
    out = tmp_path / "plate"
    assert main(["generate", str(tmp_path / "plate.toml"), "-o", str(out), "--queries", "100", "--spp", "1"]) == 0
    assert open_dataset(out).meta["material"]["name"] == "plate"


def test_generate_lists_and_reports_errors(tmp_path, capsys):
    assert main(["generate", "--list"]) == 0
    listing = capsys.readouterr().out
    assert all(name in listing for name in ("yarn", "rock", "turtle", "foam", "flat"))
    assert main(["generate", "marble", "-o", str(tmp_path / "x")]) == 2
    assert "neither a description file nor a shipped material" in capsys.readouterr().err
    assert main(["generate", "flat", "-o", str(tmp_path / "y"), "--spp", "0"]) == 2
    assert "spp" in capsys.readouterr().err


def test_generate_on_a_complete_data_set_is_a_no_op_unless_the_settings_differ(tmp_path, capsys):
    args = ["generate", "flat", "-o", str(tmp_path / "d"), "--queries", "10", "--spp", "1"]
    assert main(args) == 0
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "d").iterdir()}
    capsys.readouterr()
    assert main(args) == 0  # the same command again: nothing to do
    assert "10 queries of flat" in capsys.readouterr().out
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "d").iterdir()} == before
    assert main([*args, "--seed", "3"]) == 2
    assert "complete data set made with other settings (generator.seed: there 0, asked 3)" in capsys.readouterr().err
    assert open_dataset(tmp_path / "d").meta["generator"]["seed"] == 0


def test_generate_help_shows_the_defaults(capsys):
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.sampling import QuerySampling
    from neumip.groundtruth.tracer import TracerConfig

    with pytest.raises(SystemExit):
        main(["generate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for flag, value in [("--chunk", GenerateSettings.chunk), ("--lanes", TracerConfig.lanes),
                        ("--level-fraction", QuerySampling.level_fraction), ("--spp", GenerateSettings.spp)]:
        assert f"{flag} " in text and f"(default: {value})" in text, flag


def test_old_llvm_fails_with_a_clear_message_before_mitsuba_loads(tmp_path):
    """With only LLVM 15, drjit would abort the process; the command must say what to do instead."""
    fake = tmp_path / "libLLVM-15.so"
    fake.write_bytes(b"")
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": str(fake)}
    code = "from neumip.client.cli import main; raise SystemExit(main(['generate', 'flat', '-o', 'x']))"
    proc = subprocess.run([sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "LLVM 15" in proc.stderr and "libllvm19" in proc.stderr


def test_import_queries_from_npz_and_npy(tmp_path, capsys):
    queries = random_queries(50, seed=3)
    rgb = np.random.default_rng(0).random((50, 3)).astype(np.float32)
    np.savez(tmp_path / "btf.npz", queries=queries, rgb=rgb)
    assert main(["import-queries", str(tmp_path / "btf.npz"), "-o", str(tmp_path / "a"), "--name", "wool"]) == 0
    data = open_dataset(tmp_path / "a")
    np.testing.assert_array_equal(data.queries, queries)
    assert data.meta["generator"]["name"] == "external" and data.meta["material"]["name"] == "wool"
    np.save(tmp_path / "q.npy", queries)
    np.save(tmp_path / "c.npy", rgb[:40])
    assert main(["import-queries", str(tmp_path / "q.npy"), str(tmp_path / "c.npy"), "-o", str(tmp_path / "b"),
                 "--name", "wool"]) == 2
    assert "cannot import" in capsys.readouterr().err


def test_interrupted_process_resumes_to_the_same_data(tmp_path, default_sigint):
    """A real `neumip generate` process stopped by Ctrl-C mid-run, then the same command again."""
    import json
    import signal
    import time

    (tmp_path / "plates.toml").write_text('resolution = 16\nheight_scale = 0.05\n[procedural]\ngenerator = "turtle"\n')
    command = [sys.executable, "-m", "neumip.client.cli", "generate", str(tmp_path / "plates.toml"),
               "--queries", "40000", "--chunk", "1000", "--spp", "4", "--seed", "5", "-o"]
    proc = subprocess.Popen(command + [str(tmp_path / "a")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=default_sigint)
    progress = tmp_path / "a" / "progress.json"
    deadline = time.monotonic() + 300  # a cold drjit kernel cache on a busy 2-core machine is slow
    while proc.poll() is None:
        if progress.exists() and json.loads(progress.read_text())["done"] >= 2:
            break
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail("generate wrote fewer than 2 chunks in 300 s; cannot test the interruption")
        time.sleep(0.05)
    assert proc.poll() is None, f"generate ended before it could be interrupted: {proc.stderr.read()}"
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=60) == 130, proc.stderr.read()
    assert not (tmp_path / "a" / "meta.json").exists()
    done = json.loads(progress.read_text())["done"]
    assert 2 <= done < 40
    resumed = subprocess.run(command + [str(tmp_path / "a")], capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert subprocess.run(command + [str(tmp_path / "b")], capture_output=True, timeout=300).returncode == 0
    a, b = open_dataset(tmp_path / "a"), open_dataset(tmp_path / "b")
    np.testing.assert_array_equal(a.queries, b.queries)
    np.testing.assert_array_equal(a.rgb, b.rgb)
