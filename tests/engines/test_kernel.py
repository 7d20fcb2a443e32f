"""In-kernel evaluation (`engines/kernel.py`, the graph interpreted by `engines/onnx_kernel.py`): the
same answers as the ONNX graph in ONNX Runtime, within the export's parity tolerance, for every layout
a model file can have and for a graph written by another tool; bad files and unsupported operators
refused with a clear error; answers that do not depend on the batch or the thread. Needs drjit, not
Mitsuba (the render with it: tests/client/mitsuba/test_kernel_render.py)."""

from __future__ import annotations

import importlib
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import onnx
import pytest

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.engines.local import LocalMaterials, ModelError, UnknownMaterial

pytest.importorskip("neumip.engines.kernel")  # drjit, after the libLLVM check

import drjit as dr  # noqa: E402
from drjit.llvm.ad import Float, UInt32  # noqa: E402

from neumip.engines.kernel import KernelMaterial, KernelMaterials  # noqa: E402
from neumip.core.config import MaterialConfig  # noqa: E402
from neumip.training.export.graph import build_onnx, random_weights, save_onnx  # noqa: E402
from neumip.training.export.trim import trim_model  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "data"


BACKENDS = [
    pytest.param("drjit.llvm.ad", marks=pytest.mark.skipif(not dr.has_backend(dr.JitBackend.LLVM),
                                                           reason="no drjit LLVM backend")),
    pytest.param("drjit.cuda.ad", marks=pytest.mark.skipif(not dr.has_backend(dr.JitBackend.CUDA),
                                                           reason="no CUDA device")),
]
"""The drjit backends the kernel may run on (the CUDA one where a GPU is: the renderer's cuda variants)."""


def parity(a: np.ndarray, b: np.ndarray) -> float:
    """Worst |a - b| over the export's parity tolerance (1e-5 absolute plus 1e-4 relative): <= 1 passes."""
    return float((np.abs(a - b) / (1e-5 + 1e-4 * np.abs(b))).max())


def random_queries(n: int, seed: int, lights: int = 1) -> np.ndarray:
    """Queries over several tiles, all footprints (finer than the finest level to coarser than the
    coarsest), directions up to the horizon (a third of them within a degree of it); with ``lights``
    > 1, query groups."""
    rng = np.random.default_rng(seed)

    def direction(count):
        phi = rng.uniform(0, 2 * np.pi, count)
        theta = rng.uniform(0, np.radians(90), count)
        theta[::3] = np.radians(90) - rng.uniform(0, np.radians(1), len(theta[::3]))
        s = np.sin(theta)
        return np.stack([s * np.cos(phi), s * np.sin(phi)], 1)

    uv = rng.uniform(-3, 3, (n, 2))
    sigma = 10.0 ** rng.uniform(-4, 0.5, n)
    q = C.pack_queries(uv[:, 0], uv[:, 1], sigma, direction(n), direction(n))
    return np.concatenate([q] + [direction(n) for _ in range(lights - 1)], 1).astype(np.float32)


