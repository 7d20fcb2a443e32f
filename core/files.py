"""Writing a file atomically: readers see the old file or the whole new one, never a part.

`atomic_write` has the writer fill a temporary file in the same folder (so the rename never crosses
file systems) and renames it over the target (`os.replace`); on any exception, or an interrupt, the
temporary file is removed and the old file is left as it was. The temporary name is hidden and
unique per call (``.NAME.PID.RANDOM.partial``), so concurrent writers do not collide and a folder
listed by suffix (``*.onnx``) never shows one half-written. Every file of neumip that is written whole
(model files, checkpoints, data set records, images, cached renders) goes through it.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Callable
from pathlib import Path


def temporary_path(path: Path, keep_suffix: bool = False) -> Path:
    """A fresh hidden name beside `path` for its temporary file; with `keep_suffix` it ends in
    `path`'s suffix, for writers that choose the format by it (images)."""
    tail = f".partial{path.suffix}" if keep_suffix else ".partial"
    return path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}{tail}")


def atomic_write(path: str | os.PathLike, write: Callable[[Path], object], keep_suffix: bool = False) -> Path:
    """Call ``write(tmp)`` to write the whole file at a temporary path beside `path`, then rename it to
    `path`; on any exception the temporary file is removed and `path` is untouched. `keep_suffix`:
    the temporary name ends in `path`'s suffix. Returns `path`."""
    path = Path(path)
    tmp = temporary_path(path, keep_suffix)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)  # gone after the rename; left by a failed write
    return path


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """`Path.write_bytes`, atomically (`atomic_write`)."""
    return atomic_write(path, lambda tmp: tmp.write_bytes(data))


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """`Path.write_text` (UTF-8), atomically (`atomic_write`)."""
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))
