"""The kernel engine (``NEUMIP_ENGINE=kernel``, `neumip.server.engine`) through a real `neumip serve`
process: msgpack /v1 and OIP /v2 answer with the bits of in-process `KernelMaterials.evaluate` however
the server cuts and merges the rows, and within the export's parity tolerance of ONNX Runtime; groups;
bad files, names and queries get the same errors as with ONNX Runtime; a missing drjit is one line at
start-up; the registry's memory budget holds."""

from __future__ import annotations

import shutil
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core import wire
from neumip.core.contract import random_queries
from neumip.client.http import MaterialClient
from neumip.engines.local import LocalMaterials

pytest.importorskip("neumip.engines.kernel")  # drjit, after the libLLVM check

from neumip.engines.kernel import KernelMaterials  # noqa: E402
from neumip.server.engine import Engine, EngineUnavailable, in_groups  # noqa: E402
from neumip.server.registry import Registry  # noqa: E402

MATERIALS = ("rand16", "flat16", "lambert")
CHUNK = 1000
"""The server's kernel_chunk_rows: requests of several thousand rows run as several calls."""


def parity(a: np.ndarray, b: np.ndarray) -> float:
    """Worst |a - b| over the export's parity tolerance (1e-5 absolute plus 1e-4 relative): <= 1 passes."""
    return float((np.abs(a - b) / (1e-5 + 1e-4 * np.abs(b))).max())


@pytest.fixture(scope="module")
def folder(model_dir, tmp_path_factory, write_nan_weight):
    """The test materials, a corrupt file and a file with a NaN weight."""
    out = tmp_path_factory.mktemp("kernel_engine")
    for name in MATERIALS:
        shutil.copy(model_dir / f"{name}.onnx", out)
    (out / "corrupt.onnx").write_bytes(b"not an onnx file")
    write_nan_weight(model_dir / "rand16.onnx", out / "nan.onnx")
    return out


@pytest.fixture(scope="module")
def server(serve_module, folder):
    # small calls and a merge wait: requests are cut into several calls, and concurrent ones merged
    return serve_module(folder, engine="kernel", kernel_chunk_rows=CHUNK, max_wait_ms=20)


@pytest.fixture(scope="module")
def kernel(folder):
    return KernelMaterials(folder)


@pytest.mark.parametrize("protocol", ["msgpack", "v2"])
@pytest.mark.parametrize("lights", [1, 2, 3])
def test_answers_are_the_bits_of_in_process_kernels_and_near_onnx_runtime(server, kernel, folder, protocol, lights, groups_of):
    queries = groups_of(4321, lights, seed=lights)  # > CHUNK answers: several calls, the last one short
    local = LocalMaterials(folder, threads=1)
    with MaterialClient(server.url, protocol=protocol) as client:
        for name in MATERIALS:
            rgb = client.evaluate(name, queries)
            assert rgb.shape == (4321, 3 * lights)
            np.testing.assert_array_equal(rgb, kernel.evaluate(name, queries))
            assert parity(rgb, local.evaluate(name, queries)) <= 1.0, name
    if lights > 1:  # light j of a group: the bits of single query j
        np.testing.assert_array_equal(rgb.reshape(-1, 3), kernel.evaluate(name, C.ungroup(queries)))


def test_model_metadata_names_the_engine(server):
    model = httpx.get(f"{server.url}/v2/models/{MATERIALS[0]}").json()
    assert model["platform"] == "neumip_drjit_llvm" and model["inputs"][0]["shape"] == [-1, -1]


def test_concurrent_requests_merged_or_cut_keep_their_bits(server, kernel, groups_of):
    """Requests of several sizes and widths from several threads at once: whatever calls the batcher
    made of them (metrics: more than one request piece per call), each gets its in-process answer."""
    requests = [groups_of(n, lights, seed=n) for n, lights in ((17, 1), (2500, 2), (300, 1), (999, 3), (1, 1))]
    want = {(m, j): kernel.evaluate(m, q) for m in MATERIALS[:2] for j, q in enumerate(requests)}
    wrong, failed = [], []

    def work(offset: int) -> None:
        try:
            with MaterialClient(server.url) as client:
                for j, q in enumerate(requests * 2):
                    material = MATERIALS[(offset + j) % 2]
                    if not np.array_equal(client.evaluate(material, q), want[material, j % len(requests)]):
                        wrong.append((offset, j))
        except BaseException as exc:  # a thread's failure must fail the test, not only warn
            failed.append(repr(exc))

    def pieces_and_calls() -> tuple[float, float]:
        lines = httpx.get(server.url + "/metrics").text.splitlines()
        return tuple(float(next(line for line in lines if line.startswith(name)).split()[-1])
                     for name in ("neumip_batch_requests_sum", "neumip_batch_requests_count"))

    for _ in range(5):  # a merge needs two requests queued at once: on a quiet machine one burst may not
        threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
        assert not any(thread.is_alive() for thread in threads), "a request did not come back (server hung?)"
        assert failed == [] and wrong == []
        pieces, calls = pieces_and_calls()
        if pieces > calls:
            break
    assert pieces > calls  # some call held several pieces
    metrics = httpx.get(server.url + "/metrics").text
    assert 'neumip_query_rows_total{material="flat16"}' in metrics


