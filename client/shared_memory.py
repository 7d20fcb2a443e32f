"""`SharedMemoryCodec`: a `MaterialClient` on the server's machine passes queries and answers through
shared memory (Triton's system shared-memory extension, `neumip.server.shared_memory`).

The client makes two POSIX shared-memory objects of its own (``/dev/shm/neumip-PID-...``, mode 0600),
registers them with the server as regions, copies each request's queries into one and reads the answers
from the other; the request and the answer are then a few hundred bytes of JSON. The regions grow (a new
object, registered anew) when a request needs more, and are unregistered and removed when the client
closes; at exit without a close the objects are removed, and the server forgets their regions when it needs
the room (`neumip.server.shared_memory`). The server must allow it (``NEUMIP_ALLOW_SHARED_MEMORY=true``) and be
able to open the objects: the same machine, and a user that may read and write them.
"""

from __future__ import annotations

import json
import logging
import mmap
import os
import secrets
import weakref
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.core import wire

log = logging.getLogger(__name__)

SHM_DIR = Path("/dev/shm")
"""Where Linux keeps POSIX shared-memory objects (key ``/obj`` is ``/dev/shm/obj``)."""
MIN_BYTES = 1 << 20
"""Smallest region made; a region grows to the next power of two a request needs."""
REGIONS_PATH = "/v2/systemsharedmemory/region/{name}"
STATUS_PATH = "/v2/systemsharedmemory/status"
EXTENSION = "system_shared_memory"
"""What a server that allows it lists among its extensions (``GET /v2``)."""
LOOPBACK = ("127.0.0.1", "localhost", "::1")
"""URL hosts of this machine (`client.http.AutoCodec` takes shared memory only there)."""


class SharedBuffer:
    """A shared-memory object of this process, mapped: ``/dev/shm/<name>`` of `size` bytes. Removed by
    `close`, or when the process exits."""

    def __init__(self, size: int) -> None:
        if not SHM_DIR.is_dir():
            raise OSError(f"shared memory needs {SHM_DIR} (Linux)")
        self.name = f"neumip-{os.getpid()}-{secrets.token_hex(6)}"
        self.size = size
        path = SHM_DIR / self.name
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_RDWR | os.O_CLOEXEC, 0o600)
        try:
            try:  # the pages taken now: a full /dev/shm is an OSError here, not a SIGBUS at the first copy
                os.posix_fallocate(fd, 0, size)
            except OSError as exc:
                raise OSError(exc.errno, f"{size} bytes of shared memory do not fit in {SHM_DIR}: {exc.strerror}") \
                    from None
            self.map = mmap.mmap(fd, size)
        except BaseException:
            os.unlink(path)
            raise
        finally:
            os.close(fd)
        self._remove = weakref.finalize(self, _remove, self.map, path, os.getpid())

    @property
    def key(self) -> str:
        return "/" + self.name

    def floats(self, count: int) -> np.ndarray:
        """The first `count` float32 values, a view of the mapping."""
        return np.frombuffer(self.map, C.DTYPE, count)

    def close(self) -> None:
        self._remove()


def _remove(mapping: mmap.mmap, path: Path, owner: int) -> None:
    try:
        mapping.close()
    except BufferError:  # a view still holds it: the mapping goes with the view
        pass
    if os.getpid() == owner:  # a forked child exiting leaves its parent's object alone
        path.unlink(missing_ok=True)


class SharedMemoryCodec:
    """A `client.http.Codec` whose rows travel through shared memory; `client` is the `MaterialClient`
    whose requests register and unregister the regions."""

    def __init__(self, client) -> None:
        self.client = client
        self.buffers: dict[str, SharedBuffer] = {}  # "queries", "answers" -> its region's buffer

    def path(self, material: str) -> str:
        return wire.INFER_PATH.format(name=material)

    def encode(self, queries: np.ndarray) -> tuple[dict[str, str], list]:
        n, width = queries.shape
        lights = C.group_lights(width)
        into = self._buffer("queries", queries.nbytes).floats(queries.size)
        into[...] = queries.reshape(-1)
        answers = self._buffer("answers", n * lights * C.RGB_DIM * C.DTYPE.itemsize)
        return wire.encode_shared_infer_request(
            (n, width), wire.SharedMemoryRef(self.buffers["queries"].name, queries.nbytes),
            wire.SharedMemoryRef(answers.name, n * lights * C.RGB_DIM * C.DTYPE.itemsize))

    def decode(self, response, rows: int, lights: int) -> np.ndarray:
        shape, where = wire.decode_shared_infer_response(response.content)
        answers = self.buffers["answers"]
        if where.region != answers.name or where.offset or where.byte_size > answers.size:
            raise C.QueryError(f"the answers went to {where.byte_size} bytes of region {where.region!r} from "
                               f"{where.offset}, not to this client's {answers.name!r} ({answers.size} bytes)")
        rgb = answers.floats(shape[0] * shape[1]).reshape(shape).copy()  # the region takes the next answers
        return C.as_rgb(rgb, rows, lights)

    def _buffer(self, role: str, nbytes: int) -> SharedBuffer:
        """The buffer of `role`, made or grown (and registered) to hold `nbytes`."""
        buffer = self.buffers.get(role)
        if buffer is not None and buffer.size >= nbytes:
            return buffer
        grown = SharedBuffer(max(MIN_BYTES, 1 << (max(nbytes, 1) - 1).bit_length()))
        try:
            self._register(grown)
        except BaseException:
            grown.close()
            raise
        self.buffers[role] = grown
        if buffer is not None:
            self._drop(buffer)
        return grown

    def _register(self, buffer: SharedBuffer) -> None:
        body = json.dumps({"key": buffer.key, "offset": 0, "byte_size": buffer.size}).encode()
        self.client._request("POST", REGIONS_PATH.format(name=buffer.name) + "/register",
                             what=f"register shared-memory region {buffer.name}", body=[body],
                             headers={"Content-Type": "application/json"})

    def recover(self) -> bool:
        """After an infer answered 400 or 403: register anew the regions the server no longer holds (it restarted, or
        a client unregistered every region, as Triton's examples do at start); True if there were any, so that the
        request is worth sending again. A server that no longer allows shared memory raises its ServerError (403)."""
        try:
            listed = self.client._request("GET", STATUS_PATH, what="read the shared-memory regions").json()
        except ValueError:
            return False
        held = {(r.get("name"), r.get("key"), r.get("byte_size")) for r in listed if isinstance(r, dict)} \
            if isinstance(listed, list) else set()
        missing = [b for b in self.buffers.values() if (b.name, b.key, b.size) not in held]
        for buffer in missing:
            self._register(buffer)
        return bool(missing)

    def _drop(self, buffer: SharedBuffer) -> None:
        """Unregister `buffer`'s region (one exchange, no retries) and remove its object. A server that cannot be
        told (gone, or failing) forgets the region once it needs the room: regions of removed objects go first."""
        try:
            self.client._send("POST", REGIONS_PATH.format(name=buffer.name) + "/unregister", None, None)
        except Exception as exc:
            log.debug("unregistering shared-memory region %s: %s", buffer.name, exc)
        finally:
            buffer.close()

    def close(self) -> None:
        """Unregister and remove the regions (the objects are removed even where the server is gone)."""
        buffers, self.buffers = list(self.buffers.values()), {}
        for buffer in buffers:
            self._drop(buffer)
