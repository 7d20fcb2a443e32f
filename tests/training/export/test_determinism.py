"""A query's answer does not depend on its batch: same bits in one call, in any split, on any thread
count; the exact level of detail."""

import numpy as np
import onnxruntime as ort
import pytest
from onnx import helper

from neumip.core import contract as C
from neumip.engines.local import LocalMaterials
from neumip.core.config import MaterialConfig
from neumip.training.export.graph import build_onnx, random_weights, save_onnx
from neumip.training.export.lod import log2_mantissa
from neumip.training.export.onnx_graph import GraphWriter
from neumip.core.contract import random_queries
SPLITS = (1, 3, 17, 1000, 4099)
"""Chunk sizes the queries are cut into (cycled, so rows land at every offset of a call)."""


def _session(model, threads: int = 1) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    return ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])


def _queries(resolution: int, edge_queries) -> np.ndarray:
    """(N, 7): 12000 random queries and the edge queries (level boundaries, seams, grazing angles)."""
    return np.concatenate([random_queries(12_000, seed=31), edge_queries(resolution), random_queries(7, seed=2)])


def _in_pieces(session, q: np.ndarray, sizes) -> np.ndarray:
    """(N, 7) -> (N, 3), one call per piece, piece sizes cycling through `sizes`."""
    out, lo, i = [], 0, 0
    while lo < q.shape[0]:
        hi = min(lo + sizes[i % len(sizes)], q.shape[0])
        out.append(session.run(None, {C.ONNX_INPUT: q[lo:hi]})[0])
        lo, i = hi, i + 1
    return np.concatenate(out)


