"""`MaterialClient`: evaluate materials on a `neumip serve` server over its msgpack endpoint.

The same interface as the in-process `LocalMaterials` (`materials()`, `evaluate(name, queries)`), so
a renderer takes either. Requests go through one ``httpx.Client`` kept for the client's life: one
kept-alive HTTP/1.1 connection, the query rows handed to the socket without a copy. Requests have
timeouts; 503 (queue full, honouring ``Retry-After``) and connection failures are retried a bounded
number of times with exponential backoff; anything else fails at once with an error that says what
the server answered. Large buffers are sent as several requests of at most ``ClientConfig.max_rows``
rows. Query groups (N, 5 + 2 K) travel as they are (`neumip.core.contract`) and answer (N, 3 K);
a row is a group, so a split never cuts one. A material name
goes into the URL path, so a name that is not a material name (`neumip.engines.local.NAME_PATTERN`) is
refused before anything is sent.

How queries and answers travel is a `Codec` (`PROTOCOLS`): the msgpack ``/v1`` format by default, or
the Open Inference Protocol's ``/v2`` binary tensors (``protocol="v2"``), both laid out in
`neumip.core.wire`, or ``/v2`` with the rows in shared memory (``protocol="shm"``, a server on the same
machine: `neumip.client.shared_memory`); the retries and the transport are the same for all. Tests inject an httpx transport (``httpx.MockTransport``) into the same
``httpx.Client`` path, and run against a real server process.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from urllib.parse import urlsplit
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from neumip.core import contract as C
from neumip.core import wire
from neumip.core.errors import NeumipError
from neumip.engines.local import NAME_PATTERN, UnknownMaterial

log = logging.getLogger(__name__)

SEND_PART_BYTES = 1 << 20
"""A request body goes out in parts of at most this many bytes (views of the caller's buffers, no copies).
httpcore sends a part by slicing off what each ``send`` took, a copy of the rest every time: 2^20 single queries
(a 28 MB request and a 1.4 MB one, `ClientConfig.max_rows`) cost the client 21-31 ms of CPU sent whole, 16-17 ms in
parts of 1 MiB (`experiments/server_overhead/send_parts.py`, `benchmarks/server_cpu.py`)."""


def _in_parts(body: list | None, size: int | None = None) -> list | None:
    """`body`'s buffers cut into views of at most `size` (`SEND_PART_BYTES`) bytes, in order."""
    if not body:
        return body
    size = size or SEND_PART_BYTES
    parts = []
    for buffer in body:
        view = memoryview(buffer).cast("B")
        parts += [view[i:i + size] for i in range(0, len(view), size)] if len(view) > size else [buffer]
    return parts


def _httpx():
    try:
        import httpx
    except ImportError as exc:
        raise ImportError("MaterialClient needs httpx: pip install 'neumip[client]'") from exc
    return httpx


class ServerError(NeumipError, RuntimeError):
    """The server answered with an error, or could not be reached after the allowed retries."""

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


class ServerUnavailable(ServerError):
    """No answer from the server (connection refused/reset, timeout, or 503 past the retries)."""


class UnknownServedMaterial(ServerError, UnknownMaterial):
    """The server serves no material of that name (404 to an evaluation): an `UnknownMaterial`, as in process
    (`LocalMaterials` raises one), and a `ServerError`."""


@dataclass
class ClientConfig:
    """How `MaterialClient` talks to a server."""

    timeout_s: float = 60.0
    """Seconds allowed for connecting, sending, and each read of one request."""
    connect_timeout_s: float = 5.0
    """Seconds allowed to open a connection."""
    retries: int = 3
    """Extra attempts after a 503 or a connection failure (0: fail at the first)."""
    backoff_s: float = 0.2
    """Wait before the first retry; doubles each retry (a 503's Retry-After wins if longer)."""
    max_backoff_s: float = 5.0
    """Longest wait between two attempts."""
    max_rows: int = 1_000_000
    """Most queries per request, a query group of K lights counting K; larger buffers are split
    (between groups; server default limit: 2M)."""


class Codec(Protocol):
    """How one evaluation travels: where it goes, its request body, and how its answer reads."""

    def path(self, material: str) -> str:
        """URL path of the evaluation endpoint of `material`."""
        ...

    def encode(self, queries: np.ndarray) -> tuple[dict[str, str], list]:
        """Validated (n, 7) float32 queries or (n, 5 + 2 K) groups -> (request headers, body as a list
        of buffers)."""
        ...

    def decode(self, response, rows: int, lights: int) -> np.ndarray:
        """The answer (an ``httpx.Response``) to a request of `rows` groups of `lights` lights ->
        (rows, 3 lights) float32 RGB."""
        ...


class MsgpackCodec:
    """The ``/v1`` msgpack format (`neumip.core.wire`): the rows go out and come back as raw float32."""

    def path(self, material: str) -> str:
        return wire.EVALUATE_PATH.format(name=material)

    def encode(self, queries: np.ndarray) -> tuple[dict[str, str], list]:
        header, rows = wire.encode_request_parts(queries)
        headers = {
            "Content-Type": wire.MSGPACK_MEDIA_TYPE,
            "Accept": wire.MSGPACK_MEDIA_TYPE,
            "Content-Length": str(len(header) + rows.nbytes),  # set: the parts go out as one body, not chunked
        }
        return headers, [header, rows]

    def decode(self, response, rows: int, lights: int) -> np.ndarray:
        return C.as_rgb(wire.decode_response(response.content), rows, lights)


class InferCodec:
    """The Open Inference Protocol ``/v2`` infer endpoint with binary tensors in and out (`wire`)."""

    def path(self, material: str) -> str:
        return wire.INFER_PATH.format(name=material)

    def encode(self, queries: np.ndarray) -> tuple[dict[str, str], list]:
        return wire.encode_infer_request(queries)

    def decode(self, response, rows: int, lights: int) -> np.ndarray:
        rgb = wire.decode_infer_response(response.content, response.headers.get(wire.INFER_HEADER_LENGTH))
        return C.as_rgb(rgb, rows, lights)


class AutoCodec:
    """Shared memory where the server is on this machine and offers it (`client.shared_memory`), else msgpack:
    decided at the first evaluation, from the URL's host and the server's ``GET /v2`` extensions. A region the server
    cannot open (another user, another machine's ``/dev/shm``: a container's port on loopback) falls back to msgpack
    for good, with one log line."""

    def __init__(self, client) -> None:
        self.client = client
        self.chosen = None

    def _choose(self) -> Codec:
        from neumip.client.shared_memory import EXTENSION, LOOPBACK, SHM_DIR, SharedMemoryCodec

        if self.chosen is None:
            self.chosen = MsgpackCodec()
            if urlsplit(self.client.url).hostname in LOOPBACK and SHM_DIR.is_dir():
                try:
                    listed = self.client._request("GET", "/v2", what="read the server's metadata").json()
                except (ServerError, ValueError):
                    listed = {}
                if EXTENSION in (listed.get("extensions") or [] if isinstance(listed, dict) else []):
                    self.chosen = SharedMemoryCodec(self.client)
        return self.chosen

    def path(self, material: str) -> str:
        return self._choose().path(material)

    def encode(self, queries: np.ndarray) -> tuple[dict[str, str], list]:
        from neumip.client.shared_memory import SharedMemoryCodec

        codec = self._choose()
        if isinstance(codec, SharedMemoryCodec):
            try:
                return codec.encode(queries)
            except (ServerError, OSError) as exc:
                if isinstance(exc, ServerError) and exc.status not in (400, 403):  # unreachable, busy: not the region
                    raise
                log.info("shared memory with %s is not possible (%s): msgpack bodies instead", self.client.url, exc)
                codec.close()
                self.chosen = MsgpackCodec()
        return self.chosen.encode(queries)

    def decode(self, response, rows: int, lights: int) -> np.ndarray:
        return self.chosen.decode(response, rows, lights)

    def recover(self) -> bool:
        """`SharedMemoryCodec.recover` while shared memory is chosen; msgpack from now on where its regions cannot be
        registered anew (the server restarted without shared memory): True either way, the request goes again."""
        recover = getattr(self.chosen, "recover", None)
        if recover is None:
            return False
        try:
            return recover()
        except (ServerError, OSError) as exc:
            if isinstance(exc, ServerError) and exc.status not in (400, 403):
                raise
            log.info("shared memory with %s is no longer possible (%s): msgpack bodies instead", self.client.url, exc)
            self.chosen.close()
            self.chosen = MsgpackCodec()
            return True

    def close(self) -> None:
        if hasattr(self.chosen, "close"):
            self.chosen.close()


def _shared_memory(client: "MaterialClient") -> Codec:
    from neumip.client.shared_memory import SharedMemoryCodec

    return SharedMemoryCodec(client)


PROTOCOLS: dict[str, Callable[["MaterialClient"], Codec]] = {
    "msgpack": lambda client: MsgpackCodec(),
    "v2": lambda client: InferCodec(),
    "shm": _shared_memory,
    "auto": AutoCodec,
}
"""How `MaterialClient` can talk to the server (the codec each client gets): ``/v1`` msgpack (the default),
``/v2`` binary tensors, ``/v2`` with the rows in shared memory (a server on the same machine that allows it:
`neumip.client.shared_memory`), or ``auto``: shared memory where the server offers it on this machine, else msgpack."""


class MaterialClient:
    """Evaluate named materials on a remote server: ``MaterialClient("http://127.0.0.1:8000")``.

    `transport` replaces httpx's network transport (tests: ``httpx.MockTransport``); `protocol` says
    how queries and answers travel: ``"msgpack"`` (``/v1``, the default), ``"v2"`` (the Open Inference
    Protocol with binary tensors), ``"shm"`` (``/v2`` with the rows in shared memory) or ``"auto"`` (``shm`` where
    the server offers it on this machine, else msgpack), see `PROTOCOLS`.
    """

    def __init__(
        self, url: str, config: ClientConfig | None = None, transport=None, protocol: str = "msgpack"
    ) -> None:
        self.url = url.rstrip("/")
        if not self.url.startswith(("http://", "https://")):
            raise ValueError(f"server URL must start with http:// or https://, got {url!r}")
        self.config = config or ClientConfig()
        if self.config.max_rows < 1 or self.config.retries < 0:
            raise ValueError("ClientConfig: max_rows must be >= 1 and retries >= 0")
        if protocol not in PROTOCOLS:
            raise ValueError(f"protocol must be one of {', '.join(PROTOCOLS)}, got {protocol!r}")
        httpx = self._httpx = _httpx()
        self._http = httpx.Client(
            base_url=self.url,
            timeout=httpx.Timeout(self.config.timeout_s, connect=self.config.connect_timeout_s),
            limits=httpx.Limits(max_connections=1, max_keepalive_connections=1),
            transport=transport,
            trust_env=False,  # no proxies from the environment: the server is named by its URL
        )
        self.codec = PROTOCOLS[protocol](self)
        self._names: list[str] | None = None
        self._lobes: dict[str, C.SamplingLobe | None] = {}
        self.server_timing: dict[str, float] = {}
        """Stage durations (ms) the server reported for the last evaluation (``Server-Timing``)."""

    # --- the Evaluator interface ----------------------------------------------------------------
    def materials(self) -> list[str]:
        """Names the server serves (asked once, then cached; `refresh()` asks again)."""
        if self._names is None:
            listing = self._request("GET", wire.MATERIALS_PATH, what="list materials").json()
            entries = listing.get("materials", []) if isinstance(listing, dict) else listing
            names = sorted(e["name"] if isinstance(e, dict) else str(e) for e in entries)
            self._lobes = {e["name"]: _listed_lobe(e) for e in entries if isinstance(e, dict) and "sampling" in e}
            self._names = names
        return list(self._names)

    def sampling(self, material: str) -> C.SamplingLobe | None:
        """The sampling lobe of the material's model, from the server's listing, or for a material the
        listing shows unloaded (a lazy server) from ``GET /v1/materials/{name}``, which loads it. None
        where the model declares none (the renderer then samples the cosine alone)."""
        if material not in self.materials():
            return None
        if material not in self._lobes and NAME_PATTERN.match(material):
            info = self._request("GET", f"{wire.MATERIALS_PATH}/{material}", what=f"describe {material!r}").json()
            self._lobes[material] = _listed_lobe(info if isinstance(info, dict) else {})
        return self._lobes.get(material)

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        """(N, 7) float32 queries -> (N, 3) float32 RGB, or query groups (N, 5 + 2 K) -> (N, 3 K), in
        requests of at most `max_rows` queries (a group of K lights counting K)."""
        if not NAME_PATTERN.match(material):  # it goes into the URL path: only safe names
            raise UnknownMaterial(
                f"{material!r} is not a material name (a letter or digit, then letters, digits, '_', "
                "'.', '-'; at most 128 characters)"
            )
        queries = C.as_queries(queries, groups=True)
        n, lights = queries.shape[0], C.group_lights(queries.shape[1])
        if n == 0:
            return np.empty((0, C.RGB_DIM * lights), dtype=C.DTYPE)
        rows = max(self.config.max_rows // lights, 1)  # per request
        if n <= rows:
            rgb = self._evaluate_once(material, queries)
            return rgb if rgb.flags.writeable else rgb.copy()  # (N, 3 K) view of the answer body
        out = np.empty((n, C.RGB_DIM * lights), dtype=C.DTYPE)
        for lo in range(0, n, rows):
            hi = min(lo + rows, n)
            out[lo:hi] = self._evaluate_once(material, queries[lo:hi])
        return out

    def _evaluate_once(self, material: str, queries: np.ndarray) -> np.ndarray:
        """One request: validated (n, 7) queries or (n, 5 + 2 K) groups -> (n, 3 K) RGB (a view of the
        answer's body)."""
        n, lights = queries.shape[0], C.group_lights(queries.shape[1])
        for again in (False, True):
            headers, body = self.codec.encode(queries)
            try:
                response = self._request("POST", self.codec.path(material), what=f"evaluate {n} queries on {material!r}",
                                         body=body, headers=headers)
                break
            except ServerError as exc:  # a 400 or 403: perhaps a server that forgot this client's shared memory
                if exc.status == 404 and "unknown material" in str(exc):
                    raise UnknownServedMaterial(str(exc), 404) from None
                recover = getattr(self.codec, "recover", None)
                if again or exc.status not in (400, 403) or recover is None or not recover():
                    raise
        self.server_timing = _server_timing(response.headers.get("Server-Timing", ""))
        return self.codec.decode(response, n, lights)

    # --- plumbing -------------------------------------------------------------------------------
    def refresh(self) -> None:
        """Forget the cached material list."""
        self._names = None

    def close(self) -> None:
        if hasattr(self.codec, "close"):  # the shared-memory codec's regions
            self.codec.close()
        self._http.close()

    def __enter__(self) -> "MaterialClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _send(self, method: str, path: str, body: list | None, headers: dict | None):
        """One exchange; sent once more on a new connection if the kept-alive one turns out closed by
        the server as the request went out (a race no idle check can rule out; evaluation is
        idempotent). Not an attempt of its own: a server that is really gone fails the second send."""
        body = _in_parts(body)
        try:
            return self._http.request(method, path, content=body, headers=headers)
        except self._httpx.RemoteProtocolError:
            log.debug("%s %s: connection closed by the server as the request went out; sending anew", method, path)
            return self._http.request(method, path, content=body, headers=headers)

    def _request(self, method: str, path: str, what: str, body: list | None = None, headers: dict | None = None):
        """One HTTP exchange with bounded retries on 503 / connection errors; raises ServerError.

        `body` is a list of buffers sent one after the other as one body (none for a GET).
        """
        cfg = self.config
        delay = cfg.backoff_s
        for attempt in range(cfg.retries + 1):
            last = attempt == cfg.retries
            try:
                response = self._send(method, path, body, headers)
            except self._httpx.TransportError as exc:
                problem = _describe(exc)
                if last:
                    raise ServerUnavailable(
                        f"cannot {what}: server {self.url} unreachable after {attempt + 1} attempt(s) "
                        f"({problem})"
                    ) from exc
                log.warning("%s: %s; retrying in %.2f s", what, problem, delay)
            else:
                if response.status_code == 200:
                    return response
                message = _error_message(response)
                if response.status_code != 503:
                    raise ServerError(
                        f"cannot {what}: server answered {response.status_code}: {message}",
                        response.status_code,
                    )
                if last:
                    raise ServerUnavailable(
                        f"cannot {what}: server {self.url} busy (503) after {attempt + 1} attempt(s): "
                        f"{message}",
                        503,
                    )
                delay = max(delay, _retry_after(response))
                log.warning("%s: server busy (503: %s); retrying in %.2f s", what, message, delay)
            time.sleep(min(delay, cfg.max_backoff_s))
            delay = min(delay * 2, cfg.max_backoff_s)
        raise AssertionError("unreachable")  # pragma: no cover


def _listed_lobe(entry: dict) -> C.SamplingLobe | None:
    """The sampling lobe of one listing entry (`client.local.Material.info`); a malformed one is
    ignored with a warning (it only moves noise)."""
    lobe = entry.get("sampling")
    if not lobe:
        return None
    try:
        return C.as_sampling_lobe(lobe, "listed sampling lobe")
    except C.SamplingLobeError as exc:
        log.warning("material %r: ignoring it: %s", entry.get("name"), exc)
        return None


def _describe(exc: Exception) -> str:
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


def _server_timing(value: str) -> dict[str, float]:
    """``read;dur=0.81, decode;dur=0.42`` -> {"read": 0.81, "decode": 0.42} (ms); odd parts skipped."""
    stages = {}
    for part in value.split(","):
        stage, _, ms = part.strip().partition(";dur=")
        try:
            stages[stage] = float(ms)
        except ValueError:
            continue
    return stages


def _error_message(response) -> str:
    """The server's ``{"error": ...}`` message, else the start of the body."""
    try:
        body = response.json()
        if isinstance(body, dict) and "error" in body:
            return str(body["error"])
    except ValueError:
        pass
    text = response.text[:200].strip()
    return text or response.reason_phrase or "no message"


def _retry_after(response) -> float:
    """Seconds from a Retry-After header (0 if absent or not a number)."""
    try:
        return max(float(response.headers.get("Retry-After", 0)), 0.0)
    except ValueError:
        return 0.0


class FallbackEvaluator:
    """`primary` (a `MaterialClient`) until it becomes unavailable, then `fallback` for good.

    The configured fallback of a render: when the server cannot be reached (after the client's
    retries), the switch is logged as a warning and every later call, including the one that failed,
    goes to ``fallback`` (e.g. `LocalMaterials` over the same model files, which answers the same).
    Errors other than unavailability (bad request, unknown material) are not hidden.
    """

    def __init__(self, primary, fallback) -> None:
        self.primary = primary
        self.fallback = fallback
        self.switched: str | None = None
        """Why the fallback took over (None while the primary serves)."""

    @property
    def current(self):
        return self.fallback if self.switched else self.primary

    def materials(self) -> list[str]:
        return self._call(lambda ev: ev.materials())

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        return self._call(lambda ev: ev.evaluate(material, queries))

    def sampling(self, material: str) -> C.SamplingLobe | None:
        """The material's sampling lobe, from whichever evaluator serves (None where it knows none)."""
        return self._call(lambda ev: ev.sampling(material) if hasattr(ev, "sampling") else None)

    def _call(self, fn):
        if not self.switched:
            try:
                return fn(self.primary)
            except ServerUnavailable as exc:
                self.switched = str(exc)
                log.warning("%s; falling back to %s", exc, type(self.fallback).__name__)
        return fn(self.fallback)