@pytest.fixture(scope="module")
def layouts(tmp_path_factory):
    """One file per layout: offset (64^2 and 16^2, and one clamped only at grazing angles), no offset,
    YUV head, one- and two-layer MLPs, a base and a relief (with a ceiling; with constant map channels), and
    trimmed."""
    folder = tmp_path_factory.mktemp("kernel_models")
    configs = {
        "offset64": MaterialConfig(resolution=64),
        "offset16": MaterialConfig(resolution=16, offset_min_cos=0.3),
        "nooffset": MaterialConfig(resolution=32, offset=False),
        "yuv": MaterialConfig(resolution=16, head="yuv"),
        "layers2": MaterialConfig(resolution=16, layers=2, hidden=12),
        "layers1": MaterialConfig(resolution=16, layers=1, head="yuv"),
        "grazing": MaterialConfig(resolution=16, offset_min_cos=0.05),
        "half": MaterialConfig(resolution=16, half_vector=True),
        "base": MaterialConfig(resolution=16, base=32),
        "relief": MaterialConfig(resolution=16, base=32, relief=32),
        "frame": MaterialConfig(resolution=16, base=32, local_frame=True, half_vector=True),
        "visibility": MaterialConfig(resolution=16, base=32, relief=32, terminator="none"),
        "visibility-input": MaterialConfig(resolution=16, base=32, relief=32, terminator="none", local_frame=True,
                                           visibility_input=True),
        "half-textures": MaterialConfig(resolution=16, base=32, relief=32, lod_bias=1, half_textures=True),
        "offset-mip": MaterialConfig(resolution=16, base=32, relief=32, lod_bias=1, half_textures=True,
                                     offset_mip=True),
        "energy": MaterialConfig(resolution=16, base=32, relief=32, lod_bias=1, half_textures=True, offset_mip=True,
                                 energy_bins=6),
        "coarse-decoder": MaterialConfig(resolution=16, base=32, relief=32, lod_bias=1, half_textures=True,
                                         offset_mip=True, energy_bins=6, coarse_decoder=2),
        "energy-azimuths": MaterialConfig(resolution=16, base=32, relief=32, lod_bias=1, half_textures=True,
                                          offset_mip=True, energy_bins=6, energy_azimuths=8),
        "energy-luminance": MaterialConfig(resolution=16, base=32, relief=32, lod_bias=1, half_textures=True,
                                           offset_mip=True, energy_bins=6, energy_azimuths=8, energy_luminance=True),
    }
    for seed, (name, cfg) in enumerate(configs.items()):
        save_onnx(build_onnx(cfg, random_weights(cfg, seed=seed)), folder / f"{name}.onnx")
    # the relief layout with a ceiling at its median answer: the clamp binds on about half the queries
    median = float(np.median(LocalMaterials(folder, threads=1).evaluate("relief", random_queries(4096, seed=9))))
    relief = configs["relief"]
    save_onnx(build_onnx(replace(relief, ceiling=median), random_weights(relief, seed=list(configs).index("relief"))),
              folder / "ceiling.onnx")
    save_onnx(trim_model(onnx.load(folder / "offset64.onnx"), 2), folder / "trimmed.onnx")
    save_onnx(trim_model(onnx.load(folder / "energy.onnx"), 2), folder / "energy-trimmed.onnx")
    save_onnx(trim_model(onnx.load(folder / "coarse-decoder.onnx"), 3), folder / "coarse-decoder-trimmed.onnx")
    # base maps with channels the same in every texel, which the graph holds as constants: F0 (a dielectric), all
    for name, first, last in (("dielectric", 3, 6), ("plain", 0, 9)):
        weights = random_weights(relief, seed=len(configs))
        weights[W.BASE][:, first:last] = weights[W.BASE][0, first:last]
        save_onnx(build_onnx(relief, weights), folder / f"{name}.onnx")
    return folder


@pytest.mark.parametrize("backend", BACKENDS)
def test_answers_match_onnx_runtime_for_every_layout(layouts, backend):
    kernel = KernelMaterials(layouts, importlib.import_module(backend))
    local = LocalMaterials(layouts, threads=1)
    assert kernel.materials() == local.materials()
    for name in kernel.materials():
        for lights in (1, 3):
            q = random_queries(4096, seed=lights, lights=lights)
            got, want = kernel.evaluate(name, q), local.evaluate(name, q)
            assert got.shape == want.shape == (4096, 3 * lights)
            assert parity(got, want) <= 1.0, name


def test_float16_textures_stay_float16_tables_in_the_kernel(layouts):
    """A model whose textures are float16 (`half_textures`) keeps its five quad tables as drjit Float16 arrays - half
    the memory - and one of float32 textures keeps Float ones; the answers match ONNX Runtime's above either way."""
    from drjit.llvm.ad import Float16

    half = KernelMaterial(layouts / "half-textures.onnx").graph.tables
    full = KernelMaterial(layouts / "relief.onnx").graph.tables
    assert len(half) == 5 and all(isinstance(t, Float16) for t in half)
    assert full and all(isinstance(t, Float) for t in full)


