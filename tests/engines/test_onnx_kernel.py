"""The interpreter (`engines/onnx_kernel.py`, its operators in `engines/onnx_ops.py`): a batched tensor
held as per-lane cells reshaped, transposed, tiled, sliced, concatenated, gathered and multiplied as
numpy does it to the whole tensor. Each lane's cells hold the tensor's own values, so any misplaced row
shows. Small graphs written with onnx.helper check the operators' semantics against ONNX Runtime (the
ONNX spec's reference here): negative slice steps and indices, integer tensors, casts; what the lanes
cannot hold is refused."""

from __future__ import annotations

import importlib

import numpy as np
import onnx
import pytest

pytest.importorskip("neumip.engines.kernel")  # drjit, after the libLLVM check

import drjit as dr  # noqa: E402
from drjit.llvm.ad import Float  # noqa: E402
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

from neumip.engines.kernel import KernelMaterial  # noqa: E402
from neumip.engines.local import ModelError  # noqa: E402
from neumip.engines.onnx_ops import (Dim, GraphError, Lanes, Ops, aligned_zeros, objects, packed_table,  # noqa: E402
                                     row_stride)
from neumip.core import contract as C  # noqa: E402

N = 3
OPS = Ops(importlib.import_module("drjit.llvm.ad"), {})


def batched(full: np.ndarray) -> Lanes:
    """A (N, ...) numpy tensor as Lanes: one cell per element of a row, one lane per row."""
    cells = [Float(full[(slice(None),) + index]) for index in np.ndindex(full.shape[1:])]
    return Lanes(objects((1, 1) + full.shape[1:], cells), 0)


def whole(x: Lanes) -> np.ndarray:
    """The numpy tensor that Lanes `x` holds (its batch axis outer x N x inner long)."""
    values = np.stack([np.broadcast_to(np.asarray(c), N) for c in x.cells.ravel()])  # literals: width 1
    values = values.reshape(x.cells.shape + (N,))
    a = x.axis
    values = np.moveaxis(values, -1, a + 1)  # (..., outer, N, inner, ...)
    shape = x.cells.shape
    return values.reshape(shape[:a] + (shape[a] * N * shape[a + 1],) + shape[a + 2:])


def node(op: str, **attrs):
    return helper.make_node(op, [], ["y"], **attrs)


@pytest.fixture
def groups():
    """(N, 4, 2) values 0..: a batch of 4 lights of (wi_x, wi_y) each."""
    return np.arange(N * 8, dtype=np.float32).reshape(N, 4, 2)


def test_the_export_s_light_rows_round_trip(groups):
    """(N, K, 2) -> (K, N, 2) -> (K N, 2) -> (K, N, 2) -> (N, K, 2) -> (N, 2 K): the export's path of
    a query group's lights (`training/export/graph.py`: `_lights` and the answer's reshapes)."""
    x = batched(groups)
    t = OPS.Transpose(node("Transpose"), x, perm=[1, 0, 2])
    np.testing.assert_array_equal(whole(t), groups.transpose(1, 0, 2))
    rows = OPS.Reshape(node("Reshape"), t, objects((2,), [Dim(4), 2]))
    np.testing.assert_array_equal(whole(rows), groups.transpose(1, 0, 2).reshape(4 * N, 2))
    back = OPS.Reshape(node("Reshape"), rows, objects((3,), [4, Dim(1), 2]))
    back = OPS.Transpose(node("Transpose"), back, perm=[1, 0, 2])
    flat = OPS.Reshape(node("Reshape"), back, np.array([0, -1]))
    np.testing.assert_array_equal(whole(flat), groups.reshape(N, 8))
    assert OPS.Shape(node("Shape"), rows).tolist() == [Dim(4), 2]


