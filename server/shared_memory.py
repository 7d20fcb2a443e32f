"""Triton's system shared-memory extension: queries and answers in POSIX shared memory, not in the bodies.

A client on the same machine creates a shared-memory object (``shm_open``: a file under ``/dev/shm``),
registers a region of it by name, then names the region in an infer request's input or requested output
(``shared_memory_region``, ``shared_memory_byte_size``, ``shared_memory_offset``; `neumip.core.wire`).
The request and its answer are then a few hundred bytes of JSON: a renderer on the same host skips copying
its rows through both sockets (`benchmarks/bench_engines.py --server`).

Its routes are in `neumip.server.v2`:

    GET  /v2/systemsharedmemory[/region/{name}]/status
    POST /v2/systemsharedmemory/region/{name}/register   {"key": "/obj", "offset": 0, "byte_size": B}
    POST /v2/systemsharedmemory[/region/{name}]/unregister

Off by default (`Settings.allow_shared_memory`, Triton's ``--allow-client-shm``): a client that may
register regions makes the server read, and write answers into, any shared-memory object the server's
user can open. The server never maps a region: it reads the queries with ``pread`` and writes the answers
with ``pwrite`` on the descriptor it opened at registration, so a client that truncates its object gets a
400 (the bytes are missing), never a crash of the server (a mapping would fault).
"""

from __future__ import annotations

import asyncio
import errno
import os
import re
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.core.wire import SharedMemoryRef

from neumip.server.errors import ApiError

SHM_DIR = Path("/dev/shm")
"""Where Linux keeps POSIX shared-memory objects: key ``/obj`` is the file ``/dev/shm/obj``."""
MAX_REGIONS = 64
"""Most regions registered at once (each holds an open file descriptor)."""
KEY_PATTERN = re.compile(r"/(?!\.{1,2}$)[A-Za-z0-9_.-]{1,250}")
"""A shared-memory key: ``/`` and one file name (no further ``/``, not ``.`` or ``..``)."""
NAME_PATTERN = re.compile(r"[A-Za-z0-9_.-]{1,128}")
"""A region's name, as it appears in URLs."""
OFFLOAD_BYTES = 16 << 20
"""Reads and writes larger than this run in a thread, keeping the event loop free."""
OFF = ("shared memory is off on this server: start it with NEUMIP_ALLOW_SHARED_MEMORY=true "
       "(for clients on the same machine)")


@dataclass
class Region:
    """A registered region: ``byte_size`` bytes from ``offset`` of the object ``key``, open as ``fd``."""

    name: str
    key: str
    offset: int
    byte_size: int
    fd: int
    writable: bool
    users: int = 0  # requests reading or writing it now; unregistering closes `fd` once none are
    gone: bool = False

    def status(self) -> dict:
        return {"name": self.name, "key": self.key, "offset": self.offset, "byte_size": self.byte_size}


def _count(body: dict, key: str, default: int | None = None) -> int:
    value = body.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ApiError(400, f"'{key}' must be a non-negative integer, got {str(value)[:40]!r}")
    return value


