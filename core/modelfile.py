"""The one reader of a model file: what an ``.onnx`` material declares, checked once for every user.

Every engine (ONNX Runtime, the in-kernel engine, the server's), the export's readers (`neumip export`,
`neumip trim`), `neumip budget` and the report read a model file through `read_model_file`. It gives a
`ModelFile`: the metadata, the `MaterialConfig` (None for a graph made by another tool, which the
contract allows), the trim record, the validation record, the sampling lobe, and on request the
initializers as numpy arrays. Anything wrong with the file is one `ModelError` naming it:

- unreadable, or not an ONNX file (truncated, corrupt);
- another contract version (`contract.version_problem`, naming the upgrade) or a malformed sampling
  lobe (`contract.engine_problem`);
- metadata that is not valid JSON or not a valid config or trim record;
- a non-finite weight (NaN or Inf in any float initializer), naming the tensors;
- no neumip metadata where a command needs it (`ModelFile.require_config`).

The file is read from its protobuf bytes (`onnx_proto`): the base install has no ``onnx`` package.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.core.config import MaterialConfig
from neumip.core.errors import NeumipError
from neumip.core.onnx_proto import read_model

FLOAT_TYPES = (1, 10, 11)
"""ONNX data types whose initializers are checked for non-finite values (FLOAT, FLOAT16, DOUBLE)."""


class ModelError(NeumipError, ValueError):
    """A model file that cannot be used: unreadable, corrupt, bad metadata, another contract version,
    a non-finite weight, or no neumip metadata where it is needed. The message names the file."""


@dataclass
class TrimRecord:
    """What `neumip trim` cut from a model (its ``neumip.trim`` metadata, JSON)."""

    finest_level: int
    """Finest pyramid level the model still holds; finer queries read it."""
    finest_resolution: int
    """Texels per side of that level."""
    levels_cut: list[int]
    """Sizes (texels per side) of the levels cut, finest first."""
    texels_cut: int
    """Pyramid texels cut (each ``channels`` float32)."""
    bytes_before: int
    """Size of the serialized model before trimming (this and every earlier trim)."""
    offset: str = "kept"
    """The neural offset texture: kept whole (bit-identity above the cut needs it)."""

    def to_json(self) -> str:
        return json.dumps(asdict(self))


@dataclass(frozen=True)
class ModelFile:
    """What one model file declares (`read_model_file`)."""

    name: str
    """The file's name (``rock.onnx``), as messages give it."""
    size: int
    """Bytes of the file."""
    metadata: dict[str, str]
    """The ONNX metadata, as stored (a graph made by another tool may have none)."""
    config: MaterialConfig | None
    """The material's architecture (`META_CONFIG`); None for a graph without neumip metadata."""
    trim: TrimRecord | None
    """What `neumip trim` cut (`META_TRIM`); None: never trimmed."""
    validation: dict | None
    """The per-level validation error of a trained material (`META_VALIDATION`)."""
    sampling: C.SamplingLobe | None
    """The sampling lobe the model declares (`contract.SamplingLobe`; None: the cosine alone)."""
    version_problem: str | None = None
    """Why this build cannot serve the file's contract version (None: it can, or it declares none);
    only a file read with ``any_version`` has one."""
    initializers: dict[str, np.ndarray] | None = None
    """The graph's initializers by name (read-only views of the file's bytes); only read on request."""

    @property
    def description(self) -> str:
        return self.metadata.get(C.META_DESCRIPTION, "")

    @property
    def finest_level(self) -> int:
        """Finest pyramid level the model holds: 0 unless trimmed."""
        return self.trim.finest_level if self.trim else 0

    def require_config(self, needed: str) -> MaterialConfig:
        """The config, or a one-line ModelError saying that `needed` (what reads it) cannot work without."""
        if self.config is not None:
            return self.config
        what = ("no neumip metadata (a foreign graph)" if C.META_CONTRACT not in self.metadata
                else f"no {C.META_CONFIG} in its metadata")
        raise ModelError(f"{self.name} has {what}: {needed}")

    def config_dict(self) -> dict:
        """The config as the file stores it, a dict ({} for a graph without neumip metadata)."""
        return json.loads(self.config.to_json()) if self.config is not None else {}


def read_model_file(path: str | Path, data: bytes | None = None, *, any_version: bool = False,
                    initializers: bool = False) -> ModelFile:
    """Read and check the model file at `path` (from `data`, its bytes already read, if given); raises
    ModelError (see the module). `any_version`: accept another contract version, saying why in
    `ModelFile.version_problem` (`neumip export` reads the files it upgrades so). `initializers`: keep
    the graph's initializers (`ModelFile.initializers`)."""
    path = Path(path)
    name = path.name
    try:
        data = path.read_bytes() if data is None else data
    except OSError as exc:
        raise ModelError(f"{name}: cannot read: {exc.strerror or exc}") from exc
    try:
        metadata, tensors = read_model(data)
    except (ValueError, IndexError) as exc:
        raise ModelError(f"{name}: cannot load ONNX model: not an ONNX file ({exc})") from exc
    problem = C.version_problem(metadata, str(path)) if C.META_CONTRACT in metadata else None
    if problem and not any_version:
        raise ModelError(f"{name}: {problem}")
    try:
        sampling = C.sampling_lobe(metadata)
    except C.SamplingLobeError as exc:
        raise ModelError(f"{name}: {exc}") from exc
    config = _parse(name, metadata, C.META_CONFIG, MaterialConfig.from_dict)
    trim = _parse(name, metadata, C.META_TRIM, lambda d: TrimRecord(**d))
    validation = _parse(name, metadata, C.META_VALIDATION, dict)
    try:
        arrays = {t.name: t.array() for t in tensors if initializers or t.data_type in FLOAT_TYPES}
    except ValueError as exc:
        raise ModelError(f"{name}: cannot load ONNX model: {exc}") from exc
    bad = sorted(n for n, a in arrays.items() if a.dtype.kind == "f" and not np.isfinite(a).all())
    if bad:
        raise ModelError(f"{name}: non-finite weights in {', '.join(bad)}")
    return ModelFile(name, len(data), metadata, config, trim, validation, sampling, problem,
                     arrays if initializers else None)


def _parse(name: str, metadata: dict[str, str], key: str, build):
    """``build(json.loads(metadata[key]))``, None without the key; ModelError for a bad value."""
    text = metadata.get(key)
    if not text:
        return None
    try:
        data = json.loads(text)
        if not isinstance(data, dict):
            raise TypeError("not a JSON object")
        return build(data)
    except (ValueError, TypeError, KeyError, RecursionError) as exc:
        raise ModelError(f"{name}: bad {key} metadata: {exc}") from exc
