"""The export's texture lookups: the wrap-padded quad tables, and the graph on unusual configs."""

import numpy as np
import onnxruntime as ort
import pytest
import torch

from neumip.core import contract as C
from neumip.core.contract import random_queries
from neumip.core.config import MaterialConfig
from neumip.training.export.graph import build_onnx, weights_from_state
from neumip.training.export.lookup import quad_atlas, quad_table, wrap_pad
from neumip.training.model.material import NeuMIPMaterial


def _material(cfg: MaterialConfig, seed: int = 5) -> NeuMIPMaterial:
    torch.manual_seed(seed)
    mat = NeuMIPMaterial(cfg, init_std=0.5)
    with torch.no_grad():
        mat.decoder[-1].bias.fill_(0.3)  # answers above the final ReLU's floor, so they can differ
        if cfg.offset:
            mat.offset_mlp[-1].bias.fill_(0.5)  # an offset large enough to matter
    return mat


@pytest.mark.parametrize(
    "cfg",
    [MaterialConfig(resolution=1), MaterialConfig(resolution=2, layers=1),
     MaterialConfig(resolution=8, offset=False, channels=3, hidden=5, layers=2),
     MaterialConfig(resolution=16, offset_channels=4, hidden=9, layers=3)],
    ids=["1x1", "2x2-one-layer", "8-no-offset", "16-odd-widths"],
)
def test_graph_on_unusual_configs(cfg, edge_queries, assert_parity):
    mat = _material(cfg)
    model = build_onnx(cfg, weights_from_state(mat.state_dict(), cfg))
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    q = np.concatenate([random_queries(1000, seed=3), edge_queries(cfg.resolution)])
    with torch.no_grad():
        want = mat(torch.from_numpy(q)).numpy()
    assert want.std() > 1e-3
    assert_parity(session.run(None, {C.ONNX_INPUT: q})[0], want)


def test_graph_has_no_modulo_and_stores_textures_once():
    cfg = MaterialConfig(resolution=32)
    mat = _material(cfg)
    model = build_onnx(cfg, weights_from_state(mat.state_dict(), cfg))
    ops = {node.op_type for node in model.graph.node}
    assert not ops & {"Mod", "GridSample", "Log", "ReduceSum"}
    dims = {i.name: tuple(i.dims) for i in model.graph.initializer}
    assert dims["pyramid"] == (cfg.atlas_rows(), cfg.channels)
    assert dims["offset_texture"] == (cfg.resolution**2, cfg.offset_channels)
    float_params = sum(int(np.prod(d)) for n, d in dims.items() if n in ("pyramid", "offset_texture"))
    assert float_params == cfg.atlas_rows() * cfg.channels + cfg.resolution**2 * cfg.offset_channels


def test_queries_gather_texel_rows_only():
    """A query's Gathers are its texel rows (one per texture, the pyramid's two levels in one): the
    level of detail reads its per-level tables with a Gemm (ONNX Runtime's Gather costs ~8 ns a
    row even from a small table). The other Gathers read constants only (folded at load)."""
    cfg = MaterialConfig(resolution=32)
    model = build_onnx(cfg, weights_from_state(_material(cfg).state_dict(), cfg))
    constant = {i.name for i in model.graph.initializer}
    for node in model.graph.node:  # in graph order: a node of constants computes constants (folded at load)
        if set(node.input) <= constant:
            constant.update(node.output)
    gathers = [n for n in model.graph.node if n.op_type == "Gather"]
    per_query = [n for n in gathers if not set(n.input) <= constant]
    assert len(per_query) == 2 and len(gathers) == 4


# --- quad tables (numpy) -----------------------------------------------------------------------


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


@pytest.mark.parametrize("size", [1, 2, 5])
def test_quad_table_rows_hold_the_wrapped_footprint(size):
    table = quad_table(np.arange(size * size).reshape(size, size, 1))
    assert table.shape == ((size + 1) ** 2, 4)
    for y0 in range(-1, size):
        for x0 in range(-1, size):
            assert list(table[(y0 + 1) * (size + 1) + (x0 + 1)]) == _reference_taps(size, x0, y0), (x0, y0)


def test_quad_atlas_params_address_each_level():
    sizes = [4, 2, 1]
    atlas = quad_atlas(sizes)
    starts = np.cumsum([0] + [s * s for s in sizes])
    for level, size in enumerate(sizes):
        s, one, width, base = atlas.level_params[level]
        assert (s, one, width) == (size, 1, size + 1)
        for y0 in range(-1, size):
            for x0 in range(-1, size):
                row = atlas.rows[int(base) + x0 + y0 * int(width)]
                assert list(row) == [starts[level] + t for t in _reference_taps(size, x0, y0)]
