"""A model folder: the ``NAME.onnx`` files every evaluator of a folder serves, listed and loaded one way.

`LocalMaterials` (ONNX Runtime), `KernelMaterials` (the in-kernel engine) and the server's registry
(`neumip.server.registry`, which adds polling, swaps, a memory budget and warm-up) all build on it:

- `list_models`: the folder's ``*.onnx`` files; a file whose stem is not a material name
  (`NAME_PATTERN`) is listed as failed (`BAD_NAME`), never loaded;
- `read_model_bytes`: a file's bytes, refused (ModelError) if unreadable or changed while read;
- a loader ``load(path, data) -> material`` (an engine's: `local.load_material`,
  `kernel.KernelMaterial`) reads the bytes through the one model-file reader
  (`neumip.core.modelfile.read_model_file`) and raises its `ModelError` for a file it cannot serve;
- `ModelFolder`: every file loaded at once, or each on its first use.
"""

from __future__ import annotations

import logging
import os
import re
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Generic, TypeVar

from neumip.core.errors import NeumipError
from neumip.core.modelfile import ModelError

log = logging.getLogger(__name__)

T = TypeVar("T")

Loader = Callable[[Path, bytes], T]
"""A model file's path and bytes -> the loaded material; raises ModelError for a file it cannot serve."""

NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,127}$")
"""What a material name may look like (also guards paths built from names)."""

BAD_NAME = "file name is not a valid material name"
"""Why a file whose stem is not a material name is not served."""


class UnknownMaterial(NeumipError, KeyError):
    """A material name that is not loaded."""

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass(frozen=True)
class FileStamp:
    """What says a model file changed: modification time, size, inode."""

    mtime_ns: int
    size: int
    inode: int

    @classmethod
    def of(cls, path: Path) -> FileStamp | None:
        try:
            st = path.stat()
        except FileNotFoundError:
            return None
        return cls(st.st_mtime_ns, st.st_size, st.st_ino)


def model_folders(spec: str | Path) -> list[Path]:
    """A model folder, or several joined by `os.pathsep` as in PATH (``mine:models``) -> the folders, in order."""
    return [Path(part) for part in str(spec).split(os.pathsep) if part]


def list_models(folder: str | Path) -> tuple[dict[str, Path], set[str]]:
    """The ``*.onnx`` files of `folder` (or of several folders, `model_folders`: the first that holds a name
    serves it) -> ({name: path} of those named as materials, the stems of the others)."""
    named, bad = {}, set()
    for one in model_folders(folder):
        for path in sorted(one.glob("*.onnx")):
            if NAME_PATTERN.match(path.stem):
                named.setdefault(path.stem, path)
            elif path.stem not in named:
                bad.add(path.stem)
    return named, bad


def read_model_bytes(path: Path, stamp: FileStamp | None = None) -> bytes:
    """The bytes of the model file at `path`; ModelError if it cannot be read or, given the `stamp` it
    was listed with, changed while it was read (a file still being copied is not loaded half-way)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ModelError(f"{path.name}: cannot read: {exc.strerror or exc}") from exc
    if stamp is not None and (FileStamp.of(path) != stamp or len(data) != stamp.size):
        raise ModelError(f"{path.name} changed while it was read (still being written?)")
    return data


def load_model(path: Path, load: Loader[T]) -> T:
    """`load` the model file at `path` from its bytes; raises ModelError."""
    return load(path, read_model_bytes(path))


def open_folder(folder: str | Path, load: Loader[T]) -> tuple[dict[str, T], dict[str, str]]:
    """``load`` every ``*.onnx`` in `folder` (or folders, `model_folders`) -> (loaded by name, {name: reason} of
    files that failed).

    A file fails when it cannot be loaded (ModelError: unreadable, corrupt, another contract version,
    non-finite weights, a graph the engine cannot run) or when its stem is not a material name
    (`NAME_PATTERN`); failures are logged, the others still load.
    """
    named, bad = list_models(folder)
    loaded: dict[str, T] = {}
    failed: dict[str, str] = dict.fromkeys(bad, BAD_NAME)
    for name, path in named.items():
        try:
            loaded[name] = load_model(path, load)
        except ModelError as exc:
            failed[name] = str(exc)
    for name in sorted(failed):
        log.error("skipping %s.onnx: %s", name, failed[name])
    return loaded, failed


class ModelFolder(Generic[T]):
    """The materials of a model folder (``NAME.onnx``), each opened once by ``load(path, data)``: every
    file at once (those that fail are logged and listed in `errors`), or with ``lazy=True`` each on its
    first `get` (a file that fails then raises ModelError there, and is listed in `errors`). Shared by
    the evaluators of a folder (`LocalMaterials`, the renderer's `KernelMaterials`)."""

    def __init__(self, folder: str | Path, load: Loader[T], lazy: bool = False) -> None:
        folders = model_folders(folder)
        for one in folders or [Path(folder)]:
            if not one.is_dir():
                raise FileNotFoundError(f"model folder {one} does not exist")
        self.folder = folders[0]  # (several: `model_folders`; messages name the first)
        self._spec = os.pathsep.join(map(str, folders))
        self._load = load
        self._lock = threading.Lock()
        self._paths = list_models(self._spec)[0]
        if lazy:
            self._loaded, self.errors = {}, {}
            self._listed = sorted(self._paths)
        else:
            self._loaded, self.errors = open_folder(self._spec, load)
            self._listed = sorted(self._loaded)

    def names(self) -> list[str]:
        """Names served: loaded ones (lazy: every listed file that has not failed)."""
        return sorted(set(self._listed) - set(self.errors))

    def loaded(self) -> list[str]:
        """Names of the materials loaded so far."""
        return sorted(self._loaded)

    def get(self, name: str) -> T:
        """Material `name`, loaded on first use; raises UnknownMaterial or ModelError."""
        material = self._loaded.get(name)
        if material is not None:
            return material
        if name not in self.names():
            known = ", ".join(self.names()) or "none"
            raise UnknownMaterial(f"unknown material {name!r} (served: {known})")
        with self._lock:  # lazy: load once, whichever thread asks first
            if name not in self._loaded:
                try:
                    self._loaded[name] = load_model(self._paths[name], self._load)
                except ModelError as exc:
                    self.errors[name] = str(exc)
                    raise
                log.info("loaded %s on first use (as %s)", name, type(self._loaded[name]).__name__)
            return self._loaded[name]