def test_bad_files_names_and_queries_get_clear_errors(server):
    listing = httpx.get(server.url + "/v1/materials").json()
    assert sorted(m["name"] for m in listing["materials"]) == sorted(MATERIALS)
    failed = {f["name"]: f["error"] for f in listing["failed"]}
    assert "cannot load ONNX model" in failed["corrupt"]
    assert "non-finite weights in pyramid" in failed["nan"]
    q = random_queries(10, seed=3)

    def post(name: str, body: bytes) -> httpx.Response:
        return httpx.post(server.url + wire.EVALUATE_PATH.format(name=name), content=body,
                          headers={"content-type": wire.MSGPACK_MEDIA_TYPE})

    reply = post("corrupt", wire.encode_request(q))
    assert reply.status_code == 400 and "cannot load ONNX model" in reply.json()["error"]
    reply = post("nope", wire.encode_request(q))
    assert reply.status_code == 404 and "unknown material 'nope'" in reply.json()["error"]
    bad = q.copy()
    bad[4, C.SIGMA] = np.nan
    reply = post("rand16", wire.encode_request(bad))
    assert reply.status_code == 400 and "row 4" in reply.json()["error"]
    reply = post("rand16", wire.encode_request(q)[:-4])  # a row short of its stated count
    assert reply.status_code == 400
    assert post("rand16", wire.encode_request(q)).status_code == 200  # still serving


