"""A material as a Triton model: the one `ModelConfig` that both `GET /v2/models/{name}/config` answers
and `neumip export-repository` writes as ``config.pbtxt``.

`model_config` builds the config as a dict in protobuf's JSON form with Triton's field names
(``model_config.proto``: ``max_batch_size``, ``input``, ``dynamic_batching``, ...). `to_pbtxt` writes the
same dict in protobuf text format. Enum values are `ProtoEnum` strings (written unquoted in text format).
No protobuf or Triton package is needed; the tests parse both forms against Triton's real schema.
"""

from __future__ import annotations

from dataclasses import dataclass

from neumip.core import contract as C

from neumip.server.engine import ONNX_PLATFORM
from neumip.server.registry import MODEL_VERSION

BACKENDS = ("onnxruntime", "python")
"""Triton backends a material can be served by: ONNX Runtime itself, or the python backend running a
``model.py`` that calls ONNX Runtime (`neumip.server.triton_python_model`)."""


class ProtoEnum(str):
    """A protobuf enum value (``TYPE_FP32``): a string in JSON, a bare word in text format."""


@dataclass(frozen=True)
class TritonOptions:
    """How a material is batched and run, in Triton's terms."""

    max_batch_size: int
    """Most rows one request may carry (Triton refuses larger requests; it never splits them)."""
    preferred_batch_size: int
    """Rows the dynamic batcher aims for in one model call (merging small requests)."""
    max_queue_delay_us: int
    """How long a call that is not full waits for more requests, in microseconds."""
    instances: int = 1
    """Model instances (concurrent ONNX Runtime sessions) on the CPU."""
    intra_op_threads: int = 0
    """ONNX Runtime intra-op threads per instance; 0 = ONNX Runtime's default (one per physical core)."""
    backend: str = "onnxruntime"
    """Triton backend: "onnxruntime" (platform onnxruntime_onnx) or "python" (model.py + ONNX Runtime)."""

    def __post_init__(self) -> None:
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {', '.join(BACKENDS)}, got {self.backend!r}")
        if self.max_batch_size < 1 or self.preferred_batch_size < 1 or self.instances < 1:
            raise ValueError("max_batch_size, preferred_batch_size and instances must be >= 1")
        if self.intra_op_threads < 0 or self.max_queue_delay_us < 0:
            raise ValueError("intra_op_threads and max_queue_delay_us must be >= 0")

    @classmethod
    def from_settings(cls, settings, **overrides) -> "TritonOptions":
        """The server's batching settings (`neumip.server.settings.Settings`) in Triton's terms."""
        values = {
            "max_batch_size": settings.max_rows,
            "preferred_batch_size": min(settings.chunk_rows, settings.max_rows),
            "max_queue_delay_us": round(settings.max_wait_ms * 1000),
            "instances": settings.workers(),
            "intra_op_threads": settings.ort_threads,
        }
        return cls(**{**values, **overrides})


VARIABLE = -1
"""Triton's dimension of variable size."""


def tensor(name: str, dim: int) -> dict:
    """A batched FP32 tensor of `dim` values per row, -1 for a variable count (Triton adds the batch
    dimension)."""
    return {"name": name, "data_type": ProtoEnum("TYPE_FP32"), "dims": [dim]}


def model_config(name: str, options: TritonOptions) -> dict:
    """Triton's ModelConfig of material `name`: (N, 5 + 2 K) FP32 query groups -> (N, 3 K) FP32 rgb,
    both widths variable (Triton batches only requests of the same width together)."""
    config = {"name": name}
    if options.backend == "onnxruntime":
        config |= {"platform": ONNX_PLATFORM, "backend": "onnxruntime"}
    else:
        config["backend"] = "python"
    threads = str(options.intra_op_threads)
    return config | {
        "version_policy": {"specific": {"versions": [int(MODEL_VERSION)]}},
        "max_batch_size": options.max_batch_size,
        "input": [tensor(C.ONNX_INPUT, VARIABLE)],
        "output": [tensor(C.ONNX_OUTPUT, VARIABLE)],
        "dynamic_batching": {
            "preferred_batch_size": [options.preferred_batch_size],
            "max_queue_delay_microseconds": options.max_queue_delay_us,
        },
        "instance_group": [{"count": options.instances, "kind": ProtoEnum("KIND_CPU")}],
        # onnxruntime backend parameters (the python backend's model.py reads the same ones)
        "parameters": {
            "intra_op_thread_count": {"string_value": threads},
            "inter_op_thread_count": {"string_value": "1"},
        },
    }


# --- protobuf text format ---------------------------------------------------------------------
MAP_FIELDS = frozenset({"parameters"})
"""ModelConfig fields that are protobuf maps (``map<string, ModelParameter>``)."""


def _scalar(value) -> str:
    if isinstance(value, ProtoEnum):
        return str(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, int):
        return str(value)
    raise TypeError(f"no text format for {type(value).__name__} {value!r}")


def _fields(message: dict, indent: str) -> list[str]:
    lines = []
    for key, value in message.items():
        if key in MAP_FIELDS:
            for k, v in value.items():
                lines += [f"{indent}{key} {{", f'{indent}  key: {_scalar(k)}', f"{indent}  value {{",
                          *_fields(v, indent + "    "), f"{indent}  }}", f"{indent}}}"]
        elif isinstance(value, dict):
            lines += [f"{indent}{key} {{", *_fields(value, indent + "  "), f"{indent}}}"]
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            lines.append(f"{indent}{key} [")
            for i, item in enumerate(value):
                lines += [f"{indent}  {{", *_fields(item, indent + "    "),
                          f"{indent}  }}" + ("," if i < len(value) - 1 else "")]
            lines.append(f"{indent}]")
        elif isinstance(value, list):
            lines.append(f"{indent}{key}: [ {', '.join(_scalar(v) for v in value)} ]")
        else:
            lines.append(f"{indent}{key}: {_scalar(value)}")
    return lines


def to_pbtxt(config: dict) -> str:
    """A `model_config` dict in protobuf text format (Triton's ``config.pbtxt``)."""
    return "\n".join(_fields(config, "")) + "\n"