def test_a_group_answers_each_light_as_its_single_query(layouts):
    kernel = KernelMaterials(layouts)
    q = random_queries(1000, seed=5, lights=3)
    for name in kernel.materials():
        grouped = kernel.evaluate(name, q)
        singles = kernel.evaluate(name, C.ungroup(q)).reshape(1000, 9)
        np.testing.assert_array_equal(grouped, singles, err_msg=name)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_foreign_graph_answers_as_onnx_runtime_does(tmp_path, backend, checkerboard):
    """A material written with onnx.helper (Slice, Floor, Sub, Greater, Cast, Equal, Where; no neumip
    metadata, no query groups) is evaluated from its graph: ONNX Runtime's answers, single queries and
    groups (each light as a single query)."""
    import onnxruntime as ort

    model = checkerboard()
    save_onnx(model, tmp_path / "checker.onnx")
    kernel = KernelMaterials(tmp_path, importlib.import_module(backend))
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    q = random_queries(5000, seed=11, lights=2)
    want = session.run([C.ONNX_OUTPUT], {C.ONNX_INPUT: C.ungroup(q)})[0]
    assert len(np.unique(want, axis=0)) == 2  # both squares are read
    np.testing.assert_array_equal(kernel.evaluate("checker", q[:, :C.QUERY_DIM]), want[::2])
    np.testing.assert_array_equal(kernel.evaluate("checker", q), want.reshape(5000, 6))


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_a_graph_exported_by_torch_answers_as_onnx_runtime_does(tmp_path):
    """Another tool's graph: a small MLP on the query (Gemm, Relu, Sigmoid, Mul, a Constant node)
    written by torch.onnx.export, evaluated from its graph."""
    torch = pytest.importorskip("torch")
    import io

    import onnxruntime as ort

    class Material(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.mlp = torch.nn.Sequential(torch.nn.Linear(7, 16), torch.nn.ReLU(), torch.nn.Linear(16, 3),
                                           torch.nn.Sigmoid())

        def forward(self, queries):  # (N, 7) -> (N, 3)
            return self.mlp(queries) * 0.3

    torch.manual_seed(0)
    buffer = io.BytesIO()
    torch.onnx.export(Material(), (torch.zeros(4, 7),), buffer, input_names=[C.ONNX_INPUT],
                      output_names=[C.ONNX_OUTPUT], dynamic_axes={C.ONNX_INPUT: {0: "N"}, C.ONNX_OUTPUT: {0: "N"}},
                      dynamo=False, opset_version=18)
    (tmp_path / "mlp.onnx").write_bytes(buffer.getvalue())
    session = ort.InferenceSession(buffer.getvalue(), providers=["CPUExecutionProvider"])
    q = random_queries(3000, seed=12, lights=2)
    want = session.run([C.ONNX_OUTPUT], {C.ONNX_INPUT: C.ungroup(q)})[0].reshape(3000, 6)
    assert parity(KernelMaterials(tmp_path).evaluate("mlp", q), want) <= 1.0


@pytest.mark.parametrize("engine", ["onnxruntime", "kernel"])
def test_a_foreign_graph_is_served_alike_by_every_engine(tmp_path, checkerboard, serve, engine, groups_of):
    """A graph made by another tool (scenes/checkerboard.py: no neumip metadata, input fixed at 7
    columns) is served by ONNX Runtime in-process, by the in-kernel engine and by a real server on
    either engine with the same answers; each light of a group is answered as its single query."""
    from neumip.client.http import MaterialClient

    save_onnx(checkerboard(), tmp_path / "checker.onnx")
    q = groups_of(3000, 3, seed=4)
    local = LocalMaterials(tmp_path).evaluate("checker", q)
    assert local.shape == (3000, 9) and len(np.unique(local.reshape(-1, 3), axis=0)) == 2
    np.testing.assert_array_equal(local.reshape(-1, 3), LocalMaterials(tmp_path).evaluate("checker", C.ungroup(q)))
    np.testing.assert_array_equal(KernelMaterials(tmp_path).evaluate("checker", q), local)
    with MaterialClient(serve(tmp_path, engine=engine).url) as client:
        np.testing.assert_array_equal(client.evaluate("checker", q), local)


def test_an_unsupported_operator_or_another_contract_is_one_clear_error(tmp_path, checkerboard):
    model = checkerboard()
    next(n for n in model.graph.node if n.op_type == "Floor").op_type = "Round"
    save_onnx(model, tmp_path / "rounded.onnx")
    other = checkerboard()
    onnx.helper.set_model_props(other, {C.META_CONTRACT: "0"})
    save_onnx(other, tmp_path / "older.onnx")
    kernel = KernelMaterials(tmp_path)
    with pytest.raises(ModelError, match=r"rounded.onnx: operator\(s\) Round not supported in the kernel"):
        kernel.kernel("rounded")
    with pytest.raises(ModelError, match="older.onnx: query contract version '0'"):
        kernel.kernel("older")


def test_the_engine_imports_nothing_from_the_renderer():
    """The in-kernel engine sits below the Mitsuba plugin (client/mitsuba/, which uses it): importing
    it loads neither that package nor Mitsuba (the libLLVM check is `engines/llvm.py`). Its imports
    from training/ are checked statically by tests/test_layers.py."""
    code = ("import sys, neumip.engines.kernel; print(' '.join(m for m in sys.modules "
            "if m.startswith(('neumip.client.mitsuba', 'mitsuba'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == []


@pytest.mark.parametrize("backend", BACKENDS)
def test_answers_do_not_depend_on_the_batch(layouts, backend):
    kernel = KernelMaterials(layouts, importlib.import_module(backend))
    q = random_queries(3000, seed=7, lights=2)
    cuts = [0, 1, 2, 3, 1000, 1997, 2994, 3000]
    for name in kernel.materials():
        whole = kernel.evaluate(name, q)
        parts = np.concatenate([kernel.evaluate(name, q[a:b]) for a, b in zip(cuts, cuts[1:])])
        np.testing.assert_array_equal(whole, parts, err_msg=name)
        assert kernel.evaluate(name, q[:0]).shape == (0, 6)


def test_bad_files_and_names_get_clear_errors(layouts, tmp_path, write_nan_weight):
    (tmp_path / "corrupt.onnx").write_bytes(b"not an onnx file")
    write_nan_weight(layouts / "offset16.onnx", tmp_path / "nan.onnx")
    shutil.copy(layouts / "nooffset.onnx", tmp_path / "good.onnx")
    shutil.copy(DATA / "pre_groups_offset.onnx", tmp_path / "old.onnx")  # query contract version 1
    kernel = KernelMaterials(tmp_path)
    with pytest.raises(ModelError, match="corrupt.onnx: cannot load"):
        kernel.kernel("corrupt")
    with pytest.raises(ModelError, match="old.onnx: .*version 1.*`neumip export"):
        kernel.kernel("old")
    with pytest.raises(ModelError, match="nan.onnx: non-finite weights in pyramid"):
        kernel.kernel("nan")
    with pytest.raises(UnknownMaterial, match="unknown material 'nope'"):
        kernel.evaluate("nope", random_queries(4, seed=0))
    assert kernel.materials() == ["good"]  # the failed files are no longer offered
    bad = random_queries(4, seed=0)
    bad[2, C.SIGMA] = np.nan
    with pytest.raises(C.QueryError):
        kernel.evaluate("good", bad)
    with pytest.raises(FileNotFoundError):
        KernelMaterials(tmp_path / "missing")


def test_a_constant_material_answers_every_lane_whatever_the_batch(model_dir):
    """`lambert` answers 0.5 / pi whatever the query, so its traced arithmetic does not depend on the
    lanes; calls of other widths after the first (which replay the frozen trace) still answer one
    value per lane. The lanes are gathered from a wider array, as the renderer takes them."""
    material = KernelMaterials(model_dir).kernel("lambert")
    wide = dr.arange(Float, 186) / 186.0
    for n in (54, 3, 1, 100):
        x = dr.gather(Float, wide, dr.arange(UInt32, n) * 2)
        answers = material.answers([x, x, x * 0.01, x * 0.3, x, x * 0.1, x * 0.2, x, x * 0.1])  # 2 lights
        for rgb in answers:
            for channel in rgb:
                assert dr.width(channel) == n
                np.testing.assert_allclose(np.asarray(channel), 0.5 / np.pi, rtol=1e-6)


def test_the_arithmetic_is_traced_once_per_number_of_lights(model_dir):
    """Later calls of other sizes replay the frozen trace (tracing a material costs milliseconds,
    and a render makes a call per material and bounce)."""
    kernel = KernelMaterials(model_dir)
    for n in (500, 1500, 40, 1, 3000):  # one row too (drjit holds one lane as a literal: recorded again once)
        kernel.evaluate("rand16", random_queries(n, seed=n))
        kernel.evaluate("rand16", random_queries(n, seed=n, lights=2))
    assert kernel.kernel("rand16").traces == 2
    one = random_queries(1, seed=7, lights=2)
    np.testing.assert_array_equal(kernel.evaluate("rand16", one), kernel.evaluate("rand16", np.repeat(one, 3, 0))[:1])


def test_concurrent_calls_answer_as_one_thread_does(model_dir):
    """Threads calling the same evaluator (two materials, several widths and light counts) get the
    answers of a single thread; concurrent frozen calls deadlocked or crashed drjit (2 runs in 3)
    before they were serialised."""
    import threading

    sizes = ((300, 1), (2000, 2), (37, 1), (500, 3), (1, 2), (4000, 1), (64, 2), (1, 3))  # 1 lane: traced anew
    queries = [random_queries(n, seed=n, lights=lights) for n, lights in sizes]
    materials = ("rand16", "flat16")
    single = KernelMaterials(model_dir)
    want = {(m, j): single.evaluate(m, q) for m in materials for j, q in enumerate(queries)}
    shared, wrong = KernelMaterials(model_dir), []

    def work(offset: int) -> None:
        for j, q in enumerate(queries * 3):
            material = materials[(offset + j) % 2]
            if not np.array_equal(shared.evaluate(material, q), want[material, j % len(queries)]):
                wrong.append((offset, j))

    threads = [threading.Thread(target=work, args=(i,), daemon=True) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    assert not any(thread.is_alive() for thread in threads), "deadlocked"
    assert wrong == []


LOAD_WHILE_ANSWERING = """
import sys, threading, time
from neumip.engines.kernel import KernelMaterial
from neumip.server.registry import warmup_queries
path, seconds = sys.argv[1], float(sys.argv[2])
done, counts = threading.Event(), {"calls": 0, "loads": 0}
material, kept = KernelMaterial(path), []
queries = {k: warmup_queries(4096, k) for k in (1, 2)}
def answer():  # the server's engine thread
    while not done.is_set():
        material.run(queries[1 + counts["calls"] % 2]); counts["calls"] += 1
def load():  # the registry's thread: build, warm up (records), keep a few, drop the older ones
    while not done.is_set():
        new = KernelMaterial(path)
        for k in (1, 2):
            new.run(warmup_queries(512, k))
        kept[:] = kept[-2:] + [new]; counts["loads"] += 1
threads = [threading.Thread(target=f, daemon=True) for f in (answer, load)]
[t.start() for t in threads]
time.sleep(seconds); done.set()
[t.join() for t in threads]
print("ok", counts["calls"], counts["loads"])
"""


def test_a_material_loads_while_another_answers(layouts):
    """The server loads (builds, warms up: records frozen calls) and drops materials on one thread while
    its engine answers on another. Unserialised, drjit 1.5 hung the whole process (holding the GIL) in
    seconds; in a subprocess, so that a hang fails the test instead of stopping the run."""
    import subprocess
    import sys

    try:
        out = subprocess.run([sys.executable, "-c", LOAD_WHILE_ANSWERING, str(layouts / "offset64.onnx"), "6"],
                             capture_output=True, text=True, timeout=90)
    except subprocess.TimeoutExpired:
        pytest.fail("loading a material while another answered hung the process")
    assert out.returncode == 0, out.stderr[-2000:]
    ok, calls, loads = out.stdout.split()
    assert ok == "ok" and int(calls) > 10 and int(loads) > 2


def test_no_garbage_collection_while_the_arithmetic_is_traced(model_dir, monkeypatch):
    """drjit aborts the process when an array made from numpy memory (a material's textures) is freed
    while a frozen function records; Python's cyclic collector freed unreachable materials at any
    allocation, tracing included (a test run that made and dropped many materials died so). So no
    automatic collection may run inside a frozen call, however often the collector is due."""
    import gc

    tracing, during = [], []
    trace = KernelMaterial._trace

    def traced(self, *args):
        tracing.append(True)
        try:
            return trace(self, *args)
        finally:
            tracing.pop()

    def collected(phase, info):
        if phase == "start":
            during.append(bool(tracing))

    monkeypatch.setattr(KernelMaterial, "_trace", traced)
    kernel, q, threshold = KernelMaterials(model_dir), random_queries(100, seed=2, lights=2), gc.get_threshold()
    gc.callbacks.append(collected)
    gc.set_threshold(1)  # a collection due at nearly every allocation
    try:
        got = kernel.evaluate("rand16", q)
    finally:
        gc.set_threshold(*threshold)
        gc.callbacks.remove(collected)
    assert kernel.kernel("rand16").traces == 1 and during and not any(during)
    assert parity(got, LocalMaterials(model_dir, threads=1).evaluate("rand16", q)) <= 1.0


def test_a_lane_at_a_non_finite_position_answers_zero(model_dir):
    """A render's uv may hold inf or NaN (a mesh's bad texture coordinates): those lanes answer 0 and
    the others what they answer alone (their taps read out of the tables and crashed the process)."""
    material, q = KernelMaterials(model_dir).kernel("rand16"), random_queries(4000, seed=3)
    want = KernelMaterials(model_dir).evaluate("rand16", q)
    bad = np.zeros(len(q), bool)
    bad[::7] = True
    for value in (np.nan, np.inf, -np.inf):
        u = q[:, C.U].copy()
        u[bad] = value
        v = np.where(bad[::-1], value, q[:, C.V]).astype(np.float32)  # other lanes' v
        (rgb,) = material.answers([Float(c) for c in (u, v, *q[:, C.SIGMA:].T)])
        got = np.stack([np.asarray(c) for c in rgb], 1)
        finite = ~(bad | bad[::-1])
        np.testing.assert_array_equal(got[finite], want[finite])
        assert (got[~finite] == 0).all()
