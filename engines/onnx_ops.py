"""ONNX operators on per-lane tensors: what `onnx_kernel.LaneGraph` evaluates, node by node.

- **Shapes.** A tensor whose first dimension is the batch is held as the drjit arrays of one row: a
  (N, k) tensor is k drjit Floats. The export also reshapes and transposes the batch (a query group's
  lights become rows ``j N + n``), so a `Lanes` tensor holds its cells in a numpy object array whose
  batch dimension is ``outer x N x inner`` long: ``outer`` and ``inner`` are ordinary axes of the
  array, N the lanes. `Dim` is such a length in shape arithmetic (``Shape``, ``Concat`` of sizes).
- **Constants.** Each operator also computes on numpy constants (how the graph's constant part is
  folded). A matrix product with a constant matrix becomes per-lane dot products whose coefficients
  are literals of the kernel; zero coefficients are skipped, so the export's 0/1 column shuffles cost
  nothing. A ``Gather`` with computed indices reads a constant table as a flat drjit array.
- **Types.** Computed tensors are float32, int32 (int64 held as int32) or bool (`CASTS`).
- **Rounding.** Every operator rounds per element, so a lane's answer does not depend on the others
  (or on how a batch is cut); sums of products run in one order (fma chains from the bias), another
  order than ONNX Runtime's: answers agree with it within the export's parity tolerance.

Needs numpy, onnx and drjit.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass
from types import ModuleType

import drjit as dr
import numpy as np
import onnx
from onnx import TensorProto, numpy_helper


class GraphError(ValueError):
    """A graph the interpreter cannot evaluate: its message says which operator or shape, and why."""


@dataclass(frozen=True)
class Dim:
    """A length ``count x N`` in shape arithmetic: N is the number of lanes (unknown while tracing)."""

    count: int

    def __mul__(self, other):
        if isinstance(other, Dim):
            raise GraphError("a shape multiplies the batch size by itself")
        return Dim(self.count * int(other))

    __rmul__ = __mul__

    def __floordiv__(self, other):
        if isinstance(other, Dim) or self.count % int(other):
            raise GraphError(f"a shape divides the batch size {self} by {other}")
        return Dim(self.count // int(other))

    def __repr__(self) -> str:
        return "N" if self.count == 1 else f"{self.count}N"


@dataclass
class Lanes:
    """A tensor computed per lane. Its logical shape is that of ``cells`` with axes ``axis`` and
    ``axis + 1`` (lengths ``outer``, ``inner``) replaced by one axis of length ``outer x N x inner``:
    element ``(o, n, i)`` of that axis is row ``o N inner + n inner + i``. Each cell is a drjit array
    with one entry per lane."""

    cells: np.ndarray
    axis: int

    @property
    def rank(self) -> int:
        return self.cells.ndim - 1

    @property
    def shape(self) -> tuple:
        s = self.cells.shape
        return s[:self.axis] + (Dim(s[self.axis] * s[self.axis + 1]),) + s[self.axis + 2:]

    def storage_axis(self, axis: int) -> int:
        """The cells' axis of logical axis ``axis`` (not the lane axis)."""
        return axis if axis < self.axis else axis + 1

    def with_cells(self, cells: np.ndarray) -> "Lanes":
        return Lanes(cells, self.axis)


def objects(shape, values) -> np.ndarray:
    """An object array of `shape` holding `values` (flat, in order) as they are (np.array would read
    drjit arrays as sequences)."""
    out = np.empty(int(np.prod(shape, dtype=np.int64)), object)
    for i, value in enumerate(values):
        out[i] = value
    return out.reshape(shape)


def elementwise(fn, *args) -> np.ndarray:
    """`fn` over the cells of `args` (object arrays or numpy constants), numpy broadcasting. (numpy
    would report the CPU's floating-point flags that drjit's folding of literals raised: ignored.)"""
    with np.errstate(all="ignore"):
        return np.frompyfunc(fn, len(args), 1)(*args)