def test_a_missing_drjit_is_one_line_at_start_up(monkeypatch, folder, capsys):
    from neumip.client.cli import main

    monkeypatch.setitem(sys.modules, "drjit", None)  # import drjit raises ImportError
    monkeypatch.delitem(sys.modules, "neumip.engines.kernel")
    with pytest.raises(EngineUnavailable, match=r"drjit is not installed: pip install 'neumip\[kernel\]'"):
        Engine.kernel()
    assert main(["serve", "--engine", "kernel", "--model-dir", str(folder), "--port", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "NEUMIP_ENGINE=kernel cannot run: drjit is not installed" in err


def test_the_memory_budget_unloads_the_least_recently_used(folder, tmp_path):
    for name in ("a", "b", "c"):
        shutil.copy(folder / "rand16.onnx", tmp_path / f"{name}.onnx")
    size = (tmp_path / "a.onnx").stat().st_size
    registry = Registry.load(tmp_path, Engine.kernel(), warmup_rows=64, lazy=True,
                             memory_budget_bytes=int(2.5 * size))
    q = random_queries(100, seed=1)
    for name in ("a", "b", "a", "c"):  # as requests use them
        registry.load_material(name).run(q)
    assert sorted(registry.materials) == ["a", "c"] and registry.resident_bytes() == 2 * size
    np.testing.assert_array_equal(registry.get("b").run(q), KernelMaterials(folder).evaluate("rand16", q))


def test_loading_warms_up_the_shapes_a_renderer_sends_and_nothing_else_compiles(folder, kernel, groups_of):
    """A material is traced (and compiled) for single queries and groups of two and three lights when it
    loads, so a renderer's first requests do not pay for it. Wider groups (issue 27, F4: each new width
    compiled for seconds, up to 13 s for 64 lights, under the lock every material needs) run as groups
    of three and one group of the rest: no new trace, and the bits of the groups' single queries."""
    registry = Registry.load(folder, Engine.kernel(), warmup_rows=16)
    material = registry.materials["rand16"].session
    assert material.traces == 3
    for lights in (1, 2, 3, 4, 5, 8, 33, C.MAX_LIGHTS):
        queries = groups_of(50, lights, seed=lights)
        rgb = registry.materials["rand16"].run(queries)
        assert rgb.shape == (50, 3 * lights)
        np.testing.assert_array_equal(rgb.reshape(-1, 3), kernel.evaluate("rand16", C.ungroup(queries)))
    assert material.traces == 3


def test_wide_groups_run_as_groups_of_the_widest_traced_width(groups_of):
    """`in_groups` cuts K lights into groups of `width` and one group of the rest (one call each), each light
    answered as its single query: a stand-in engine answers each light from its own single query."""

    def answer(groups: np.ndarray) -> np.ndarray:
        q = C.ungroup(groups)
        return np.stack([q[:, 0] + 2 * q[:, 3] - q[:, 5], q[:, 1] * q[:, 4], q[:, 2] + q[:, 6]], 1).reshape(len(groups), -1)

    for width in (1, 2, 3):
        for lights in (1, 2, 3, 4, 5, 7, 9):
            calls = []
            queries = groups_of(20, lights, seed=lights)
            rgb = in_groups(lambda g: calls.append((len(g), C.group_lights(g.shape[1]))) or answer(g), queries, width)
            np.testing.assert_array_equal(rgb, answer(queries))
            whole, rest = divmod(lights, width)
            assert calls == [(20 * whole, width)] * bool(whole) + [(20, rest)] * bool(rest)


def test_the_kernel_engine_sizes_drjits_pool_only_when_it_starts(monkeypatch):
    """Building the engine changes nothing in the process; its `start` sizes drjit's pool to the cores
    the process may run on (drjit counts the calling thread: on one core, no worker thread)."""
    import drjit as dr

    from neumip.server import engine as E

    before = dr.thread_count()
    kernel = Engine.kernel()
    assert dr.thread_count() == before
    try:
        for cores, pool in ((1, 1), (3, 3)):
            monkeypatch.setattr(E, "available_cores", lambda cores=cores: cores)
            kernel.start()
            assert dr.thread_count() == pool
    finally:
        dr.set_thread_count(before)


def test_a_wide_group_does_not_stall_another_material(folder, tmp_path, kernel, groups_of):
    """Issue 27, F4, with an empty drjit kernel cache (a new HOME), as on a new pod: a one-row request of
    64 lights used to compile a kernel for 13 s while requests on every other material waited. It is
    answered from the kernels traced at load; requests on another material meanwhile stay fast."""
    from neumip.server.process import ServerProcess

    home = tmp_path / "home"
    home.mkdir()
    wide = groups_of(1, C.MAX_LIGHTS, seed=64)
    small = random_queries(16, seed=5)
    with ServerProcess.start(folder, tmp_path / "server.log", env={"HOME": str(home)}, engine="kernel",
                             warmup_rows=64) as server, httpx.Client(timeout=60) as http:
        def post(name: str, q: np.ndarray) -> tuple[httpx.Response, float]:
            start = time.perf_counter()
            reply = http.post(server.url + wire.EVALUATE_PATH.format(name=name), content=wire.encode_request(q),
                              headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
            return reply, time.perf_counter() - start

        post("flat16", small)  # the connection is up
        with ThreadPoolExecutor(1) as pool:
            wide_reply = pool.submit(lambda: post("rand16", wide))
            others = []
            while not wide_reply.done() or len(others) < 5:
                others.append(post("flat16", small)[1])
            reply, wide_s = wide_reply.result()
    assert reply.status_code == 200
    np.testing.assert_array_equal(wire.decode_response(reply.content).reshape(-1, 3),
                                  kernel.evaluate("rand16", C.ungroup(wide)))
    assert (home / ".drjit").exists()  # the server's kernels were compiled into the empty cache
    print(f"64-light request {wide_s * 1e3:.0f} ms; another material meanwhile: max {max(others) * 1e3:.0f} ms "
          f"over {len(others)} requests")
    assert wide_s < 2.0 and max(others) < 0.5  # goal ~0.1 s; a busy shared machine adds its own delays


def test_auto_chooses_the_kernel_engine_where_it_runs_and_onnx_runtime_elsewhere(monkeypatch):
    from neumip.server.engine import Engine, EngineUnavailable
    from neumip.server.settings import Settings

    monkeypatch.delenv("NEUMIP_ENGINE", raising=False)
    assert Settings().engine == "auto"
    assert Engine.from_settings(Settings(engine="auto")).name == "kernel"  # drjit and libLLVM are installed here

    def unavailable(*args, **kwargs):
        raise EngineUnavailable("NEUMIP_ENGINE=kernel cannot run: drjit is not installed")

    monkeypatch.setattr(Engine, "kernel", classmethod(unavailable))
    assert Engine.from_settings(Settings(engine="auto")).name == "onnxruntime"
    with pytest.raises(EngineUnavailable):
        Engine.from_settings(Settings(engine="kernel"))
