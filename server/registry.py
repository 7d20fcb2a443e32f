"""The model registry: the ``*.onnx`` materials of the model folder, loaded, checked and warmed up.

Loading. Eagerly (``NEUMIP_LOAD=eager``, the default) every file loads at start-up; lazily
(``NEUMIP_LOAD=lazy``) start-up only lists the folder and a material loads on its first request. In
both modes a request for a file that appeared later loads it (no restart).

Following the folder. Every ``NEUMIP_POLL_S`` seconds the folder is listed again (`Registry.poll`):
a new file loads (eager mode; lazy mode waits for a request), a changed file of a loaded material is
loaded and swapped in, a deleted file's material is dropped (404 from then on). A file is acted on
only once it looked the same on two polls in a row, so one being copied is not read half-way.
``POST /v2/repository/models/{name}/load`` and ``/unload`` do the same for one material at once.

Swaps are atomic: the new model is read, loaded and warmed up beside the old one, which serves until
the new one takes its place; requests already given the old one finish on it. A file that fails to
load (corrupt, half-written, another contract) never replaces a working model: the old one keeps
serving and the failure is logged; a material with no working model is kept in :attr:`failed` with
its reason, so its ready endpoint can say no. A file that changes while it is read is not loaded.

Engines. The materials load into the engine of ``NEUMIP_ENGINE`` (`neumip.server.engine`): ONNX
Runtime sessions or drjit kernels; everything here holds for both.

Memory. With ``NEUMIP_MEMORY_BUDGET_MB`` the least recently used materials are unloaded (they load
again when asked for) while the loaded models' bytes exceed it; a material with a request in flight
(`Registry.using`) is never unloaded, so the budget may be exceeded while every loaded material is
busy; the excess is unloaded when their requests finish. A model's bytes are its file's size.

Material names from requests are only ever looked up in dicts, never joined into a path before
`check_name` accepted them.

The registry builds on the engines' model folder (`neumip.engines.folder`): the same listing and
names, the same read of a file's bytes, and each file read and checked by the one model-file reader
(`neumip.core.modelfile`) inside the engine's loader.
"""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from collections import Counter, OrderedDict
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.core.modelfile import ModelError
from neumip.engines.folder import BAD_NAME, NAME_PATTERN, FileStamp, UnknownMaterial, list_models, read_model_bytes
from neumip.engines.local import Material

from neumip.server.engine import WARM_LIGHTS, Engine
from neumip.server.errors import ApiError
from neumip.server.metrics import Metrics

log = logging.getLogger(__name__)

MODEL_VERSION = "1"
"""The one version of each material the server exposes (Open Inference Protocol model version)."""


def warmup_queries(rows: int, lights: int = 1) -> np.ndarray:
    """(rows, 7) float32 valid queries spread over the tile, all levels and a cone of directions; with
    ``lights`` > 1, (rows, 5 + 2 lights) query groups whose further lights are other rows' wi."""
    t = np.linspace(0.0, 1.0, rows, dtype=np.float32)
    queries = np.zeros((rows, C.QUERY_DIM), dtype=C.DTYPE)
    queries[:, C.U] = t
    queries[:, C.V] = t[::-1]
    queries[:, C.SIGMA] = 2.0 ** (-12.0 * t)
    queries[:, C.WI_X] = 0.7 * np.cos(7 * t)
    queries[:, C.WI_Y] = 0.7 * np.sin(7 * t)
    queries[:, C.WO_X] = 0.5 * np.sin(3 * t)
    queries[:, C.WO_Y] = 0.5 * np.cos(3 * t)
    others = [np.roll(queries[:, C.WI_X:C.WI_Y + 1], j, axis=0) for j in range(1, lights)]
    return np.ascontiguousarray(np.hstack([queries, *others])) if others else queries


def without_folder(message: str, folder: Path) -> str:
    """`message` with the model folder's path taken out of the file paths in it (ONNX Runtime's errors
    name the file in full): clients learn the file name, not where the server keeps its files."""
    for prefix in {str(folder.resolve()), str(folder.absolute()), str(folder)}:
        message = message.replace(prefix + os.sep, "")
    return message


