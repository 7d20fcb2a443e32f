"""Ground truth as Ray tasks on a local 2-CPU Ray: bit-identical to one process, resumable after an
interrupt, and after a worker process is killed mid-chunk (Ray retries the chunk)."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
import pytest

from neumip.client.cli import main
from neumip.groundtruth.dataset import DatasetError, open_dataset
from neumip.groundtruth.description import find_description
from neumip.groundtruth.generate import GenerateSettings, generate

from neumip.core.cluster import RayConfig

pytest.importorskip("ray", reason="Ray is not installed: pip install 'neumip[cluster]'")

SETTINGS = dict(queries=3000, spp=4, seed=11, chunk=500)


class Interrupt(Exception):
    pass


def turtle():
    desc = find_description("turtle")
    desc.resolution = 16
    return desc


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The single-process data set with the same seed."""
    return generate(turtle(), tmp_path_factory.mktemp("single") / "data", GenerateSettings(**SETTINGS))


def assert_same_data(data, reference):
    assert data.meta == reference.meta
    np.testing.assert_array_equal(data.queries, reference.queries)
    np.testing.assert_array_equal(data.rgb, reference.rgb)


def test_ray_data_set_is_bit_identical_to_one_process(local_ray, reference, tmp_path):
    reports = []
    config = RayConfig(in_flight=3)  # fewer than the 6 chunks: the window must slide
    data = generate(turtle(), tmp_path / "data", GenerateSettings(**SETTINGS), lambda d, t: reports.append(d), config)
    assert reports == [0, 500, 1000, 1500, 2000, 2500, 3000]  # progress in chunk order
    assert_same_data(data, reference)


def test_ray_run_resumes_after_an_interrupt(local_ray, reference, tmp_path):
    out = tmp_path / "data"

    def stop_after_two_chunks(done: int, total: int) -> None:
        if done >= 1000:
            raise Interrupt

    with pytest.raises(Interrupt):
        generate(turtle(), out, GenerateSettings(**SETTINGS), stop_after_two_chunks, RayConfig())
    with pytest.raises(DatasetError, match="incomplete"):
        open_dataset(out)
    resumed = []
    data = generate(turtle(), out, GenerateSettings(**SETTINGS), lambda d, t: resumed.append(d), RayConfig())
    assert resumed[0] == 1000  # the written chunks were kept
    assert_same_data(data, reference)


def test_a_partial_ray_run_resumes_in_one_process(local_ray, reference, tmp_path):
    """The data set does not record how it was traced: either way finishes the other's run."""
    out = tmp_path / "data"
    with pytest.raises(Interrupt):
        generate(turtle(), out, GenerateSettings(**SETTINGS), lambda d, t: _stop_at(d, 1500), RayConfig())
    assert_same_data(generate(turtle(), out, GenerateSettings(**SETTINGS)), reference)


def _stop_at(done: int, limit: int) -> None:
    if done >= limit:
        raise Interrupt


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds Ray's worker processes in /proc")
def test_a_worker_killed_mid_chunk_is_retried_with_identical_data(local_ray, tmp_path, killing_the_first_busy_worker):
    settings = GenerateSettings(**{**SETTINGS, "seed": 12})  # a new scene key: workers build their tracer
    with killing_the_first_busy_worker(local_ray, "_chunk_task") as killed:
        data = generate(turtle(), tmp_path / "ray", settings, ray=RayConfig())
    assert killed, "no worker was seen running a chunk"
    assert_same_data(data, generate(turtle(), tmp_path / "single", settings))


def test_generate_command_with_ray(local_ray, tmp_path, capsys):
    args = ["generate", "flat", "--queries", "1200", "--spp", "2", "--seed", "3", "--chunk", "500"]
    assert main([*args, "-o", str(tmp_path / "ray"), "--ray", "--ray-in-flight", "2"]) == 0
    captured = capsys.readouterr()
    assert "1200 queries of flat (2 spp), complete" in captured.out and "1.20k/1.20k" in captured.err
    single = generate(find_description("flat"), tmp_path / "single", GenerateSettings(queries=1200, spp=2, seed=3, chunk=500))
    assert_same_data(open_dataset(tmp_path / "ray"), single)


def test_ray_address_swallowing_the_material_is_explained(capsys):
    assert main(["generate", "--ray", "flat", "-o", "x"]) == 2
    assert "--ray took 'flat' as its address" in capsys.readouterr().err


@pytest.mark.slow  # starts a local Ray twice in child processes (~10 s each on 2 cores)
def test_interrupted_ray_process_resumes_to_the_same_data(tmp_path, default_sigint):
    """A real `neumip generate --ray` stopped by Ctrl-C mid-run, then the same command again."""
    import json
    import subprocess
    import sys

    command = [sys.executable, "-m", "neumip.client.cli", "generate", "turtle", "--resolution", "16", "--queries",
               "40000", "--chunk", "1000", "--spp", "4", "--seed", "5", "-o", str(tmp_path / "a"), "--ray"]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=default_sigint)
    progress = tmp_path / "a" / "progress.json"
    deadline = time.monotonic() + 300
    while proc.poll() is None and time.monotonic() < deadline:
        if progress.exists() and json.loads(progress.read_text())["done"] >= 2:
            break
        time.sleep(0.05)
    assert proc.poll() is None, f"generate ended before it could be interrupted: {proc.stderr.read()}"
    proc.send_signal(signal.SIGINT)
    assert proc.wait(timeout=60) == 130, proc.stderr.read()
    done = json.loads(progress.read_text())["done"]
    assert 2 <= done < 40 and not (tmp_path / "a" / "meta.json").exists()
    resumed = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    desc = find_description("turtle")
    single = generate(desc, tmp_path / "b", GenerateSettings(queries=40000, chunk=1000, spp=4, seed=5, resolution=16))
    assert_same_data(open_dataset(tmp_path / "a"), single)


def test_a_worker_with_other_versions_refuses_to_trace(monkeypatch):
    from neumip.groundtruth import generate as module

    desc = turtle()
    driver = {**module._versions(), "mitsuba": "0.0.1"}
    monkeypatch.setattr(module, "_worker_tracer", {})
    with pytest.raises(RuntimeError, match="same versions on every node"):
        module._chunk_task(None, "key", GenerateSettings(**SETTINGS), desc.resolution, 1, driver, 0, 10)
