"""MBTF query data sets on disk: chunked, resumable writing and memory-mapped reading.

A data set is a folder::

    DATA/
      queries.npy     (N, 7) float32, the contract's query layout
      rgb.npy         (N, 3) float32, the MBTF value of each query
      meta.json       {"format", "n", "complete", "material", "generator", ...}
      progress.json   only while being written: chunks done so far

Why this format: ``.npy`` files are memory-mapped by numpy with no extra dependency (training draws
random batches straight from the page cache), readable by any tool, and can be pre-allocated at full
size and filled chunk by chunk in place. ``meta.json`` says ``"complete": true`` only after every
chunk is flushed, and it is written atomically, so an interrupted run is never mistaken for a whole
data set; re-running the same command resumes at the first unfinished chunk, and on a complete data
set made with the same settings does nothing.

External data (e.g. converted measured BTFs) enters through :func:`write_dataset`: any (N, 7)
queries in the contract's layout with their (N, 3) RGB.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from neumip.core import contract as C
from neumip.core.errors import NeumipError, differences
from neumip.core.files import write_text_atomic

FORMAT = "neumip-mbtf-1"

LOCATION_KEYS = ("description_dir",)
"""meta.json keys that say where the inputs were, not what the data are: a data set resumed or
remade from a moved description keeps its identity, and the keys take the newest values."""


class DatasetError(NeumipError, RuntimeError):
    """A data set folder that is missing, incomplete or inconsistent."""


FILES = ("meta.json", "progress.json", "queries.npy", "rgb.npy")
"""The files of a data set folder (the layout above)."""


def remove_dataset(path: str | Path) -> None:
    """Delete the data set files at `path` (a stale cache), leaving anything else in the folder."""
    for name in FILES:
        (Path(path) / name).unlink(missing_ok=True)


def _identity(meta: dict) -> dict:
    """What identifies a data set in its meta (JSON-normalised): all but completion and location."""
    return json.loads(json.dumps({k: v for k, v in meta.items() if k != "complete" and k not in LOCATION_KEYS}))


def _other_settings(saved: dict, asked: dict) -> str:
    """The settings in which a data set on disk differs from the one asked for, for an error message."""
    changed = differences(_identity(saved), _identity(asked), ("there", "asked"))
    return "; ".join(changed[:4]) + (f"; {len(changed) - 4} more" if len(changed) > 4 else "")


def _write_json(path: Path, data: dict) -> None:
    write_text_atomic(path, json.dumps(data, indent=2, sort_keys=True))


def read_meta(path: Path) -> dict:
    """A data set's JSON file (meta.json, progress.json); DatasetError naming it if it is not a JSON object."""
    try:
        data = json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path} is damaged ({exc}): remove the data set folder and generate it again") from None
    if not isinstance(data, dict):
        raise DatasetError(f"{path} is damaged (not a JSON object): remove the data set folder and generate it again")
    return data


def _check_npy(path: Path, shape: tuple[int, int]) -> None:
    """DatasetError naming `path` unless it is a little-endian float32 ``.npy`` file of `shape` and of the full length
    that shape needs (a truncated file would otherwise be grown with zeros when resumed, or fail to map)."""
    try:
        with path.open("rb") as f:
            version = np.lib.format.read_magic(f)
            if version not in ((1, 0), (2, 0), (3, 0)):
                raise ValueError(f"unknown .npy format version {version}")
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            stored, fortran, dtype = read_header(f)
            offset = f.tell()
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path} is damaged ({exc}): remove the data set folder and generate it again") from None
    if tuple(stored) != shape or fortran or dtype != C.DTYPE:
        raise DatasetError(f"{path} holds a {'Fortran-ordered ' if fortran else ''}{dtype} array of shape {tuple(stored)}, "
                           f"not {shape} little-endian float32: remove the data set folder and generate it again")
    expected = offset + int(np.prod(shape)) * C.DTYPE.itemsize
    if path.stat().st_size != expected:
        raise DatasetError(f"{path} is damaged: it holds {path.stat().st_size} bytes of the {expected} its header "
                           "says (a truncated copy?): remove the data set folder and generate it again")


def _check_arrays(folder: Path, n: int) -> None:
    """`_check_npy` of both arrays of a data set of `n` rows."""
    _check_npy(folder / "queries.npy", (n, C.QUERY_DIM))
    _check_npy(folder / "rgb.npy", (n, C.RGB_DIM))


@dataclass
class Dataset:
    """A complete data set, memory-mapped."""

    path: Path
    queries: np.ndarray  # (N, 7) float32, read-only memmap
    rgb: np.ndarray  # (N, 3) float32, read-only memmap
    meta: dict[str, Any]

    def __len__(self) -> int:
        return self.queries.shape[0]