def test_tile_concat_slice_and_gather_follow_numpy(groups):
    x = OPS.Transpose(node("Transpose"), batched(groups), perm=[2, 0, 1])  # (2, N, 4)
    want = groups.transpose(2, 0, 1)
    np.testing.assert_array_equal(whole(OPS.Tile(node("Tile"), x, np.array([2, 3, 1]))), np.tile(want, (2, 3, 1)))
    both = OPS.Concat(node("Concat"), x, np.ones((1, 1, 2), np.float32), axis=2)
    np.testing.assert_array_equal(whole(both), np.concatenate([want, np.ones((2, N, 2))], axis=2))
    part = OPS.Slice(node("Slice"), x, np.array([1]), np.array([2**62]), np.array([2]), np.array([2]))
    np.testing.assert_array_equal(whole(part), want[:, :, 1::2])
    taken = OPS.Gather(node("Gather"), x, np.array([[3, 0]]), axis=2)
    np.testing.assert_array_equal(whole(taken), np.take(want, [[3, 0]], axis=2))


def test_products_with_constant_matrices_follow_numpy(groups):
    rng = np.random.default_rng(0)
    x = OPS.Reshape(node("Reshape"), batched(groups), np.array([-1, 8]))  # (N, 8)
    w = rng.integers(-3, 4, (8, 5)).astype(np.float32)  # small integers: every sum exact
    w[2] = 0.0
    full = groups.reshape(N, 8)
    np.testing.assert_array_equal(whole(OPS.Gemm(node("MatMul"), x, w, matmul=True)), full @ w)
    bias = rng.integers(-3, 4, (5, 1)).astype(np.float32)
    columns = OPS.Gemm(node("Gemm"), w.T.copy(), x, bias, alpha=2.0, transB=1)  # (5, N): the batch on columns
    assert columns.axis == 1
    np.testing.assert_array_equal(whole(columns), 2 * w.T @ full.T + bias)


def test_the_batch_axis_cannot_be_cut_or_mixed(groups):
    x = batched(groups)
    with pytest.raises(GraphError, match="Slice of the batch"):
        OPS.Slice(node("Slice"), x, np.array([1]), np.array([2]), np.array([0]))
    with pytest.raises(GraphError, match="mix with other axes"):
        OPS.Reshape(node("Reshape"), x, objects((2,), [8, Dim(1)]))
    with pytest.raises(GraphError, match="two computed tensors"):
        OPS.Gemm(node("MatMul"), x, x, matmul=True)



def test_elementwise_attributes_of_old_opsets_are_refused(groups):
    """Opset 6's Add broadcast along `axis`, numpy broadcasting since opset 7: refused, not misread."""
    old_add = helper.make_node("Add", ["x", "b"], ["y"], broadcast=1, axis=0)
    with pytest.raises(GraphError, match="attribute.s. axis, broadcast"):
        OPS.run(old_add, [batched(groups), np.ones(3, np.float32)])


def test_a_folded_power_keeps_its_base_s_type():
    """Pow's result has its base's type (the exponent may be another): float32 ** int64 stays float32,
    so a table computed with it is read as any other."""
    folded = OPS.run(helper.make_node("Pow", ["x", "e"], ["y"]), [np.float32([1.5, 2.0]), np.int64([2])])
    assert folded.dtype == np.float32 and folded.tolist() == [2.25, 4.0]


def test_every_listed_operator_has_an_evaluation():
    """`OPERATORS` (what a graph may use) and the evaluations agree: a listed operator without one would
    fail at load with an AttributeError, not a clear error."""
    from neumip.engines.onnx_ops import BINARY, OPERATORS, UNARY

    assert [op for op in OPERATORS if op not in UNARY and op not in BINARY and not hasattr(Ops, op)] == []

# --- small graphs against ONNX Runtime: the operators' semantics as the ONNX spec gives them -----------


def ints(*values) -> np.ndarray:
    return np.array(values, np.int64)


def against_onnx_runtime(tmp_path, nodes: list, **inits) -> tuple[np.ndarray, np.ndarray]:
    """A material whose graph is `nodes` (``queries`` (N, 7) -> ``rgb`` (N, 3)) with initializers
    `inits` -> (the interpreter's answers, ONNX Runtime's) on queries whose u, v span [-3, 3]."""
    import onnxruntime as ort

    graph = helper.make_graph(nodes, "probe",
                              [helper.make_tensor_value_info(C.ONNX_INPUT, TensorProto.FLOAT, ["N", 7])],
                              [helper.make_tensor_value_info(C.ONNX_OUTPUT, TensorProto.FLOAT, ["N", 3])],
                              initializer=[numpy_helper.from_array(v, k) for k, v in inits.items()])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    path = tmp_path / "probe.onnx"
    path.write_bytes(model.SerializeToString())
    rng = np.random.default_rng(0)
    q = np.concatenate([rng.uniform(-3, 3, (200, 2)), rng.uniform(0.01, 1, (200, 1)),
                        rng.uniform(-0.6, 0.6, (200, 4))], 1).astype(np.float32)
    material = KernelMaterial(path)  # first: a graph that both refuse gives the interpreter's error
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return material.evaluate(q), session.run([C.ONNX_OUTPUT], {C.ONNX_INPUT: q})[0]


