"""The whole path on one tiny material, through the command line: `neumip generate` -> `train` ->
`export` -> `serve` (a real process on loopback) -> `render` (through that server and in-process).

The material is the shipped `flat` Lambertian plane (albedo 0.5), whose MBTF is known: 0.5 / pi for
every query, so the trained model is checked against the answer, not only for running.
"""

from __future__ import annotations

import json
import math
import socket
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.client.cli import main
from neumip.core.contract import random_queries

pytest.importorskip("mitsuba")
pytest.importorskip("torch")
pytest.importorskip("fastapi")

EXACT = 0.5 / math.pi
"""The flat Lambertian's MBTF: albedo / pi."""

SCENE = """<scene version="3.0.0">
    <integrator type="neumip_path"><integer name="max_depth" value="3"/></integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 2, 3" target="0, 0.3, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="24"/></film>
        <float name="fov" value="45"/>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world">
            <scale value="0.5"/><rotate x="1" angle="90"/><translate value="0, 2.5, 0"/>
        </transform>
        <emitter type="area"><rgb name="radiance" value="20"/></emitter>
    </shape>
    <emitter type="constant"><rgb name="radiance" value="0.2"/></emitter>
    <shape type="rectangle">
        <transform name="to_world"><scale value="2"/><rotate x="1" angle="-90"/></transform>
        <bsdf type="neumip"><string name="material" value="flat"/><float name="uv_scale" value="2"/></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" x="0" y="0.5" z="0"/><float name="radius" value="0.5"/>
        <bsdf type="neumip"><string name="material" value="flat"/></bsdf>
    </shape>
</scene>
"""
"""A neural floor and sphere under an area light and a dim sky, 24 x 24 pixels, 4 spp."""


@contextmanager
def serving(models: Path, log: Path):
    """`neumip serve` in its own process on a free loopback port; yields its URL once it is ready."""
    import httpx

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    command = [sys.executable, "-m", "neumip.client.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
               "--model-dir", str(models)]
    with log.open("w") as out:
        process = subprocess.Popen(command, stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 90
        while True:
            assert process.poll() is None and time.monotonic() < deadline, log.read_text()
            try:
                if httpx.get(f"{url}/v2/health/ready", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.1)
        yield url
    finally:
        process.terminate()
        assert process.wait(timeout=30) == 0, log.read_text()


def _image(path: Path) -> np.ndarray:
    from neumip.client.mitsuba.bsdf import mi

    return np.array(mi.Bitmap(str(path)), dtype=np.float32)


def test_generate_train_export_serve_render(tmp_path, capsys):
    from neumip.client.http import MaterialClient
    from neumip.engines.local import LocalMaterials
    from neumip.groundtruth.dataset import open_dataset

    data, models = tmp_path / "data", tmp_path / "models"

    # --- ground truth: 8 000 path-traced queries of the flat plane, sigma for an 8^2 pyramid ---------
    argv = ["generate", "flat", "-o", str(data), "--queries", "8000", "--spp", "2", "--resolution", "8"]
    assert main(argv) == 0
    dataset = open_dataset(data)
    assert len(dataset) == 8000 and dataset.meta["generator"]["resolution"] == 8
    np.testing.assert_allclose(dataset.rgb, EXACT, rtol=1e-3)

    # --- train (resolution from the data), then export the checkpoint again ---------------------------
    argv = ["train", str(data), "-o", str(models / "flat.onnx"), "--preset", "test", "--steps", "150",
            "--batch", "1024", "--threads", "1", "--checkpoint", str(tmp_path / "run.pt"),
            "--description", "e2e"]
    assert main(argv) == 0
    assert "wrote" in capsys.readouterr().out
    exported = tmp_path / "exported" / "flat.onnx"
    assert main(["export", str(tmp_path / "run.pt"), "-o", str(exported)]) == 0
    assert exported.read_bytes() == (models / "flat.onnx").read_bytes()

    local = LocalMaterials(models)
    meta = local.get("flat").metadata
    assert meta[C.META_CONTRACT] == C.CONTRACT_VERSION and meta[C.META_DESCRIPTION] == "e2e"
    config = json.loads(meta[C.META_CONFIG])
    assert config["resolution"] == 8 and config["offset"] is True
    assert json.loads(meta[C.META_VALIDATION])["overall"]["rel_l1"] < 0.02
    q = random_queries(5000, seed=3, max_zenith_deg=80.0)
    rgb = local.evaluate("flat", q)
    assert abs(rgb.mean() / EXACT - 1) < 0.01 and np.abs(rgb / EXACT - 1).max() < 0.05

    # --- serve, and render through the server and in-process -----------------------------------------
    scene = tmp_path / "scene.xml"
    scene.write_text(SCENE)
    with serving(models, tmp_path / "serve.log") as url:
        np.testing.assert_array_equal(MaterialClient(url).evaluate("flat", q), rgb)  # same bits
        capsys.readouterr()
        assert main(["render", str(scene), "-o", str(tmp_path / "served.exr"), "--server", url]) == 0
        queries = int(capsys.readouterr().out.split(" queries")[0].split()[-1].replace(",", ""))
        assert queries > 24 * 24 * 4  # the neural surfaces were shaded through the server
    assert main(["render", str(scene), "-o", str(tmp_path / "local.exr"), "--models", str(models)]) == 0
    served, in_process = _image(tmp_path / "served.exr"), _image(tmp_path / "local.exr")
    assert served.shape == (24, 24, 3) and np.isfinite(served).all()
    assert served.mean() > 0.05 and served.std() > 0.02  # lit, and shaded: not a flat image
    np.testing.assert_allclose(served, in_process, atol=1e-5)