def open_dataset(path: str | Path) -> Dataset:
    """Open a complete data set read-only. Raises DatasetError if it is incomplete or inconsistent."""
    path = Path(path)
    meta_path = path / "meta.json"
    if not meta_path.exists():
        if (path / "progress.json").exists():
            raise DatasetError(f"{path} is incomplete (interrupted run?): re-run the generator to resume")
        raise DatasetError(f"{path} is not a data set (no meta.json)")
    meta = read_meta(meta_path)
    if meta.get("format") != FORMAT:
        raise DatasetError(f"{path}: format {meta.get('format')!r}, expected {FORMAT!r}")
    if not meta.get("complete"):
        raise DatasetError(f"{path} is incomplete (interrupted run?): re-run the generator to resume")
    n = meta.get("n")
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise DatasetError(f"{meta_path} is damaged (n = {str(n)[:40]}): remove the data set folder and generate it again")
    _check_arrays(path, n)
    queries = np.load(path / "queries.npy", mmap_mode="r")
    rgb = np.load(path / "rgb.npy", mmap_mode="r")
    return Dataset(path, queries, rgb, meta)


class DatasetWriter:
    """Fill a data set of `n` rows chunk by chunk; resumable.

    ``meta`` must identify what is generated (material, settings, seed): resuming with different
    ``meta`` is refused rather than mixing two data sets. On a complete data set with the same
    ``meta`` there is nothing to write (`complete`), and `finalize` reopens it.
    """

    def __init__(self, path: str | Path, n: int, chunk: int, meta: dict[str, Any]) -> None:
        self.path = Path(path)
        self.n, self.chunk = n, chunk
        self.meta = {"format": FORMAT, "n": n, "chunk": chunk, **meta}
        self.path.mkdir(parents=True, exist_ok=True)
        self._progress = self.path / "progress.json"
        meta_path = self.path / "meta.json"
        saved = read_meta(meta_path) if meta_path.exists() else {}
        self.complete = bool(saved.get("complete"))
        if self.complete:  # the same data set again: nothing to write; another one: refused
            if _identity(saved) != _identity(self.meta):
                raise DatasetError(
                    f"{self.path} already holds a complete data set made with other settings "
                    f"({_other_settings(saved, self.meta)}); remove it or write to another folder"
                )
            if any(saved.get(k) != self.meta.get(k) for k in LOCATION_KEYS):  # its inputs moved
                _write_json(meta_path, {**self.meta, "complete": True})
            self.done = self.chunks
            return
        if self._progress.exists():
            state = read_meta(self._progress)
            if not isinstance(state.get("meta"), dict) or not isinstance(state.get("done"), int):
                raise DatasetError(f"{self._progress} is damaged: remove the data set folder and generate it again")
            if _identity(state["meta"]) != _identity(self.meta):
                raise DatasetError(
                    f"{self.path} holds a partial data set made with other settings "
                    f"({_other_settings(state['meta'], self.meta)}); remove it or use the same settings to resume"
                )
            self.done = int(state["done"])
            _check_arrays(self.path, n)  # before r+ would grow a truncated one
            mode = "r+"
        else:
            self.done = 0
            mode = "w+"
        open_mm = np.lib.format.open_memmap
        kw = {} if mode == "r+" else {"dtype": C.DTYPE}
        self.queries = open_mm(self.path / "queries.npy", mode=mode, shape=None if mode == "r+" else (n, C.QUERY_DIM), **kw)
        self.rgb = open_mm(self.path / "rgb.npy", mode=mode, shape=None if mode == "r+" else (n, C.RGB_DIM), **kw)
        if mode == "w+":
            self._save_progress()

    @property
    def chunks(self) -> int:
        return -(-self.n // self.chunk)

    def chunk_range(self, index: int) -> tuple[int, int]:
        return index * self.chunk, min((index + 1) * self.chunk, self.n)

    def write_chunk(self, index: int, queries: np.ndarray, rgb: np.ndarray) -> None:
        """Store chunk `index` (must be the next one) and record it as done once flushed."""
        if index != self.done:
            raise DatasetError(f"chunk {index} written out of order (next is {self.done})")
        lo, hi = self.chunk_range(index)
        self.queries[lo:hi] = C.as_queries(queries)
        self.rgb[lo:hi] = C.as_rgb(rgb, hi - lo)
        self.queries.flush()
        self.rgb.flush()
        self.done = index + 1
        self._save_progress()

    def finalize(self) -> Dataset:
        """Mark the data set complete (every chunk must be written) and reopen it read-only."""
        if self.done != self.chunks:
            raise DatasetError(f"{self.done} of {self.chunks} chunks written; cannot finalize")
        if self.complete:
            return open_dataset(self.path)
        del self.queries, self.rgb
        _write_json(self.path / "meta.json", {**self.meta, "complete": True})
        self._progress.unlink(missing_ok=True)
        return open_dataset(self.path)

    def _save_progress(self) -> None:
        _write_json(self._progress, {"done": self.done, "meta": self.meta})


def write_dataset(path: str | Path, queries: np.ndarray, rgb: np.ndarray, meta: dict[str, Any]) -> Dataset:
    """Write a whole data set at once (e.g. converted external/measured data)."""
    q = C.as_queries(queries)
    writer = DatasetWriter(path, q.shape[0], max(q.shape[0], 1), meta)
    if q.shape[0]:
        writer.write_chunk(0, q, C.as_rgb(rgb, q.shape[0]))
    return writer.finalize()