def test_a_slice_with_a_negative_step_runs_to_the_start(tmp_path):
    """Slice with step -1 and the end INT64_MIN (numpy's ``[::-1]``): the query's columns reversed."""
    nodes = [helper.make_node("Slice", ["queries", "start", "end", "axes", "step"], ["reversed"]),
             helper.make_node("Slice", ["reversed", "zero", "three", "axes"], ["rgb"])]
    got, want = against_onnx_runtime(tmp_path, nodes, start=ints(-1), end=ints(-2**63), axes=ints(1),
                                     step=ints(-1), zero=ints(0), three=ints(3))
    np.testing.assert_array_equal(got, want)


def test_computed_negative_indices_count_from_the_table_s_end(tmp_path):
    """Gather of a constant table with computed indices in [-5, 4]: -1 is the last row."""
    nodes = [helper.make_node("Slice", ["queries", "zero", "one", "axes"], ["u"]),  # (N, 1) in [-3, 3]
             helper.make_node("Floor", ["u"], ["floored"]),
             helper.make_node("Cast", ["floored"], ["index"], to=7),  # INT64, in [-3, 2]
             helper.make_node("Gather", ["table", "index"], ["rows"]),  # (N, 1, 3)
             helper.make_node("Reshape", ["rows", "shape"], ["rgb"])]
    table = np.arange(15, dtype=np.float32).reshape(5, 3)
    got, want = against_onnx_runtime(tmp_path, nodes, table=table, zero=ints(0), one=ints(1), axes=ints(1),
                                     shape=ints(-1, 3))
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("row", [(1,), (3,), (4,), (2, 3), (28,), (32,)])
@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_a_table_s_rows_read_whole_are_onnx_runtime_s(tmp_path, row, dtype):
    """A table's rows are stored padded to a power of two and read by packet gathers (`onnx_ops.packed_table`):
    the first, a middle and the last value of each row read are ONNX Runtime's, in every width and type."""
    width = int(np.prod(row))
    nodes = [helper.make_node("Slice", ["queries", "zero", "one", "axes"], ["u"]),  # (N, 1) in [-3, 3]
             helper.make_node("Add", ["u", "three"], ["shifted"]),
             helper.make_node("Mul", ["shifted", "scale"], ["scaled"]),
             helper.make_node("Cast", ["scaled"], ["index"], to=7),  # INT64 rows in [0, 299]
             helper.make_node("Gather", ["table", "index"], ["rows"]),  # (N, 1, *row)
             helper.make_node("Reshape", ["rows", "flat"], ["values"]),  # (N, width)
             helper.make_node("Gather", ["values", "pick"], ["picked"], axis=1),  # (N, 3)
             helper.make_node("Cast", ["picked"], ["rgb"], to=TensorProto.FLOAT)]
    table = np.random.default_rng(1).standard_normal((300, *row)).astype(dtype)
    got, want = against_onnx_runtime(tmp_path, nodes, table=table, zero=ints(0), one=ints(1), axes=ints(1),
                                     three=np.float32(3.0), scale=np.float32(49.9), flat=ints(-1, width),
                                     pick=ints(0, width // 2, width - 1))
    np.testing.assert_array_equal(got, want)
    assert len(np.unique(got[:, 0])) > 100  # many rows read
    stored = np.asarray(packed_table(dr.llvm.ad, table)).reshape(300, -1)  # rows of 1, 4, 4, 8, 32, 32
    assert stored.shape[1] == row_stride(width) == 2 ** int(np.ceil(np.log2(width)))
    np.testing.assert_array_equal(stored[:, :width], table.reshape(300, width))


def test_every_table_read_is_a_packet_load():
    """The tables are aligned (`onnx_ops.aligned_zeros`), so drjit reads every row whole: the kernel of a read of
    tables of each width and type has packet loads and no per-value gather (drjit reads a table mapped from numpy
    memory one value at a time where it is not aligned to a vector of lanes)."""
    import re

    rng = np.random.default_rng(2)
    widths = [w for w in (2, 3, 4, 24, 28) for _ in range(3)]  # three tables of each: each aligned by chance or not
    tables = {f"t{i}": (packed_table(dr.llvm.ad, rng.standard_normal((500, w)).astype(t)), (500, w))
              for i, (w, t) in enumerate((w, t) for w in widths for t in (np.float32, np.float16))}
    assert all(aligned_zeros((7, w), t).ctypes.data % 64 == 0 for w in (1, 3, 28) for t in (np.float32, np.float16))
    rows = dr.llvm.ad.UInt32(rng.integers(0, 500, 1000).astype(np.uint32))
    dr.eval([t for t, _ in tables.values()], rows)
    ops = Ops(dr.llvm.ad, tables)
    total = Float(0.0)
    for i in range(len(tables)):
        read = ops.Gather(helper.make_node("Gather", [f"t{i}", "index"], ["rows"]), f"table t{i}",
                          Lanes(objects((1, 1, 1), [rows]), 0))
        for value in read.cells.ravel():
            total += value
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.eval(total)
        ir = "".join(str(k["ir"].getvalue() if hasattr(k["ir"], "getvalue") else k["ir"])
                     for k in dr.kernel_history() if "ir" in k)
    assert re.search(r"@gather_\d+xf(16|32)", ir), "no packet loads"
    assert "llvm.masked.gather" not in ir, "a table read one value at a time"


def test_integer_lanes_divide_and_rectify_as_integers(tmp_path):
    """Div of int64 tensors truncates toward zero; Relu of one stays an integer."""
    nodes = [helper.make_node("Slice", ["queries", "zero", "three", "axes"], ["uvs"]),
             helper.make_node("Mul", ["uvs", "ten"], ["scaled"]),
             helper.make_node("Cast", ["scaled"], ["whole"], to=7),  # INT64 in [-30, 30]
             helper.make_node("Div", ["whole", "seven"], ["quotient"]),
             helper.make_node("Relu", ["whole"], ["rectified"]),
             helper.make_node("Div", ["rectified", "four"], ["quarter"]),
             helper.make_node("Add", ["quotient", "quarter"], ["sum"]),
             helper.make_node("Cast", ["sum"], ["rgb"], to=1)]
    got, want = against_onnx_runtime(tmp_path, nodes, zero=ints(0), three=ints(3), axes=ints(1),
                                     ten=np.float32([10.0]), seven=ints(7), four=ints(4))
    assert (want < 0).any() and (want > 0).any()
    np.testing.assert_array_equal(got, want)


def test_unsqueeze_places_negative_axes_in_the_output_s_rank():
    x = np.arange(3, dtype=np.float32)
    assert OPS.Unsqueeze(node("Unsqueeze"), x, ints(-2, -1)).shape == (3, 1, 1)
    assert OPS.Unsqueeze(node("Unsqueeze"), x, ints(-1, 0)).shape == (1, 3, 1)


@pytest.mark.parametrize("to", [10, 11, 3])  # FLOAT16, DOUBLE, INT8
def test_a_cast_to_a_type_the_lanes_cannot_hold_is_refused(tmp_path, to):
    nodes = [helper.make_node("Slice", ["queries", "zero", "three", "axes"], ["uvs"]),
             helper.make_node("Cast", ["uvs"], ["narrow"], to=to),
             helper.make_node("Cast", ["narrow"], ["rgb"], to=1)]
    with pytest.raises(ModelError, match="Cast node .*: a cast to"):
        against_onnx_runtime(tmp_path, nodes, zero=ints(0), three=ints(3), axes=ints(1))


def test_a_node_reading_a_name_nothing_produces_is_a_damaged_file(tmp_path):
    """A graph whose node reads a tensor no input, initializer or earlier node gives (a name damaged on disk):
    refused at load, naming the node and the name."""
    nodes = [helper.make_node("Slice", ["queries", "zero", "three", "axes"], ["uvs"]),
             helper.make_node("Mul", ["uvs", "u\u00e0s"], ["rgb"])]
    with pytest.raises(ModelError, match="Mul node .* reads 'u\u00e0s', which nothing before it produces"):
        against_onnx_runtime(tmp_path, nodes, zero=ints(0), three=ints(3), axes=ints(1))


def test_a_table_of_integers_read_with_computed_indices_is_refused(tmp_path):
    nodes = [helper.make_node("Slice", ["queries", "zero", "one", "axes"], ["u"]),
             helper.make_node("Cast", ["u"], ["index"], to=7),
             helper.make_node("Gather", ["table", "index"], ["rows"]),
             helper.make_node("Reshape", ["rows", "shape"], ["whole"]),
             helper.make_node("Cast", ["whole"], ["rgb"], to=1)]
    with pytest.raises(ModelError, match="table 'table' of int64"):
        against_onnx_runtime(tmp_path, nodes, table=np.arange(15).reshape(5, 3), zero=ints(0), one=ints(1),
                             axes=ints(1), shape=ints(-1, 3))


def test_a_slice_or_squeeze_that_would_cut_the_batch_is_refused(groups):
    rows = OPS.Reshape(node("Reshape"), batched(groups), objects((2,), [Dim(4), 2]))  # (4 N, 2)
    with pytest.raises(GraphError, match="Slice of the batch"):
        OPS.Slice(node("Slice"), rows, np.array([0]), objects((1,), [Dim(1)]), np.array([0]))
    with pytest.raises(GraphError, match="Squeeze of axis 1, of length 2"):
        OPS.Squeeze(node("Squeeze"), rows, np.array([1]))


def test_an_answer_that_is_not_float32_is_refused(tmp_path):
    """The contract's ``rgb`` is float32: a graph declaring another type is refused at load."""
    nodes = [helper.make_node("Slice", ["queries", "zero", "three", "axes"], ["uvs"]),
             helper.make_node("Cast", ["uvs"], ["rgb"], to=7)]
    graph = helper.make_graph(nodes, "probe",
                              [helper.make_tensor_value_info(C.ONNX_INPUT, TensorProto.FLOAT, ["N", 7])],
                              [helper.make_tensor_value_info(C.ONNX_OUTPUT, TensorProto.INT64, ["N", 3])],
                              initializer=[numpy_helper.from_array(ints(v), k)
                                           for k, v in {"zero": 0, "three": 3, "axes": 1}.items()])
    path = tmp_path / "ints.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)]), path)
    with pytest.raises(ModelError, match="ints.onnx: 'rgb' must be float32"):
        KernelMaterial(path)


def test_a_gemm_scales_its_bias_by_beta(tmp_path):
    """Gemm alpha A B^T + beta C on the query (the batch on A's rows)."""
    w = np.random.default_rng(1).normal(size=(3, 7)).astype(np.float32)
    nodes = [helper.make_node("Gemm", ["queries", "w", "c"], ["rgb"], transB=1, alpha=0.5, beta=2.0)]
    got, want = against_onnx_runtime(tmp_path, nodes, w=w, c=np.float32([1, 2, 3]))
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)


def test_an_operator_on_a_type_drjit_lacks_is_a_clear_error(tmp_path):
    """Sqrt of an integer tensor (ONNX Runtime refuses the graph too): drjit's RuntimeError becomes a
    ModelError naming the node, as any other failure of a node does."""
    nodes = [helper.make_node("Slice", ["queries", "zero", "three", "axes"], ["uvs"]),
             helper.make_node("Cast", ["uvs"], ["whole"], to=7),
             helper.make_node("Sqrt", ["whole"], ["root"]),
             helper.make_node("Cast", ["root"], ["rgb"], to=1)]
    with pytest.raises(ModelError, match="Sqrt node 'root'"):
        against_onnx_runtime(tmp_path, nodes, zero=ints(0), three=ints(3), axes=ints(1))
