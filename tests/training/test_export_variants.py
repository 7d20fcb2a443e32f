"""Export graph variants (`GraphOptions`): parity with torch for each, the tap tables, the graph's shape."""

import numpy as np
import onnxruntime as ort
import pytest
import torch

from neumip.client import contract as C
from neumip.training.config import MaterialConfig
from neumip.training.export import GraphOptions, build_onnx, weights_from_state
from neumip.training.material import NeuMIPMaterial
from neumip.training.texture_tables import tap_atlas, tap_table, wrap_pad
from neumip.client.contract import random_queries
from tests.training.test_export import ATOL, RTOL, edge_queries

TAPS_VARIANTS = [
    GraphOptions(taps_per_row=t, blend=b, index_type=i)
    for t in (1, 2, 4)
    for b in ("sum", "gemm", "premultiplied")
    for i in ("int64", "int32")
    if (t == 4 or (b == "sum" and i == "int64"))
]


def _material(cfg: MaterialConfig, seed: int = 5) -> NeuMIPMaterial:
    torch.manual_seed(seed)
    mat = NeuMIPMaterial(cfg, init_std=0.5)
    if cfg.offset:
        with torch.no_grad():
            mat.offset_mlp[-1].bias.fill_(0.5)
    return mat


def _run(mat: NeuMIPMaterial, options: GraphOptions, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    model = build_onnx(mat.config, weights_from_state(mat.state_dict(), mat.config), options=options)
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        want = mat(torch.from_numpy(q)).numpy()
    return session.run(None, {C.ONNX_INPUT: q})[0], want


@pytest.fixture(scope="module")
def material32():
    return _material(MaterialConfig(resolution=32))


@pytest.mark.parametrize("options", TAPS_VARIANTS, ids=str)
def test_taps_variants_meet_the_parity_contract(material32, options):
    q = np.concatenate([random_queries(3000, seed=21), edge_queries(32)])
    got, want = _run(material32, options, q)
    assert want.std() > 1e-3
    np.testing.assert_allclose(got, want, atol=ATOL, rtol=RTOL)


def test_modulo_graph_still_matches(material32):
    got, want = _run(material32, GraphOptions(lookup="modulo"), random_queries(2000, seed=4))
    np.testing.assert_allclose(got, want, atol=ATOL, rtol=RTOL)


def test_gridsample_variant_matches(material32):
    q = np.concatenate([random_queries(3000, seed=22), edge_queries(32)])
    got, want = _run(material32, GraphOptions(lookup="gridsample"), q)
    np.testing.assert_allclose(got, want, atol=ATOL, rtol=RTOL)


@pytest.mark.parametrize(
    "cfg",
    [MaterialConfig(resolution=1), MaterialConfig(resolution=2, layers=1),
     MaterialConfig(resolution=8, offset=False, channels=3, hidden=5, layers=2),
     MaterialConfig(resolution=16, offset_channels=4, hidden=9, layers=3)],
    ids=["1x1", "2x2-one-layer", "8-no-offset", "16-odd-widths"],
)
def test_default_graph_on_unusual_configs(cfg):
    q = np.concatenate([random_queries(1000, seed=3), edge_queries(cfg.resolution)])
    got, want = _run(_material(cfg), GraphOptions(), q)
    np.testing.assert_allclose(got, want, atol=ATOL, rtol=RTOL)


@pytest.mark.parametrize("options", [GraphOptions(), GraphOptions(taps_per_row=1, blend="premultiplied"),
                                     GraphOptions(lookup="gridsample")], ids=str)
def test_empty_and_odd_batches(material32, options):
    model = build_onnx(material32.config, weights_from_state(material32.state_dict(), material32.config),
                       options=options)
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    for n in (0, 1, 3):
        assert session.run(None, {C.ONNX_INPUT: random_queries(n)})[0].shape == (n, 3)


def test_default_graph_has_no_modulo_and_stores_textures_once(material32):
    cfg = material32.config
    model = build_onnx(cfg, weights_from_state(material32.state_dict(), cfg))
    ops = {node.op_type for node in model.graph.node}
    assert "Mod" not in ops and "GridSample" not in ops
    dims = {i.name: tuple(i.dims) for i in model.graph.initializer}
    assert dims["pyramid"] == (cfg.atlas_rows(), cfg.channels)
    assert dims["offset_texture"] == (cfg.resolution**2, cfg.offset_channels)
    float_params = sum(int(np.prod(d)) for n, d in dims.items() if n in ("pyramid", "offset_texture"))
    assert float_params == cfg.atlas_rows() * cfg.channels + cfg.resolution**2 * cfg.offset_channels


def test_bad_options_are_clear_errors():
    with pytest.raises(ValueError, match="taps_per_row"):
        GraphOptions(taps_per_row=3)
    with pytest.raises(ValueError, match="lookup"):
        GraphOptions(lookup="texture")


# --- tap tables (numpy) ------------------------------------------------------------------------


def _reference_taps(size: int, x0: int, y0: int) -> list[int]:
    """Flat texel indices of the 4 bilinear taps at (x0, y0), x0, y0 in [-1, S - 1], wrap-around."""
    xs, ys = (x0 % size, (x0 + 1) % size), (y0 % size, (y0 + 1) % size)
    return [ys[0] * size + xs[0], ys[0] * size + xs[1], ys[1] * size + xs[0], ys[1] * size + xs[1]]


def test_wrap_pad_copies_opposite_edges():
    level = np.arange(9).reshape(3, 3, 1)
    padded = wrap_pad(level)[:, :, 0]
    assert padded.shape == (5, 5)
    assert padded[0, 0] == level[2, 2, 0] and padded[4, 4] == level[0, 0, 0]
    np.testing.assert_array_equal(padded[1:4, 1:4], level[:, :, 0])
    np.testing.assert_array_equal(padded[0, 1:4], level[2, :, 0])


@pytest.mark.parametrize("taps", [1, 2, 4])
@pytest.mark.parametrize("size", [1, 2, 5])
def test_tap_table_rows_hold_the_wrapped_footprint(size, taps):
    table = tap_table(np.arange(size * size).reshape(size, size, 1), taps)
    for y0 in range(-1, size):
        for x0 in range(-1, size):
            first = (y0 + 1) * table.width + (x0 + 1)
            got = np.concatenate([table.rows[first + o] for o in table.offsets])
            assert list(got) == _reference_taps(size, x0, y0), (x0, y0)


@pytest.mark.parametrize("taps", [1, 2, 4])
def test_tap_atlas_params_address_each_level(taps):
    sizes = [4, 2, 1]
    atlas = tap_atlas(sizes, taps)
    starts = np.cumsum([0] + [s * s for s in sizes])
    for level, size in enumerate(sizes):
        s, one, width, *bases = atlas.level_params[level]
        assert (s, one) == (size, 1)
        for y0 in range(-1, size):
            for x0 in range(-1, size):
                rows = [int(b) + x0 + y0 * int(width) for b in bases]
                got = np.concatenate([atlas.rows[r] for r in rows])
                assert list(got) == [starts[level] + t for t in _reference_taps(size, x0, y0)]