def _same_bits(a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape and a.dtype == b.dtype == np.float32
    differ = (a.view(np.uint32) != b.view(np.uint32)).any(axis=1)
    assert not differ.any(), f"{differ.sum()} of {len(a)} rows differ in their bits, first at row {differ.argmax()}"


@pytest.fixture(scope="module", params=[(True, 0, 0), (False, 0, 0), (True, 64, 64)], ids=["offset", "no-offset", "relief-base"])
def config(request):
    offset, base, relief = request.param
    return MaterialConfig(resolution=32, offset=offset, base=base, relief=relief)


def test_answers_do_not_depend_on_the_batch(config, edge_queries):
    model = build_onnx(config, random_weights(config, seed=4))
    session = _session(model)
    q = _queries(config.resolution, edge_queries)
    whole = session.run(None, {C.ONNX_INPUT: q})[0]  # (N, 3)
    assert (whole > 0).mean() > 0.9 and whole.std(axis=0).min() > 1e-2, "the material must vary"
    _same_bits(_in_pieces(session, q, SPLITS), whole)
    _same_bits(_in_pieces(session, q, (17,)), whole)
    _same_bits(_in_pieces(session, q[:600], (1,)), whole[:600])
    _same_bits(_in_pieces(session, q[::-1], (3, 1000)), whole[::-1])  # other neighbours
    _same_bits(_session(model, threads=2).run(None, {C.ONNX_INPUT: q})[0], whole)


def _groups(q: np.ndarray, lights: int, seed: int) -> np.ndarray:
    """Query groups of `lights` lights: each row of `q` plus the wi of other random queries."""
    more = [random_queries(len(q), seed=seed + j)[:, [C.WI_X, C.WI_Y]] for j in range(lights - 1)]
    return np.ascontiguousarray(np.concatenate([q, *more], axis=1))


@pytest.mark.parametrize("lights", [1, 2, 5])
def test_a_group_answers_each_light_as_its_single_query(config, edge_queries, lights):
    """Light j of a group gets the bits of the single query (u, v, sigma, wi_j, wo), in any split."""
    session = _session(build_onnx(config, random_weights(config, seed=4)))
    groups = _groups(_queries(config.resolution, edge_queries), lights, seed=40)
    assert groups.shape[1] == C.group_width(lights)
    whole = session.run(None, {C.ONNX_INPUT: groups})[0]
    assert whole.shape == (len(groups), 3 * lights)
    singles = session.run(None, {C.ONNX_INPUT: C.ungroup(groups)})[0]
    _same_bits(whole.reshape(-1, 3), singles)
    _same_bits(_in_pieces(session, groups, SPLITS), whole)
    _same_bits(session.run(None, {C.ONNX_INPUT: groups[:0]})[0], whole[:0])


def test_local_materials_answer_the_same_bits_for_any_threads_and_chunk(tmp_path, edge_queries):
    cfg = MaterialConfig(resolution=64)
    save_onnx(build_onnx(cfg, random_weights(cfg, seed=9)), tmp_path / "m.onnx")
    q = np.concatenate([random_queries(20_011, seed=8), edge_queries(cfg.resolution)])
    want = LocalMaterials(tmp_path, threads=1).evaluate("m", q)
    for threads, chunk in [(2, 4096), (2, 1000), (3, 17), (1, 333), (2, 1 << 20)]:
        _same_bits(LocalMaterials(tmp_path, threads=threads, chunk=chunk).evaluate("m", q), want)
    for n in (1, 5, 4097):  # a row alone or among few answers as it does among many
        _same_bits(LocalMaterials(tmp_path, threads=2).evaluate("m", q[:n]), want[:n])
    groups = _groups(q, 2, seed=50)  # groups: chunks are cut by groups, answers as their single queries
    want = LocalMaterials(tmp_path, threads=1).evaluate("m", C.ungroup(groups)).reshape(len(q), 6)
    for threads, chunk in [(2, 4096), (3, 17), (1, 1)]:
        _same_bits(LocalMaterials(tmp_path, threads=threads, chunk=chunk).evaluate("m", groups), want)


def _log2_session() -> ort.InferenceSession:
    g = GraphWriter()
    g.nodes.append(helper.make_node("Identity", [log2_mantissa(g, "m")], ["y"]))
    return _session(g.model("m", 1, "y", 1, 18, 9))


def test_log2_of_every_float32_mantissa():
    """All 2^23 float32 m in [1, 2): within 2e-7 of log2, in [0, 1), nondecreasing, 0 at m = 1."""
    m = (1.0 + np.arange(2**23, dtype=np.float64) / 2**23).astype(np.float32)[:, None]  # (2^23, 1)
    got = _log2_session().run(None, {"m": m})[0][:, 0]
    err = np.abs(got.astype(np.float64) - np.log2(m[:, 0].astype(np.float64)))
    assert err.max() < 2e-7, err.max()
    assert got[0] == 0.0 and got.min() >= 0.0 and got.max() < 1.0
    assert (np.diff(got) >= 0).all()


def test_level_of_detail_is_exact_on_level_boundaries():
    """A constant material whose pyramid holds its level index: sigma = 2^j / R answers level j exactly."""
    cfg = MaterialConfig(resolution=64, offset=False, channels=1, hidden=1, layers=1)
    weights = {name: np.zeros_like(w) for name, w in random_weights(cfg).items()}
    sizes = cfg.level_sizes()
    weights["pyramid"] = np.concatenate([np.full((s * s, 1), level, np.float32) for level, s in enumerate(sizes)])
    weights["decoder.0.weight"][:, 0] = 1.0  # rgb = the looked-up feature
    session = _session(build_onnx(cfg, weights))
    boundaries = [2.0**j / cfg.resolution for j in range(cfg.levels + 1)]  # level j exactly
    sigma = np.asarray(boundaries + [0.0, 1e-30, 1e30, 1.5 / 64])
    # u = v on the centre of texel 0 of the level read, so its bilinear weights are exactly (1, 0, 0, 0)
    uv = np.asarray([0.5 / s for s in sizes] + [0.5 / sizes[0]] * 2 + [0.5] + [0.5 / sizes[0]])
    q = C.pack_queries(uv, uv, sigma, np.zeros((len(sigma), 2)), np.zeros((len(sigma), 2)))
    got = session.run(None, {C.ONNX_INPUT: q})[0][:, 0]
    want = [*range(cfg.levels + 1), 0, 0, cfg.levels, np.log2(1.5)]
    np.testing.assert_array_equal(got[:-1], np.asarray(want[:-1], np.float32))
    assert abs(got[-1] - want[-1]) < 3e-7
