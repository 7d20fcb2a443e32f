"""Server settings: read once from ``NEUMIP_*`` environment variables (pydantic-settings).

Every field below is an environment variable with the ``NEUMIP_`` prefix, e.g.
``NEUMIP_MODEL_DIR=models NEUMIP_MAX_WAIT_MS=2 neumip serve``. The field docstrings are the
documentation (``neumip serve --help`` prints them too).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from neumip.core.wire import ROW_BYTES  # a single query's bytes: the most a row of answers reads from shared memory


ANSWER_BYTES = 12
"""Bytes of memory one answer (3 float32) holds until it is sent, whatever the format: msgpack and
binary answers are sent from the evaluated array itself, JSON is encoded from it piece by piece."""
JSON_MEMORY_FACTOR = 16
"""Bytes of memory one byte of a JSON body may become while parsed: ``json.loads`` of the densest query
JSON (``[0,0,0,0,0,0,0]`` rows), then numpy, peaked at 13.5x the body's length (tracemalloc)."""


def available_cores() -> int:
    """CPU cores this process may run on (affinity-aware where the OS tells)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        return os.cpu_count() or 1


class Settings(BaseSettings):
    """Configuration of the inference server (environment variables with the ``NEUMIP_`` prefix)."""

    model_config = SettingsConfigDict(env_prefix="NEUMIP_", frozen=True, use_attribute_docstrings=True)

    model_dir: Path = Path("models")
    """Folder whose ``*.onnx`` files are served; material name = file stem."""
    host: str = "127.0.0.1"
    """Address `neumip serve` binds to (loopback by default)."""
    port: int = Field(8000, ge=0, le=65535)
    """TCP port `neumip serve` listens on."""
    log_level: str = "info"
    """Log level of the server and uvicorn (debug, info, warning, error)."""
    access_log: bool = False
    """Log every request at INFO (method, path, status); off: only 4xx and 5xx answers are logged (with
    their message). /metrics counts every request either way."""

    engine: Literal["auto", "onnxruntime", "kernel"] = "auto"
    """What evaluates the materials: kernel (the file's graph as drjit LLVM kernels, the renderer's in-process
    engine: one call at a time over every core; needs pip install 'neumip[kernel]' and a libLLVM >= 16),
    onnxruntime (the file's graph in ONNX Runtime sessions), or auto: kernel where it can run, else onnxruntime
    (the faster through the server by several times: server/README.md, Engines)."""
    ort_workers: int = Field(0, ge=0)
    """Concurrent ONNX Runtime calls (threads of the dedicated executor); 0 = one per core."""
    ort_threads: int = Field(1, ge=0)
    """Intra-op threads of each ONNX Runtime call (keep workers x threads <= cores); 0 = all cores."""
    chunk_rows: int = Field(8192, ge=1)
    """Most answers in one ONNX Runtime call (chunk_rows // K groups of K lights): large requests are
    split, small ones merged."""
    kernel_chunk_rows: int = Field(262144, ge=1)
    """Most answers in one call of the kernel engine (NEUMIP_ENGINE=kernel)."""
    max_wait_ms: float = Field(2.0, ge=0)
    """How long a batch that is not yet full waits for more rows while other requests are being decoded."""
    max_rows: int = Field(2_000_000, ge=1)
    """Most queries one request may carry, a query group of K lights counting K (more is rejected with
    413): it bounds the work and the answer's memory whatever the width."""
    max_queue_rows: int = Field(8_000_000, ge=1)
    """Most queries (a group of K lights counting K) admitted and not yet answered; beyond it requests
    get 503 with Retry-After."""
    max_body_bytes: int = Field(128 * 1024 * 1024, ge=1024)
    """Largest request body accepted, in bytes (more is rejected with 413)."""
    max_json_body_bytes: int = Field(16 * 1024 * 1024, ge=1024)
    """Largest JSON body (or v2 JSON header) accepted, in bytes (more: 413; large requests go as msgpack/binary)."""
    body_budget_bytes: int = Field(512 * 1024 * 1024, ge=1024)
    """Most request-body memory the requests in flight may reserve (JSON counts 16x); beyond it: 503."""
    answer_budget_bytes: int = Field(256 * 1024 * 1024, ge=1024)
    """Most answer memory the requests in flight may reserve (12 bytes an answer), from before their rows
    are evaluated until the answer is sent; beyond it: 503."""
    write_timeout_s: float = Field(30.0, gt=0)
    """Seconds an answer may wait for a client that does not read it (the connection's send buffer stays
    full); then the connection is dropped and the answer freed."""
    body_timeout_s: float = Field(60.0, gt=0)
    """Seconds a request body may take to arrive once its headers are in (slower: 408, connection closed)."""
    header_timeout_s: float = Field(10.0, gt=0)
    """Seconds a request line and headers may take to arrive (slower: 408, connection closed)."""
    max_header_bytes: int = Field(64 * 1024, ge=1024)
    """Largest request line plus headers, in bytes (more: 431, connection closed)."""
    keep_alive_s: int = Field(5, ge=1)
    """Seconds an idle kept-alive connection stays open."""
    retry_after_s: int = Field(1, ge=0)
    """Seconds a 503 (queue full) tells the client to wait, in its Retry-After header."""
    load: Literal["eager", "lazy"] = "eager"
    """eager: load every model at start-up; lazy: list the folder at start-up, load a model on its first request."""
    memory_budget_mb: float = Field(0.0, ge=0)
    """Most MB of loaded models (file sizes); past it the least recently used idle ones unload (0: no limit)."""
    poll_s: float = Field(2.0, ge=0)
    """Seconds between listings of the model folder (new, changed, deleted files); 0: only on request."""
    warmup_rows: int = Field(1024, ge=0)
    """Rows each material evaluates at start-up, before the server reports ready: as single queries and as
    query groups of two and three lights, the shapes a renderer sends (the kernel engine compiles each once)."""
    model_control: Literal["none", "explicit"] = "none"
    """none: ``POST /v2/repository/models/{name}/load`` and ``/unload`` answer 403; explicit: they load and
    unload models (Triton's ``--model-control-mode``)."""
    model_control_token: SecretStr | None = None
    """With model_control=explicit: load and unload need ``Authorization: Bearer <token>`` (unset: none)."""
    allow_shared_memory: bool = False
    """Clients on this machine may register shared-memory regions and pass queries and answers through them
    instead of the bodies (Triton's system shared-memory extension, its ``--allow-client-shm``;
    `server.shared_memory`). Off: such a client makes the server read, and write into, any shared-memory
    object the server's user can open."""
    graceful_shutdown_s: float = Field(10.0, ge=0)
    """Seconds uvicorn lets running requests finish after SIGTERM."""

    @model_validator(mode="after")
    def _consistent(self) -> "Settings":
        if self.max_queue_rows < self.max_rows:
            raise ValueError(
                f"max_queue_rows ({self.max_queue_rows}) must be >= max_rows ({self.max_rows}):"
                " otherwise the largest allowed request could never be admitted"
            )
        # a v2 body: both parts; with shared memory, its queries read from a region take memory as a body's do
        rows_bytes = max(self.max_body_bytes, ROW_BYTES * self.max_rows if self.allow_shared_memory else 0)
        largest = rows_bytes + JSON_MEMORY_FACTOR * self.max_json_body_bytes
        if self.body_budget_bytes < largest:
            raise ValueError(
                f"body_budget_bytes ({self.body_budget_bytes}) must be >= max(max_body_bytes ({self.max_body_bytes})"
                f"{f', {ROW_BYTES} x max_rows ({self.max_rows}) with shared memory' if self.allow_shared_memory else ''}"
                f") + {JSON_MEMORY_FACTOR} x max_json_body_bytes ({self.max_json_body_bytes}): otherwise the largest "
                "allowed request could never be admitted"
            )
        if self.answer_budget_bytes < ANSWER_BYTES * self.max_rows:
            raise ValueError(
                f"answer_budget_bytes ({self.answer_budget_bytes}) must be >= {ANSWER_BYTES} x max_rows "
                f"({self.max_rows}): otherwise the largest allowed answer could never be reserved"
            )
        return self

    @classmethod
    def describe(cls) -> str:
        """One line per setting: environment variable, default, and what it does."""
        lines = []
        for name, field in cls.model_fields.items():
            lines.append(f"NEUMIP_{name.upper():22s} {str(field.default):12s} {field.description}")
        return "\n".join(lines)

    def workers(self) -> int:
        """Threads of the ONNX Runtime executor."""
        return self.ort_workers or available_cores()