class SharedMemory:
    """The registered regions of one server (touched on the event loop only)."""

    def __init__(self, allowed: bool) -> None:
        self.allowed = allowed
        self.regions: dict[str, Region] = {}

    def check_allowed(self) -> None:
        if not self.allowed:
            raise ApiError(403, OFF)

    def register(self, name: str, body: object) -> None:
        """Open ``/dev/shm`` + key and register `byte_size` bytes of it from `offset` as `name`; 400 saying
        what is wrong (a name in use, a key that is no shared-memory object, a region past its end)."""
        self.check_allowed()
        if not NAME_PATTERN.fullmatch(name):
            raise ApiError(400, f"{name[:40]!r} is not a region name (1-128 letters, digits, '_', '.', '-')")
        if not isinstance(body, dict):
            raise ApiError(400, 'register takes {"key": "/name", "offset": 0, "byte_size": B}')
        if name in self.regions:
            raise ApiError(400, f"shared-memory region {name!r} is already registered: unregister it first")
        if len(self.regions) >= MAX_REGIONS:
            self._forget_removed()
        if len(self.regions) >= MAX_REGIONS:
            raise ApiError(400, f"{MAX_REGIONS} shared-memory regions are registered, the most at once")
        key = body.get("key")
        if not isinstance(key, str) or not KEY_PATTERN.fullmatch(key):
            raise ApiError(400, f"'key' must name a shared-memory object, '/' then a file name, got {str(key)[:60]!r}")
        offset, size = _count(body, "offset", 0), _count(body, "byte_size")
        if not size:
            raise ApiError(400, "'byte_size' must be at least 1")
        fd, writable = _open(SHM_DIR / key[1:], key)
        try:
            info = os.fstat(fd)
            if not stat.S_ISREG(info.st_mode):
                raise ApiError(400, f"shared-memory key {key!r} is not a shared-memory object")
            if offset + size > info.st_size:
                raise ApiError(400, f"region {name!r} ends at byte {offset + size}, past the end of {key!r} "
                                    f"({info.st_size} bytes)")
        except BaseException:
            os.close(fd)
            raise
        self.regions[name] = Region(name, key, offset, size, fd, writable)

    def unregister(self, name: str | None = None) -> None:
        """Forget region `name`, or every region; a region in use closes when its requests are done."""
        self.check_allowed()
        if name is None:
            return self.close()
        names = [name]
        for each in names:
            region = self.regions.pop(each, None)
            if region is not None:
                region.gone = True
                if not region.users:
                    os.close(region.fd)

    def _forget_removed(self) -> None:
        """Unregister the regions whose objects were removed (``shm_unlink``) by clients that did not unregister
        them (a client that died): nobody can open them again, and each holds a descriptor and its memory."""
        for region in list(self.regions.values()):
            if not region.users and os.fstat(region.fd).st_nlink == 0:
                self.unregister(region.name)

    def close(self) -> None:
        """Forget every region (at shutdown, or unregistering all); one in use closes when its request is done."""
        for region in list(self.regions.values()):
            region.gone = True
            if not region.users:
                os.close(region.fd)
        self.regions.clear()

    def status(self, name: str | None = None) -> list[dict]:
        self.check_allowed()
        if name is None:
            return [region.status() for region in self.regions.values()]
        if name not in self.regions:
            raise ApiError(400, f"no shared-memory region {name[:40]!r} is registered")
        return [self.regions[name].status()]

    @contextmanager
    def using(self, ref: SharedMemoryRef) -> Iterator[Region]:
        """The region `ref` points into, kept open for the ``with`` block; 400 unless it is registered and
        holds ``ref``'s bytes."""
        self.check_allowed()
        region = self.regions.get(ref.region)
        if region is None:
            raise ApiError(400, f"no shared-memory region {ref.region[:40]!r} is registered")
        if ref.offset + ref.byte_size > region.byte_size:
            raise ApiError(400, f"{ref.byte_size} bytes from offset {ref.offset} pass the end of shared-memory "
                                f"region {ref.region!r} ({region.byte_size} bytes)")
        region.users += 1
        try:
            yield region
        finally:
            region.users -= 1
            if region.gone and not region.users:
                os.close(region.fd)

    async def read_queries(self, ref: SharedMemoryRef, shape: tuple[int, int]) -> np.ndarray:
        """The (N, 5 + 2 K) queries `ref` points to, validated (`contract.as_queries`); 400 if the object
        no longer holds them."""
        out = np.empty(shape, C.DTYPE)
        with self.using(ref) as region:
            got = await _io(os.preadv, region, [out], region.offset + ref.offset, out.nbytes)
        if got != out.nbytes:
            raise ApiError(400, f"shared-memory region {ref.region!r} holds {got} of the {out.nbytes} bytes of "
                                f"the queries: its object {region.key!r} was truncated")
        return C.as_queries(out, groups=True)

    def check_answer(self, ref: SharedMemoryRef, nbytes: int) -> None:
        """Before evaluating: 400 unless `ref` can take `nbytes` of answers."""
        with self.using(ref) as region:
            _check_writable(region)
        if ref.byte_size < nbytes:
            raise ApiError(400, f"the answers take {nbytes} bytes; shared_memory_byte_size of '{C.ONNX_OUTPUT}' "
                                f"is {ref.byte_size}")

    async def write_answer(self, ref: SharedMemoryRef, rgb: np.ndarray) -> None:
        """Write (N, 3 K) answers where `ref` points; 400 if the object was truncated below them."""
        rgb = np.ascontiguousarray(rgb, C.DTYPE)
        with self.using(ref) as region:
            _check_writable(region)  # again: registered anew meanwhile, the name may be another object's
            start = region.offset + ref.offset
            if os.fstat(region.fd).st_size < start + rgb.nbytes:  # writing would grow it, not fill it
                raise ApiError(400, f"shared-memory object {region.key!r} was truncated below the answers")
            put = await _io(os.pwritev, region, [rgb], start, rgb.nbytes)
        if put != rgb.nbytes:
            raise ApiError(500, f"wrote {put} of {rgb.nbytes} bytes of answers to shared-memory region {ref.region!r}")


def _check_writable(region: Region) -> None:
    if not region.writable:
        raise ApiError(400, f"shared-memory object {region.key!r} is read-only to the server: it cannot take the answers")


def _open(path: Path, key: str) -> tuple[int, bool]:
    """(descriptor, writable) of the object at `path`: read-write where allowed, else read-only; 400 if
    it cannot be opened. No symbolic links are followed, and nothing blocks (a FIFO put there is refused as
    no regular file once open)."""
    flags = os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK
    try:
        return os.open(path, os.O_RDWR | flags), True
    except PermissionError:
        pass
    except OSError as exc:
        raise ApiError(400, f"cannot open shared-memory object {key!r}: {_why(exc)}") from None
    try:
        return os.open(path, os.O_RDONLY | flags), False
    except OSError as exc:
        raise ApiError(400, f"cannot open shared-memory object {key!r}: {_why(exc)}") from None


def _why(exc: OSError) -> str:
    return {errno.ENOENT: "no such object (create it with shm_open first)",
            errno.ELOOP: "it is a symbolic link"}.get(exc.errno, exc.strerror or str(exc))


async def _io(call, region: Region, buffers: list, offset: int, nbytes: int) -> int:
    """``preadv``/``pwritev`` on the region's object, in a thread when large (on a descriptor of its own, which the
    thread closes: a handler cancelled meanwhile may close the region's); 400 with the system's reason if it fails
    (507 for a full ``/dev/shm``)."""
    try:
        if nbytes <= OFFLOAD_BYTES:
            return call(region.fd, buffers, offset)
        fd = os.dup(region.fd)

        def run() -> int:
            try:
                return call(fd, buffers, offset)
            finally:
                os.close(fd)

        return await asyncio.to_thread(run)
    except OSError as exc:
        status = 507 if exc.errno == errno.ENOSPC else 400
        raise ApiError(status, f"shared-memory object {region.key!r}: {exc.strerror or exc}") from None