def check_name(name: str) -> str:
    """Raise a 400 ApiError unless `name` looks like a material name (no paths, no dots first)."""
    if not NAME_PATTERN.match(name):
        raise ApiError(
            400,
            f"invalid material name {name[:80]!r}: use letters, digits, '_', '.', '-'"
            " (starting with a letter or digit, at most 128 characters)",
        )
    return name


@dataclass
class RegistryConfig:
    """How the registry loads and keeps materials (from the server settings)."""

    engine: Engine = field(default_factory=Engine.onnxruntime)
    """What loads and evaluates the materials."""
    warmup_rows: int = 1024
    """Rows each material evaluates when it loads, before it serves (single queries, then groups of two and three)."""
    lazy: bool = False
    """Load a material on its first request instead of at start-up."""
    memory_budget_bytes: int = 0
    """Most bytes of loaded models before the least recently used are unloaded (0: no limit)."""


@dataclass
class Registry:
    """Materials by name: loaded ones, the folder's files, and the files that failed and why."""

    folder: Path
    """The model folder the materials come from."""
    config: RegistryConfig = field(default_factory=RegistryConfig)
    metrics: Metrics | None = None
    materials: dict[str, Material] = field(default_factory=dict)
    """Materials loaded and warmed up, by name (file stem)."""
    failed: dict[str, str] = field(default_factory=dict)
    """Files that could not be served: name -> reason."""
    files: dict[str, FileStamp] = field(default_factory=dict)
    """The folder's model files with valid names, as last listed."""
    unloaded: set[str] = field(default_factory=set)
    """Materials unloaded by request: not served until loaded again."""

    def __post_init__(self) -> None:
        self._lock = threading.RLock()
        self._load_locks: dict[str, threading.Lock] = {}
        self._stamps: dict[str, FileStamp] = {}  # stamp of each loaded material's file when read
        self._in_flight: Counter[str] = Counter()
        self._used: OrderedDict[str, None] = OrderedDict()  # loaded materials, least recently used first
        self._seen: dict[str, FileStamp | None] = {}  # the previous poll's listing
        self._failed_at: dict[str, FileStamp] = {}  # the file a failed material failed with

    @classmethod
    def load(cls, folder: Path, engine: Engine | None = None, warmup_rows: int = 1024, lazy: bool = False,
             memory_budget_bytes: int = 0, metrics: Metrics | None = None) -> "Registry":
        """List `folder` and (unless lazy) load and warm up every ``*.onnx`` in it (raises
        FileNotFoundError if the folder is missing)."""
        folder = Path(folder)
        if not folder.is_dir():
            raise FileNotFoundError(f"model folder {folder} does not exist")
        config = RegistryConfig(engine or Engine.onnxruntime(), warmup_rows, lazy, memory_budget_bytes)
        registry = cls(folder, config, metrics)
        registry._seen = registry._list()
        registry.files = {n: s for n, s in registry._seen.items() if s is not None}
        if not lazy:
            for name in sorted(registry.files):
                registry._try_load(name)
        log.info(
            "%s %d material(s) from %s%s", "listed (lazy loading)" if lazy else "serving",
            len(registry.files) if lazy else len(registry.materials), folder,
            f"; {len(registry.failed)} failed" if registry.failed else "",
        )
        return registry

    # --- the folder ------------------------------------------------------------------------------
    def _list(self) -> dict[str, FileStamp | None]:
        """Name -> stamp of every ``*.onnx`` in the folder (None: an invalid name, recorded as failed)."""
        named, bad = list_models(self.folder)
        listing: dict[str, FileStamp | None] = dict.fromkeys(bad)
        for name in bad:
            self.failed.setdefault(name, BAD_NAME)
        for name, path in named.items():
            stamp = FileStamp.of(path)
            if stamp is not None:
                listing[name] = stamp
        return listing

    def poll(self) -> None:
        """List the folder again and act on the files that changed and then stayed the same since
        the previous poll (see the module docstring). Runs in a thread."""
        listing = self._list()
        stable = {n: s for n, s in listing.items() if s is not None and self._seen.get(n) == s}
        self._seen = listing
        with self._lock:
            gone = [n for n in set(self.files) | set(self.materials) if n not in listing]
            self.files = {**{n: s for n, s in self.files.items() if n in listing}, **stable}
            for name in [n for n in self.failed if n not in listing]:  # e.g. a badly named file removed
                del self.failed[name]
        for name in gone:
            self._drop(name, "deleted")
        for name, stamp in stable.items():
            loaded = self._stamps.get(name)
            if loaded is not None:
                reload = loaded != stamp and self._failed_at.get(name) != stamp  # changed: swap it in
            else:  # not loaded: eager mode loads new files (and failed ones that changed since)
                reload = not self.config.lazy and name not in self.unloaded and self._failed_at.get(name) != stamp
            if reload:
                self._try_load(name)

    def path(self, name: str) -> Path:
        return self.folder / f"{check_name(name)}.onnx"

    # --- loading -----------------------------------------------------------------------------------
    def _try_load(self, name: str) -> None:
        try:
            self.load_material(name)
        except (ApiError, UnknownMaterial):
            pass  # logged and recorded; a file deleted meanwhile is dropped

    def load_material(self, name: str, pin: bool = False) -> Material:
        """Load (or reload, if its file changed) material `name` and make it the one served; with
        `pin`, count a request in flight on it in the same step. Blocking: run it in a thread.

        Raises ApiError: 404 if there is no such file, 400 if it cannot be served (the reason; an
        older model of the same name, if loaded, keeps serving).
        """
        path = self.path(name)
        with self._lock:
            lock = self._load_locks.setdefault(name, threading.Lock())
        with lock:
            stamp = FileStamp.of(path)
            if stamp is None:
                self._drop(name, "deleted")
                raise UnknownMaterial(f"unknown material {name!r} (no {name}.onnx in the model folder)")
            with self._lock:
                if name in self.materials and self._stamps.get(name) == stamp:
                    return self._mark_used(name, pin)
            start = time.perf_counter()
            try:
                material = self._read(path, stamp)
            except ApiError as exc:
                self._count_load(name, "failed")
                with self._lock:
                    self._failed_at[name] = stamp  # polls do not retry this file
                    if name in self.materials:
                        log.error("keeping the loaded %s: its new file cannot be served: %s", name, exc.message)
                    else:
                        self.failed[name] = exc.message
                raise
            with self._lock:
                self.materials[name], self._stamps[name], self.files[name] = material, stamp, stamp
                self.failed.pop(name, None)
                self._failed_at.pop(name, None)
                self.unloaded.discard(name)
                self._mark_used(name, pin)
            seconds = time.perf_counter() - start
            self._count_load(name, "loaded", seconds, material.bytes)
            log.info("loaded %s (%d bytes) in %.3f s", name, material.bytes, seconds)
        self._evict(keep=name)
        return material

    def _read(self, path: Path, stamp: FileStamp) -> Material:
        """Read, load and warm up one file; ApiError(400) with the reason if it cannot be served."""
        try:
            data = read_model_bytes(path, stamp)
            material = self.config.engine.load(path, data)
            rows = self.config.warmup_rows
            for lights in WARM_LIGHTS if rows else ():  # the renderer's two shapes (the kernel engine traces each)
                C.as_rgb(material.run(warmup_queries(rows, lights)), rows, lights)
        except (ModelError, OSError) as exc:
            reason = str(exc)
        except Exception as exc:  # a model that loads but fails to run (bad graph, wrong shapes)
            reason = f"{path.name}: warm-up evaluation failed: {exc}"
        else:
            return material
        log.error("cannot serve %s: %s", path.name, reason)
        raise ApiError(400, without_folder(reason, self.folder))

    def _mark_used(self, name: str, pin: bool) -> Material:
        """Under the lock: `name` was just used (and, with `pin`, has one more request in flight)."""
        self._used[name] = None
        self._used.move_to_end(name)
        if pin:
            self._in_flight[name] += 1
        return self.materials[name]

    # --- unloading ---------------------------------------------------------------------------------
    def _drop(self, name: str, reason: str) -> None:
        """Stop serving `name` (its file is gone, or on request); requests holding it finish on it."""
        with self._lock:
            material = self.materials.pop(name, None)
            self._stamps.pop(name, None)
            self._used.pop(name, None)
            if reason == "deleted":
                self.files.pop(name, None)
                self.failed.pop(name, None)
        if material is not None:
            self._count_unload(name, reason)
            log.info("unloaded %s (%s)", name, reason)

    def unload(self, name: str) -> None:
        """`POST .../unload`: unload `name` now; it is not served until loaded again (404 if unknown)."""
        self.check(name)
        with self._lock:
            self.unloaded.add(name)
        self._drop(name, "request")

    def _evict(self, keep: str | None = None) -> None:
        """Unload least recently used materials with no request in flight (but `keep`) while over the
        budget."""
        budget = self.config.memory_budget_bytes
        if not budget:
            return
        while True:
            with self._lock:
                if sum(m.bytes for m in self.materials.values()) <= budget:
                    return
                idle = [n for n in self._used if n != keep and not self._in_flight[n]]
                if not idle:
                    log.warning("memory budget exceeded: every other loaded material has a request in flight")
                    return
                victim = idle[0]
            self._drop(victim, "memory")

    # --- requests ----------------------------------------------------------------------------------
    @asynccontextmanager
    async def using(self, name: str):
        """Around evaluating a request: the material, loaded if need be, counted in flight (so it is
        not unloaded for memory) until the block ends."""
        check_name(name)
        with self._lock:
            material = self._mark_used(name, pin=True) if name in self.materials else None
        if material is None:
            self._servable(name)
            material = await asyncio.to_thread(self.load_material, name, True)
        try:
            yield material
        finally:
            with self._lock:
                self._in_flight[name] -= 1
                idle = not self._in_flight[name]
            if idle:  # a material kept over the budget while busy may go now
                self._evict()

    def _servable(self, name: str) -> None:
        """Raise unless `name` is loaded or can be loaded on request: 400 if it failed or was unloaded,
        404 if there is no file for it."""
        if name in self.unloaded:
            raise ApiError(400, f"material {name!r} is not ready: it was unloaded (POST .../load to load it)")
        stamp = FileStamp.of(self.path(name))
        if name in self.failed and stamp == self._failed_at.get(name):  # the same file: no second try
            raise ApiError(400, f"material {name!r} is not ready (failed to load): {self.failed[name]}")
        if stamp is None:
            known = ", ".join(self.names()) or "none"
            raise UnknownMaterial(f"unknown material {name!r} (served: {known})")

    def check(self, name: str) -> str:
        """`name` if it is served (loaded, or loadable on request); 400 if malformed, failed or
        unloaded, 404 if unknown. Loads nothing."""
        check_name(name)
        if name not in self.materials:
            self._servable(name)
        return name

    def get(self, name: str) -> Material:
        """The loaded material `name` (loading it first if need be; blocking)."""
        self.check(name)
        material = self.materials.get(name)
        return material if material is not None else self.load_material(name)

    def names(self) -> list[str]:
        """Materials served: loaded, or (lazily) loadable on request."""
        with self._lock:
            listed = set(self.files) - set(self.failed) - self.unloaded
            return sorted(listed | set(self.materials))

    def resident_bytes(self) -> int:
        with self._lock:
            return sum(m.bytes for m in self.materials.values())

    def listing(self) -> dict:
        """What ``GET /v1/materials`` answers: each served material (metadata if loaded) and the failures."""
        with self._lock:
            materials = dict(self.materials)
            files = dict(self.files)
        entries = []
        for name in self.names():
            if name in materials:
                entries.append({**materials[name].info(), "loaded": True})
            else:
                entries.append({"name": name, "loaded": False, "bytes": files[name].size})
        return {
            "materials": entries,
            "failed": [{"name": n, "error": e} for n, e in sorted(self.failed.items())],
        }

    def info(self, name: str) -> dict:
        """``GET /v1/materials/{name}``: the material's metadata (loads it if need be)."""
        return {**self.get(name).info(), "loaded": True}

    # --- metrics -----------------------------------------------------------------------------------
    def _count_load(self, name: str, outcome: str, seconds: float = 0.0, size: int = 0) -> None:
        if self.metrics is None:
            return
        self.metrics.model_loads.labels(name, outcome).inc()
        if outcome == "loaded":
            self.metrics.model_load_seconds.observe(seconds)
            self.metrics.resident_bytes.labels(name).set(size)

    def _count_unload(self, name: str, reason: str) -> None:
        if self.metrics is not None:
            self.metrics.model_unloads.labels(name, reason).inc()
            self.metrics.resident_bytes.labels(name).set(0)
