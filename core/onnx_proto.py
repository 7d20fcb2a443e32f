"""The parts of an ONNX file neumip reads - metadata and initializers - from its protobuf bytes.

The base install (numpy, ONNX Runtime) has no ``onnx`` package, and ONNX Runtime does not give a
graph's initializers back, so `neumip.core.modelfile` reads the file's protobuf wire format itself:
the few fields below (`onnx.proto`), nothing else. Every other field is skipped unread.

Raises `ProtoError` (a ValueError) on bytes that are not well-formed protobuf; the reader turns it
into its one `ModelError`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Field numbers of onnx.proto (ModelProto, StringStringEntryProto, GraphProto, TensorProto).
MODEL_GRAPH, MODEL_METADATA = 7, 14
ENTRY_KEY, ENTRY_VALUE = 1, 2
GRAPH_INITIALIZER = 5
TENSOR_DIMS, TENSOR_TYPE, TENSOR_FLOAT, TENSOR_INT32, TENSOR_INT64 = 1, 2, 4, 5, 7
TENSOR_NAME, TENSOR_RAW, TENSOR_DOUBLE, TENSOR_UINT64, TENSOR_LOCATION = 8, 9, 10, 11, 14

DTYPES = {1: "<f4", 2: "u1", 3: "i1", 4: "<u2", 5: "<i2", 6: "<i4", 7: "<i8", 9: "?", 10: "<f2", 11: "<f8",
          12: "<u4", 13: "<u8"}
"""TensorProto.DataType -> numpy dtype, for the types read (FLOAT ... UINT64 but STRING)."""

TYPED_FIELD = {1: TENSOR_FLOAT, 11: TENSOR_DOUBLE, 7: TENSOR_INT64, 12: TENSOR_UINT64, 13: TENSOR_UINT64}
"""Where a tensor of each type keeps its values when not in ``raw_data`` (the others: ``int32_data``)."""


class ProtoError(ValueError):
    """Bytes that are not a well-formed protobuf message (truncated, corrupt, not ONNX)."""


@dataclass(frozen=True)
class Tensor:
    """One initializer as stored: its values still encoded."""

    name: str
    data_type: int
    """TensorProto.DataType (1: FLOAT)."""
    dims: tuple[int, ...]
    parts: tuple[tuple[int, int, memoryview], ...]
    """(field number, wire type, value) of each field holding values."""
    external: bool = False
    """Whether its values are stored outside the file (ONNX external data)."""

    def array(self) -> np.ndarray:
        """The values as numpy, shaped ``dims`` (a read-only view of the file's bytes where they are
        raw data); ProtoError for a type neumip does not read (strings, bfloat16, float8...)."""
        if self.external:
            raise ProtoError(f"initializer {self.name!r} is stored outside the file (ONNX external data)")
        dtype = DTYPES.get(self.data_type)
        if dtype is None:
            raise ProtoError(f"initializer {self.name!r} is of ONNX data type {self.data_type}, which neumip does not read")
        raw = [value for number, _, value in self.parts if number == TENSOR_RAW]
        if raw:
            values = np.frombuffer(raw[-1], np.dtype(dtype))
        else:
            values = self._typed(np.dtype(dtype))
        count = int(np.prod(self.dims, dtype=np.int64))
        if values.size != count:
            raise ProtoError(f"initializer {self.name!r} holds {values.size} values for dims {list(self.dims)}")
        return values.reshape(self.dims)

    def _typed(self, dtype: np.dtype) -> np.ndarray:
        """Values kept in the typed field of the tensor's type (packed, or one field a value)."""
        field = TYPED_FIELD.get(self.data_type, TENSOR_INT32)
        chunks = [value for number, _, value in self.parts if number == field]
        if field in (TENSOR_FLOAT, TENSOR_DOUBLE):  # fixed-width little-endian
            width = "<f4" if field == TENSOR_FLOAT else "<f8"
            flat = [np.frombuffer(c, width) for c in chunks if isinstance(c, memoryview)]
            return np.concatenate(flat).astype(dtype) if flat else np.zeros(0, dtype)
        ints = [v for c in chunks for v in (packed_varints(c) if isinstance(c, memoryview) else [c])]
        if field == TENSOR_UINT64:
            return np.asarray(ints, np.uint64).astype(dtype)
        signed = np.asarray([v - (1 << 64) if v >= 1 << 63 else v for v in ints], np.int64)
        if self.data_type == 10:  # float16: int32_data holds the bits
            return signed.astype(np.uint16).view(np.float16).astype(dtype)
        return signed.astype(dtype)