def lift(backend: ModuleType, value):
    """A cell as a drjit array: a Python or numpy scalar becomes a literal of its type."""
    if isinstance(value, (bool, np.bool_)):
        return backend.Bool(bool(value))
    if isinstance(value, (int, np.integer)):
        return backend.Int32(int(value))
    if isinstance(value, (float, np.floating)):
        return backend.Float(float(value))
    return value


def scalars(value: np.ndarray) -> np.ndarray:
    """A numpy constant as an object array of Python scalars (drjit literals when combined with lanes)."""
    value = np.asarray(value)
    return objects(value.shape, value.ravel().tolist())


# --- operators ---------------------------------------------------------------------------------------


class Ops:
    """The operators, each on numpy constants (folded) or `Lanes` (traced); ``backend`` None while
    folding. ``tables``: {name: (flat drjit array, shape)} of the textures."""

    def __init__(self, backend: ModuleType | None, tables: dict) -> None:
        self.jit, self.tables = backend, tables

    def run(self, node, args):
        op = node.op_type
        if (op in UNARY or op in BINARY) and node.attribute:  # opset 6's broadcast and axis, say
            raise GraphError(f"attribute(s) {', '.join(a.name for a in node.attribute)} (none since opset 7)")
        if op in UNARY:
            return self.unary(args[0], op)
        if op in BINARY:
            return _fold(args, lambda a, b: self.binary(a, b, *BINARY[op]))  # Max, Min, Sum: any count
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
        return getattr(self, op)(node, *args, **attrs)

    # -- elementwise ------------------------------------------------------------------------------

    def unary(self, x, name: str):
        numpy_fn, drjit_fn = UNARY[name]
        if not isinstance(x, Lanes):
            return numpy_fn(np.asarray(x))
        return x.with_cells(elementwise(drjit_fn, x.cells))

    def binary(self, a, b, numpy_fn, drjit_fn):
        if not isinstance(a, Lanes) and not isinstance(b, Lanes):
            return numpy_fn(np.asarray(a), np.asarray(b))
        (a, b), axis = self.align(a, b)
        return Lanes(elementwise(drjit_fn, a, b), axis)

    def align(self, *values) -> tuple[list[np.ndarray], int]:
        """Cells of `values` (Lanes or constants) broadcast-compatible, and the result's lane axis."""
        rank = max(v.rank if isinstance(v, Lanes) else np.ndim(v) for v in values)
        lanes = [v for v in values if isinstance(v, Lanes)]
        axes = {rank - v.rank + v.axis for v in lanes}
        splits = {v.cells.shape[v.axis:v.axis + 2] for v in lanes}
        if len(axes) != 1 or len(splits) != 1:
            shapes = [v.shape if isinstance(v, Lanes) else np.shape(v) for v in values]
            raise GraphError(f"tensors batched differently: {shapes}")
        (axis,) = axes
        out = []
        for v in values:
            if isinstance(v, Lanes):
                out.append(v.cells.reshape((1,) * (rank - v.rank) + v.cells.shape))
            else:
                c = np.asarray(v).reshape((1,) * (rank - np.ndim(v)) + np.shape(v))
                if c.shape[axis] != 1:
                    raise GraphError(f"a constant of shape {np.shape(v)} against the batch axis")
                out.append(scalars(c.reshape(c.shape[:axis + 1] + (1,) + c.shape[axis + 1:])))
        return out, axis

    def Div(self, node, a, b):
        if not isinstance(a, Lanes) and not isinstance(b, Lanes):
            a, b = np.asarray(a), np.asarray(b)
            return a / b if a.dtype.kind == "f" else _int_divide(a, b)
        with dr.scoped_set_flag(dr.JitFlag.FastMath, False):  # GPU: div.rn, as ONNX Runtime rounds
            return self.binary(a, b, None, _divide)

    def Clip(self, node, x, lo=None, hi=None):
        if lo is not None:
            x = self.binary(x, lo, *BINARY["Max"])
        return x if hi is None else self.binary(x, hi, *BINARY["Min"])

    def Where(self, node, cond, a, b):
        if not any(isinstance(v, Lanes) for v in (cond, a, b)):
            return np.where(cond, a, b)
        cells, axis = self.align(cond, a, b)
        return Lanes(elementwise(dr.select, *cells), axis)

    def Cast(self, node, x, to):
        if not isinstance(x, Lanes):
            return np.asarray(x).astype(onnx.helper.tensor_dtype_to_np_dtype(to))
        if to not in CASTS:
            raise GraphError(f"a cast to {TensorProto.DataType.Name(to)} (computed tensors are float32, "
                             "int32, int64 (held as int32) or bool)")
        jit, kind = self.jit, CASTS[to]

        def convert(c):
            if kind == "Bool":
                return c if dr.is_mask_v(c) else c != 0
            return getattr(jit, kind)(dr.select(c, 1, 0) if dr.is_mask_v(c) else c)

        return x.with_cells(elementwise(lambda c: lift(jit, convert(c)), x.cells))

    def Identity(self, node, x):
        return x

    def Constant(self, node, **attrs):
        if "value" not in attrs:
            raise GraphError(f"a Constant with {', '.join(attrs)} (only 'value' is supported)")
        return numpy_helper.to_array(attrs["value"])

    # -- matrix products ----------------------------------------------------------------------------

    def MatMul(self, node, a, b):
        return self.Gemm(node, a, b, matmul=True)

    def Gemm(self, node, a, b, c=None, alpha=1.0, beta=1.0, transA=0, transB=0, matmul=False):
        """alpha A' B' + beta C (A' = A or its transpose, B' likewise) where A or B is a constant
        (MatMul: A B, constant B on a batch of rows, or constant A on columns)."""
        if not isinstance(a, Lanes) and not isinstance(b, Lanes):
            a, b = np.asarray(a), np.asarray(b)
            if matmul:
                return np.matmul(a, b)
            a, b = (a.T if transA else a), (b.T if transB else b)
            product = np.float32(alpha) * (a @ b)
            return product if c is None else product + np.float32(beta) * np.asarray(c)
        if isinstance(a, Lanes) and isinstance(b, Lanes):
            raise GraphError("a product of two computed tensors (only products with a constant matrix)")
        if not matmul:
            a = self.Transpose(node, a, perm=[1, 0]) if transA else a
            b = self.Transpose(node, b, perm=[1, 0]) if transB else b
        if c is not None and beta != 1.0:
            c = self.binary(c, np.float32(beta), *BINARY["Mul"])
        if isinstance(a, Lanes):
            return self._rows(a, np.asarray(b, np.float32) * np.float32(alpha), c)
        # constant A on columns of B: (B^T A^T)^T, the batch on B's columns
        if b.rank != 2 or np.ndim(a) != 2:
            raise GraphError("a constant matrix times a batched tensor of rank other than 2")
        if c is not None:
            c = self.Transpose(node, c, perm=[1, 0]) if isinstance(c, Lanes) else np.asarray(c).T
        w = np.asarray(a, np.float32).T * np.float32(alpha)
        out = self._rows(self.Transpose(node, b, perm=[1, 0]), w, c)
        return self.Transpose(node, out, perm=[1, 0])

    def _rows(self, x: Lanes, w: np.ndarray, start) -> Lanes:
        """x (..., k) (the batch not on the last axis) @ constant w (k, m) (+ start) -> (..., m): per
        output a chain of fmas from ``start`` (or the first term), zero coefficients skipped."""
        if w.ndim != 2 or x.shape[-1] != w.shape[0] or x.axis == x.rank - 1:
            raise GraphError(f"a product of {x.shape} and a constant {w.shape}")
        rows = x.cells.reshape(-1, w.shape[0])
        out_shape = x.cells.shape[:-1] + (w.shape[1],)
        if start is not None:  # the bias (or a computed tensor) in the output's layout
            start = self.align(Lanes(np.empty(out_shape, object), x.axis), start)[0][1]
            start = np.broadcast_to(start, out_shape).reshape(-1, w.shape[1])
        cells = []
        for r, row in enumerate(rows):
            for j in range(w.shape[1]):
                acc = None if start is None else start[r, j]
                for k in np.flatnonzero(w[:, j]):
                    acc = _fma(row[k], float(w[k, j]), acc)
                cells.append(lift(self.jit, 0.0 if acc is None else acc))
        return Lanes(objects(out_shape, cells), x.axis)

    # -- gathers --------------------------------------------------------------------------------------

    def Gather(self, node, data, indices, axis=0):
        if not isinstance(data, Lanes) and not isinstance(indices, Lanes):
            return np.take(np.asarray(data), np.asarray(indices).astype(np.int64), axis=axis)
        if isinstance(data, Lanes):
            axis = axis % data.rank
            if axis == data.axis:
                raise GraphError("a Gather along the batch axis")
            taken = np.take(data.cells, np.asarray(indices).astype(np.int64), axis=data.storage_axis(axis))
            shift = np.ndim(indices) - 1
            return Lanes(taken, data.axis + (shift if axis < data.axis else 0))
        if node.input[0] not in self.tables or axis not in (0, -len(self.tables[node.input[0]][1])):
            raise GraphError("computed indices must read a constant table along its first axis")
        table, shape = self.tables[node.input[0]]
        rows, width = shape[0], int(np.prod(shape[1:], dtype=np.int64))
        stride = row_stride(width)  # the stored row (`packed_table`)
        jit = self.jit
        row_type = jit.ArrayXf16 if type(table) is jit.Float16 else jit.ArrayXf

        def read(index):
            index = jit.Int32(index)
            index = dr.select(index < 0, index + rows, index)  # -1: the last row
            row = jit.UInt32(dr.clip(index, 0, rows - 1))  # out of range: ONNX Runtime refuses
            if stride == 1:
                return [jit.Float(dr.gather(type(table), table, row))]
            values = dr.gather(row_type, table, row, shape=(stride, dr.width(row)))  # packet loads
            return [jit.Float(values[i]) for i in range(width)]  # float16: exact

        values = [value for index in indices.cells.ravel() for value in read(index)]
        return Lanes(objects(indices.cells.shape + tuple(shape[1:]), values), indices.axis)

    # -- shapes ---------------------------------------------------------------------------------------

    def Shape(self, node, x, start=0, end=None):
        dims = (x.shape if isinstance(x, Lanes) else np.shape(x))[start:end]
        if any(isinstance(d, Dim) for d in dims):
            return objects((len(dims),), dims)
        return np.asarray(dims, np.int64)

    def Reshape(self, node, x, shape, allowzero=0):
        old = x.shape if isinstance(x, Lanes) else np.shape(x)
        target = [old[i] if _is(d, 0) and not allowzero else d
                  for i, d in enumerate(np.asarray(shape).ravel())]
        if not isinstance(x, Lanes):
            return np.reshape(x, [int(d) for d in target])
        # the cells hold the tensor in row-major order with N left out: `before` cells up to the
        # batch axis's outer part, `after` from its inner part on
        before, after = _size(x.cells.shape[:x.axis + 1]), _size(x.cells.shape[x.axis + 1:])
        batch = [i for i, d in enumerate(target) if isinstance(d, Dim)]
        free = [i for i, d in enumerate(target) if _is(d, -1)]
        if len(batch) > 1 or len(free) > 1 or not batch + free:
            raise GraphError(f"reshape of batched {x.shape} to {target}")
        if batch and free:  # the -1 is an axis of its own
            rest = _size(d for i, d in enumerate(target) if i not in (batch[0], free[0]))
            target[free[0]] = before * after // (target[batch[0]].count * rest)
        j = (batch or free)[0]
        head, tail = _size(target[:j]), _size(target[j + 1:])
        outer, inner = (before // head, after // tail) if head and tail else (0, 0)
        if before % head or after % tail or (batch and outer * inner != target[j].count):
            raise GraphError(f"reshape of batched {x.shape} to {target}: the batch would mix with other axes")
        dims = [int(d) for d in target[:j]] + [outer, inner] + [int(d) for d in target[j + 1:]]
        return Lanes(x.cells.reshape(dims), j)

    def Flatten(self, node, x, axis=1):
        shape = x.shape if isinstance(x, Lanes) else np.shape(x)
        return self.Reshape(node, x, objects((2,), [_prod(shape[:axis]), _prod(shape[axis:])]), allowzero=1)

    def Transpose(self, node, x, perm=None):
        rank = x.rank if isinstance(x, Lanes) else np.ndim(x)
        perm = list(perm) if perm is not None else list(range(rank))[::-1]
        if not isinstance(x, Lanes):
            return np.transpose(x, perm)
        storage = []
        for p in perm:
            storage += [x.axis, x.axis + 1] if p == x.axis else [x.storage_axis(p)]
        return Lanes(x.cells.transpose(storage), perm.index(x.axis))

    def Concat(self, node, *xs, axis):
        if not any(isinstance(v, Lanes) for v in xs):
            return _concat_shapes(xs, axis)
        rank = next(v.rank for v in xs if isinstance(v, Lanes))
        axis %= rank
        cells, lane = self.align(*xs)
        if axis == lane:
            raise GraphError("a Concat along the batch axis")
        storage = axis if axis < lane else axis + 1
        full = np.broadcast_shapes(*(c.shape[:storage] + (1,) + c.shape[storage + 1:] for c in cells))
        parts = [np.broadcast_to(c, full[:storage] + (c.shape[storage],) + full[storage + 1:]) for c in cells]
        joined = np.concatenate(parts, axis=storage)  # constants' cells as literals of the lanes' arrays
        return Lanes(elementwise(lambda c: lift(self.jit, c), joined), lane)

    def Slice(self, node, x, starts, ends, axes=None, steps=None):
        rank = x.rank if isinstance(x, Lanes) else np.ndim(x)
        shape = x.shape if isinstance(x, Lanes) else np.shape(x)
        axes = list(range(len(starts))) if axes is None else [int(a) % rank for a in np.asarray(axes)]
        steps = [1] * len(axes) if steps is None else [int(s) for s in np.asarray(steps)]
        index = [slice(None)] * (rank + (1 if isinstance(x, Lanes) else 0))
        for a, s, e, st in zip(axes, np.asarray(starts).tolist(), np.asarray(ends).tolist(), steps):
            if isinstance(x, Lanes) and a == x.axis:
                whole = e.count >= shape[a].count if isinstance(e, Dim) else e >= 2**31 - 1
                if s != 0 or st != 1 or not whole:
                    raise GraphError("a Slice of the batch axis")
                continue
            axis = x.storage_axis(a) if isinstance(x, Lanes) else a
            index[axis] = _slice(int(s), int(e), st, int(shape[a]))
        if not isinstance(x, Lanes):
            return np.asarray(x)[tuple(index)]
        return x.with_cells(x.cells[tuple(index)])

    def Tile(self, node, x, repeats):
        repeats = [int(r) for r in np.asarray(repeats)]
        if not isinstance(x, Lanes):
            return np.tile(x, repeats)
        storage = []
        for a, r in enumerate(repeats):
            storage += [r, 1] if a == x.axis else [r]
        return x.with_cells(np.tile(x.cells, storage))

    def Unsqueeze(self, node, x, axes=None):
        shape = list(x.shape if isinstance(x, Lanes) else np.shape(x))
        rank = len(shape) + np.size(axes)  # negative axes count from the output's end
        for a in sorted(int(a) % rank for a in np.asarray(axes).ravel()):
            shape.insert(a, 1)
        return self.Reshape(node, x, objects((len(shape),), shape), allowzero=1)

    def Squeeze(self, node, x, axes=None):
        shape = list(x.shape if isinstance(x, Lanes) else np.shape(x))
        if axes is None:
            axes = [i for i, d in enumerate(shape) if _is(d, 1)]
        axes = [int(a) % len(shape) for a in np.asarray(axes).ravel()]
        for a in axes:
            if not _is(shape[a], 1):
                raise GraphError(f"a Squeeze of axis {a}, of length {shape[a]}")
        kept = [d for i, d in enumerate(shape) if i not in axes]
        return self.Reshape(node, x, objects((len(kept),), kept), allowzero=1)


def row_stride(width: int) -> int:
    """The stored length of a table's row of `width` values: the next power of two, so that a row is read by
    drjit's packet gathers (a few vector loads a lane) instead of one gather a value."""
    return 1 << max(int(width) - 1, 0).bit_length()


def packed_table(backend: ModuleType, table: np.ndarray):
    """A constant table (rows, ...) as a flat drjit array, each row padded with zeros to `row_stride` values.
    float16 tables (the export's with `half_textures`, whose reads are cast to float32) stay float16: a read converts
    its values to float32, exactly, so the answers are those of float32 tables, at half the memory."""
    rows = np.ascontiguousarray(table).reshape(len(table), -1)
    padded = aligned_zeros((len(rows), row_stride(rows.shape[1])), rows.dtype)
    padded[:, :rows.shape[1]] = rows
    return (backend.Float16 if table.dtype == np.float16 else backend.Float)(padded.ravel())


TABLE_ALIGNMENT = 64
"""Bytes a table's first value is aligned to. drjit maps a numpy array's memory without copying it, and on the LLVM
backend reads it with packet gathers only where it is aligned to a vector of lanes (16 x 4 bytes with AVX-512);
numpy aligns to 16 bytes, so without this a table's rows were read whole or one value at a time by chance."""


def aligned_zeros(shape: tuple, dtype) -> np.ndarray:
    """np.zeros(shape, dtype) whose data start at a multiple of `TABLE_ALIGNMENT` bytes (a view of a larger buffer,
    which it keeps alive)."""
    size = int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize
    raw = np.zeros(size + TABLE_ALIGNMENT, np.uint8)
    start = -raw.ctypes.data % TABLE_ALIGNMENT
    return raw[start:start + size].view(dtype).reshape(shape)


def _product(a, b):
    """a * b rounded on its own, as ONNX Runtime rounds it, also where it is added to something next:
    on the CUDA backend ptxas fuses a product and a following sum into one fma (drjit emits them
    without a rounding mode), whose single rounding differs from ONNX Runtime's two. There the product
    is an fma with 0 (kept: constant propagation off), which rounds like a product and is not fused."""
    array = a if dr.is_array_v(a) else b
    if not (dr.is_float_v(array) and dr.backend_v(array) == dr.JitBackend.CUDA):
        return a * b
    with dr.scoped_set_flag(dr.JitFlag.ConstantPropagation, False):
        return dr.fma(a, b, 0.0)


def _divide(a, b):
    """a / b of drjit arrays (or one and a Python scalar): ONNX's integer Div truncates, as drjit's
    ``//`` of integers does."""
    array = a if dr.is_array_v(a) else b
    return a / b if dr.is_float_v(array) else a // b


def _sqrt(x):
    with dr.scoped_set_flag(dr.JitFlag.FastMath, False):  # GPU: sqrt.rn, as ONNX Runtime rounds
        return dr.sqrt(x)


def _same_dtype(fn):
    """A numpy function whose result keeps its argument's dtype (float32 stays float32)."""
    return lambda x: fn(x).astype(x.dtype)


UNARY = {  # name: (on numpy constants, on a drjit array)
    "Relu": (_same_dtype(lambda x: np.maximum(x, 0)), lambda x: dr.maximum(x, 0)), "Sqrt": (np.sqrt, _sqrt),
    "Floor": (np.floor, dr.floor), "Ceil": (np.ceil, dr.ceil), "Exp": (np.exp, dr.exp),
    "Log": (np.log, dr.log),
    "Sigmoid": (_same_dtype(lambda x: 1 / (1 + np.exp(-x))), lambda x: dr.rcp(1.0 + dr.exp(-x))),
    "Tanh": (np.tanh, dr.tanh), "Neg": (np.negative, operator.neg), "Abs": (np.abs, dr.abs),
    "Reciprocal": (_same_dtype(lambda x: 1 / x), dr.rcp), "Sin": (np.sin, dr.sin), "Cos": (np.cos, dr.cos),
    "Not": (np.logical_not, operator.invert),
}
BINARY = {  # name: (on numpy constants, on drjit arrays or a drjit array and a Python scalar)
    "Add": (np.add, operator.add), "Sub": (np.subtract, operator.sub), "Mul": (np.multiply, _product),
    "Pow": (lambda a, b: np.power(a, b).astype(a.dtype), dr.power),  # the base's type, as ONNX's
    "Max": (np.maximum, dr.maximum), "Min": (np.minimum, dr.minimum),
    "Sum": (np.add, operator.add), "Greater": (np.greater, operator.gt), "Less": (np.less, operator.lt),
    "GreaterOrEqual": (np.greater_equal, operator.ge), "LessOrEqual": (np.less_equal, operator.le),
    "Equal": (np.equal, operator.eq), "And": (np.logical_and, operator.and_),
    "Or": (np.logical_or, operator.or_),
}
OPERATORS = sorted({*UNARY, *BINARY, "Div", "Clip", "Where", "Cast", "Identity", "Constant", "MatMul",
                    "Gemm", "Gather", "Shape", "Reshape", "Flatten", "Transpose", "Concat", "Slice", "Tile",
                    "Unsqueeze", "Squeeze"})
"""The operators (ONNX's default domain) the kernel evaluates."""
CASTS = {TensorProto.FLOAT: "Float", TensorProto.INT32: "Int32", TensorProto.INT64: "Int32",
         TensorProto.BOOL: "Bool"}
"""The types a computed tensor can be cast to: the drjit array type that holds it."""


def _fma(x, w: float, acc):
    """acc + x w, one rounding (x alone where w is 1 and nothing came before)."""
    if acc is None:
        return x if w == 1.0 else x * w
    return acc + x if w == 1.0 else dr.fma(x, w, acc)


def _fold(xs, fn):
    out = xs[0]
    for x in xs[1:]:
        out = fn(out, x)
    return out


def _slice(start: int, end: int, step: int, n: int) -> slice:
    """ONNX Slice's range of an axis of length `n` as a Python slice: ONNX clamps as
    `slice.indices` does, and a negative step's end before the first element (-1 there) is
    ``None`` (-1 in a slice is the last element)."""
    start, end, step = slice(start, end, step).indices(n)
    return slice(start, end if end >= 0 else None, step)


def _int_divide(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """ONNX integer Div (truncation); shape arithmetic with batch sizes (`Dim`, positive) floors."""
    if a.dtype == object or b.dtype == object:
        return elementwise(lambda x, y: x // y, a, b)
    q = np.floor_divide(a, b)
    return q + ((q < 0) & (q * b != a))


def _is(d, value: int) -> bool:
    """Whether shape entry `d` (an int or a `Dim`) is the int `value`."""
    return not isinstance(d, Dim) and d == value


def _size(dims) -> int:
    """The product of int shape entries (1 for none)."""
    return int(np.prod([int(d) for d in dims], dtype=np.int64))


def _prod(dims) -> object:
    out = 1
    for d in dims:
        out = d * out if isinstance(d, Dim) else out * int(d)
    return out


def _concat_shapes(xs, axis: int) -> np.ndarray:
    """Concat of constants, shape vectors holding `Dim` included."""
    arrays = [np.asarray(x) for x in xs]
    if any(a.dtype == object for a in arrays):
        return np.concatenate([a.astype(object) for a in arrays], axis=axis)
    return np.concatenate(arrays, axis=axis)