def varint(buf: memoryview, i: int) -> tuple[int, int]:
    """The varint at ``buf[i]`` -> (value, index after it)."""
    value = shift = 0
    while True:
        if i >= len(buf) or shift > 63:
            raise ProtoError("a varint runs past the end of the data")
        byte = buf[i]
        value |= (byte & 0x7F) << shift
        i, shift = i + 1, shift + 7
        if byte < 0x80:
            return value, i


def packed_varints(buf: memoryview) -> list[int]:
    values, i = [], 0
    while i < len(buf):
        value, i = varint(buf, i)
        values.append(value)
    return values


def fields(buf: memoryview):
    """The (field number, wire type, value) of each field of a message: an int for a varint, a
    memoryview of the bytes otherwise."""
    i = 0
    while i < len(buf):
        key, i = varint(buf, i)
        number, kind = key >> 3, key & 7
        if number == 0:
            raise ProtoError("field number 0")
        if kind == 0:
            value, i = varint(buf, i)
        elif kind in (1, 2, 5):
            if kind == 2:
                size, i = varint(buf, i)
            else:
                size = 8 if kind == 1 else 4
            if i + size > len(buf):
                raise ProtoError("a field runs past the end of the data (a truncated file?)")
            value, i = buf[i:i + size], i + size
        else:
            raise ProtoError(f"unsupported protobuf wire type {kind}")
        yield number, kind, value


def _text(value) -> str:
    if not isinstance(value, memoryview):
        raise ProtoError("a string field holds a number")
    return bytes(value).decode("utf-8", "replace")


def read_model(data: bytes) -> tuple[dict[str, str], list[Tensor]]:
    """An ONNX file's bytes -> (its metadata, its graph's initializers). ProtoError if they are not
    a well-formed ONNX ModelProto with a graph."""
    metadata: dict[str, str] = {}
    graph = None
    for number, kind, value in fields(memoryview(data)):
        if number == MODEL_METADATA and kind == 2:
            entry = {n: _text(v) for n, _, v in fields(value) if n in (ENTRY_KEY, ENTRY_VALUE)}
            metadata[entry.get(ENTRY_KEY, "")] = entry.get(ENTRY_VALUE, "")
        elif number == MODEL_GRAPH and kind == 2:
            graph = value
    if graph is None:
        raise ProtoError("no graph")
    tensors = [_tensor(value) for number, kind, value in fields(graph) if number == GRAPH_INITIALIZER and kind == 2]
    return metadata, tensors


def _tensor(buf: memoryview) -> Tensor:
    name, data_type, dims, parts, external = "", 0, [], [], False
    for number, kind, value in fields(buf):
        if number == TENSOR_NAME:
            name = _text(value)
        elif number == TENSOR_TYPE and kind == 0:
            data_type = value
        elif number == TENSOR_DIMS:
            dims += packed_varints(value) if kind == 2 else [value]
        elif number == TENSOR_LOCATION and kind == 0:
            external = value == 1
        elif number in (TENSOR_FLOAT, TENSOR_INT32, TENSOR_INT64, TENSOR_RAW, TENSOR_DOUBLE, TENSOR_UINT64):
            parts.append((number, kind, value))
    dims = [d - (1 << 64) if d >= 1 << 63 else d for d in dims]
    if any(d < 0 for d in dims):
        raise ProtoError(f"initializer {name!r} has a negative dimension")
    return Tensor(name, data_type, tuple(dims), tuple(parts), external)
