"""Triton's system shared-memory extension (`server.shared_memory`): registration, infer with the rows in
shared memory, every way a client can get it wrong, `MaterialClient(protocol="shm")` and tritonclient's own
shared-memory utilities against a real server process."""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.server.app import create_app
from neumip.server.settings import Settings

SHM = Path("/dev/shm")
pytestmark = pytest.mark.skipif(not SHM.is_dir(), reason="POSIX shared memory lives in /dev/shm (Linux)")
Q = C.random_queries(300, seed=11)
REGIONS = "/v2/systemsharedmemory"


@pytest.fixture(scope="module")
def shm_client(model_dir):
    """TestClient of an in-process app that allows shared memory."""
    from fastapi.testclient import TestClient

    app = create_app(Settings(model_dir=model_dir, warmup_rows=64, max_rows=50_000, allow_shared_memory=True))
    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


@pytest.fixture
def shm_object():
    """make(size) -> (key, path) of a new shared-memory object; each is removed after the test."""
    made = []

    def make(size: int) -> tuple[str, Path]:
        path = SHM / f"neumip-test-{secrets.token_hex(6)}"
        with path.open("wb") as f:
            f.truncate(size)
        made.append(path)
        return "/" + path.name, path

    yield make
    for path in made:
        path.unlink(missing_ok=True)


def register(client, name: str, key: str, byte_size: int, offset: int = 0):
    return client.post(f"{REGIONS}/region/{name}/register", json={"key": key, "offset": offset, "byte_size": byte_size})


def infer(client, queries_at: dict, answers_at: dict | None, shape, model: str = "rand16"):
    inputs = [{"name": "queries", "datatype": "FP32", "shape": list(shape), "parameters": queries_at}]
    outputs = [{"name": "rgb", "parameters": answers_at}] if answers_at is not None else None
    return client.post(f"/v2/models/{model}/infer", json={"inputs": inputs, **({"outputs": outputs} if outputs else {})})


def at(region: str, byte_size: int, offset: int = 0) -> dict:
    return {"shared_memory_region": region, "shared_memory_byte_size": byte_size, "shared_memory_offset": offset}


def test_queries_and_answers_through_shared_memory(shm_client, shm_object, reference):
    """Queries at an offset of one object, answers in another: the same bits as in process, and the answer's
    JSON says where they are and holds no data."""
    key, path = shm_object(4096 + Q.nbytes)
    out_key, out_path = shm_object(Q.shape[0] * 12)
    with path.open("r+b") as f:
        f.seek(4096)
        f.write(Q.tobytes())
    assert register(shm_client, "in", key, Q.nbytes + 96, offset=4000).status_code == 200
    assert register(shm_client, "out", out_key, Q.shape[0] * 12).status_code == 200
    listed = shm_client.get(f"{REGIONS}/status").json()
    assert {r["name"]: (r["key"], r["offset"], r["byte_size"]) for r in listed} == {
        "in": (key, 4000, Q.nbytes + 96), "out": (out_key, 0, Q.shape[0] * 12)}
    resp = infer(shm_client, at("in", Q.nbytes, 96), at("out", Q.shape[0] * 12), Q.shape)
    assert resp.status_code == 200, resp.text
    [output] = resp.json()["outputs"]
    assert output["shape"] == [Q.shape[0], 3] and "data" not in output
    assert output["parameters"] == at("out", Q.shape[0] * 12)
    rgb = np.frombuffer(out_path.read_bytes(), np.float32).reshape(-1, 3)
    np.testing.assert_array_equal(rgb, reference.evaluate("rand16", Q))
    # queries in shared memory, the answer in the response as usual
    plain = infer(shm_client, at("in", Q.nbytes, 96), None, Q.shape)
    np.testing.assert_array_equal(np.asarray(plain.json()["outputs"][0]["data"], np.float32).reshape(-1, 3), rgb)
    assert shm_client.post(f"{REGIONS}/region/in/unregister").status_code == 200
    gone = infer(shm_client, at("in", Q.nbytes, 96), None, Q.shape)
    assert gone.status_code == 400 and "no shared-memory region 'in'" in gone.json()["error"]
    assert shm_client.post(f"{REGIONS}/unregister").status_code == 200
    assert shm_client.get(f"{REGIONS}/status").json() == []


def test_query_groups_through_shared_memory(shm_client, shm_object, reference):
    groups = np.ascontiguousarray(np.hstack([Q, Q[::-1, C.WI_X:C.WI_Y + 1]]))  # (N, 9): two lights
    key, path = shm_object(groups.nbytes + groups.shape[0] * 24)
    path.write_bytes(groups.tobytes() + bytes(groups.shape[0] * 24))
    assert register(shm_client, "groups", key, path.stat().st_size).status_code == 200
    try:
        resp = infer(shm_client, at("groups", groups.nbytes), at("groups", groups.shape[0] * 24, groups.nbytes),
                     groups.shape)
        assert resp.status_code == 200, resp.text
        rgb = np.frombuffer(path.read_bytes()[groups.nbytes:], np.float32).reshape(-1, 6)
        np.testing.assert_array_equal(rgb, reference.evaluate("rand16", groups))
    finally:
        shm_client.post(f"{REGIONS}/region/groups/unregister")


def test_bad_registrations_say_what_is_wrong(shm_client, shm_object, tmp_path):
    key, path = shm_object(1024)
    cases = [
        ("r1", {"key": "/../etc/passwd", "byte_size": 8}, "must name a shared-memory object"),
        ("r1", {"key": "/a/b", "byte_size": 8}, "must name a shared-memory object"),
        ("r1", {"key": "noslash", "byte_size": 8}, "must name a shared-memory object"),
        ("r1", {"key": "/neumip-test-none", "byte_size": 8}, "no such object"),
        ("r1", {"key": key, "byte_size": 2048}, "past the end"),
        ("r1", {"key": key, "offset": 1000, "byte_size": 25}, "past the end"),
        ("r1", {"key": key, "byte_size": 0}, "at least 1"),
        ("r1", {"key": key, "byte_size": -1}, "non-negative integer"),
        ("r1", {"key": key, "byte_size": True}, "non-negative integer"),
        ("r1", {"key": key}, "'byte_size' must be"),
        ("bad/name", {"key": key, "byte_size": 8}, None),  # not a route: 404
        ("r1", [1, 2], "register takes"),
    ]
    for name, body, message in cases:
        resp = shm_client.post(f"{REGIONS}/region/{name}/register", json=body)
        if message is None:
            assert resp.status_code == 404
            continue
        assert resp.status_code == 400 and message in resp.json()["error"], (body, resp.text)
    link = SHM / f"neumip-test-link-{secrets.token_hex(4)}"
    link.symlink_to(path)
    try:
        resp = shm_client.post(f"{REGIONS}/region/r1/register", json={"key": "/" + link.name, "byte_size": 8})
        assert resp.status_code == 400 and "symbolic link" in resp.json()["error"]
    finally:
        link.unlink()
    fifo = SHM / f"neumip-test-fifo-{secrets.token_hex(4)}"
    os.mkfifo(fifo)
    try:  # opened without blocking, then refused
        resp = shm_client.post(f"{REGIONS}/region/r1/register", json={"key": "/" + fifo.name, "byte_size": 8})
        assert resp.status_code == 400 and "is not a shared-memory object" in resp.json()["error"]
    finally:
        fifo.unlink()
    assert shm_client.post(f"{REGIONS}/region/r1/register", content=b"{").status_code == 400
    assert shm_client.post(f"{REGIONS}/region/r1/register", content=b" " * 5000).status_code == 413
    assert register(shm_client, "r1", key, 8).status_code == 200
    again = register(shm_client, "r1", key, 8)
    assert again.status_code == 400 and "already registered" in again.json()["error"]
    assert shm_client.get(f"{REGIONS}/region/nope/status").status_code == 400
    shm_client.post(f"{REGIONS}/unregister")


def test_regions_of_removed_objects_make_room(shm_client, shm_object):
    """At the most regions, those whose objects were removed without unregistering (a client that died) are
    forgotten; live ones are not."""
    from neumip.server.shared_memory import MAX_REGIONS

    objects = [shm_object(8) for _ in range(MAX_REGIONS)]
    for i, (key, _) in enumerate(objects):
        assert register(shm_client, f"r{i}", key, 8).status_code == 200
    extra, _ = shm_object(8)
    full = register(shm_client, "extra", extra, 8)
    assert full.status_code == 400 and "the most at once" in full.json()["error"]
    objects[7][1].unlink()
    assert register(shm_client, "extra", extra, 8).status_code == 200
    names = {r["name"] for r in shm_client.get(f"{REGIONS}/status").json()}
    assert "r7" not in names and len(names) == MAX_REGIONS
    shm_client.post(f"{REGIONS}/unregister")


def test_bad_infer_requests_are_400_and_the_server_carries_on(shm_client, shm_object, reference):
    """Sizes that do not match, regions too small, NaN in the rows, an object truncated after it was
    registered (read with pread: a short read, never a fault), half the parameters."""
    key, path = shm_object(Q.nbytes)
    path.write_bytes(Q.tobytes())
    out_key, out_path = shm_object(Q.shape[0] * 12)
    assert register(shm_client, "q", key, Q.nbytes).status_code == 200
    assert register(shm_client, "a", out_key, Q.shape[0] * 12).status_code == 200
    small_key, _ = shm_object(64)
    assert register(shm_client, "small", small_key, 64).status_code == 200
    n = Q.shape[0]
    cases = [
        (at("q", Q.nbytes - 4), at("a", n * 12), Q.shape, "FP32 needs"),
        (at("q", Q.nbytes, 4), at("a", n * 12), Q.shape, "pass the end"),
        (at("q", Q.nbytes), at("a", n * 12 - 4), Q.shape, "the answers take"),
        (at("q", Q.nbytes), at("small", n * 12), Q.shape, "pass the end"),
        (at("nope", Q.nbytes), at("a", n * 12), Q.shape, "no shared-memory region 'nope'"),
        ({"shared_memory_region": "q"}, None, Q.shape, "must be a non-negative integer"),
        ({"shared_memory_byte_size": Q.nbytes}, None, Q.shape, "must name a registered region"),
        ({**at("q", Q.nbytes), "binary_data_size": Q.nbytes}, None, Q.shape, "neither"),
    ]
    for queries_at, answers_at, shape, message in cases:
        resp = infer(shm_client, queries_at, answers_at, shape)
        assert resp.status_code == 400 and message in resp.json()["error"], (queries_at, resp.text)
    bad = Q.copy()
    bad[5, C.U] = np.nan
    path.write_bytes(bad.tobytes())
    resp = infer(shm_client, at("q", Q.nbytes), at("a", n * 12), Q.shape)
    assert resp.status_code == 400 and "row 5" in resp.json()["error"]
    os.truncate(path, Q.nbytes // 2)  # the client shrank its object after registering it
    resp = infer(shm_client, at("q", Q.nbytes), at("a", n * 12), Q.shape)
    assert resp.status_code == 400 and "truncated" in resp.json()["error"]
    path.write_bytes(Q.tobytes())
    os.truncate(out_path, 8)
    resp = infer(shm_client, at("q", Q.nbytes), at("a", n * 12), Q.shape)
    assert resp.status_code == 400 and "truncated below the answers" in resp.json()["error"]
    assert out_path.stat().st_size == 8  # nothing was written past it
    os.truncate(out_path, n * 12)
    resp = infer(shm_client, at("q", Q.nbytes), at("a", n * 12), Q.shape)
    assert resp.status_code == 200
    np.testing.assert_array_equal(np.frombuffer(out_path.read_bytes(), np.float32).reshape(-1, 3),
                                  reference.evaluate("rand16", Q))
    shm_client.post(f"{REGIONS}/unregister")


def test_shared_memory_is_off_unless_allowed(client, shm_client):
    """Off by default, as Triton's --allow-client-shm: every route says how to turn it on, and the server's
    metadata lists the extension only where it is on."""
    for method, path in (("get", f"{REGIONS}/status"), ("post", f"{REGIONS}/unregister"),
                         ("post", f"{REGIONS}/region/x/register")):
        resp = getattr(client, method)(path, **({"json": {"key": "/x", "byte_size": 1}} if "register" in path else {}))
        assert resp.status_code == 403 and "NEUMIP_ALLOW_SHARED_MEMORY" in resp.json()["error"]
    resp = infer(client, at("q", Q.nbytes), None, Q.shape)
    assert resp.status_code == 403
    assert "system_shared_memory" not in client.get("/v2").json()["extensions"]
    assert "system_shared_memory" in shm_client.get("/v2").json()["extensions"]


def test_material_client_through_shared_memory(serve, reference):
    """`MaterialClient(protocol="shm")` against a real server: the same bits as in process for single queries
    and groups, regions that grow with the request, and nothing left in /dev/shm after close."""
    from neumip.client.http import MaterialClient, ServerError

    server = serve(allow_shared_memory="true")
    mine = lambda: {p.name for p in SHM.glob(f"neumip-{os.getpid()}-*")}  # noqa: E731
    with MaterialClient(server.url, protocol="shm") as client:
        for n in (1, 1000, 70_000):  # 70 000 rows (1.96 MB) grow the 1 MiB regions
            q = C.random_queries(n, seed=n)
            np.testing.assert_array_equal(client.evaluate("rand16", q), reference.evaluate("rand16", q))
        groups = np.ascontiguousarray(np.hstack([q, q[::-1, C.WI_X:C.WI_Y + 1], q[:, C.WO_X:C.QUERY_DIM]]))
        np.testing.assert_array_equal(client.evaluate("rand16", groups), reference.evaluate("rand16", groups))
        assert len(mine()) == 2
        listed = json.loads(client._http.get(f"{REGIONS}/status").text)
        assert {r["name"] for r in listed} == mine()
        bad = q.copy()
        bad[3, C.WO_X] = 2.0
        with pytest.raises(C.QueryError):  # checked before anything is sent
            client.evaluate("rand16", bad)
    assert not mine()
    refused = serve()  # shared memory not allowed: a clear error
    with MaterialClient(refused.url, protocol="shm") as client, pytest.raises(ServerError, match="ALLOW_SHARED_MEMORY"):
        client.evaluate("rand16", Q)
    assert not mine()


def test_tritonclient_shared_memory_against_a_real_server(serve, reference):
    """Triton's own client and its shared-memory utilities (`tritonclient.utils.shared_memory`)."""
    triton = pytest.importorskip("tritonclient.http")
    shm = pytest.importorskip("tritonclient.utils.shared_memory")

    server = serve(allow_shared_memory="true")
    client = triton.InferenceServerClient(server.host_port)
    q = C.random_queries(5000, seed=3)
    key = f"/neumip-test-triton-{secrets.token_hex(4)}"
    handles = [shm.create_shared_memory_region("tin", key, q.nbytes),
               shm.create_shared_memory_region("tout", key + "o", q.shape[0] * 12)]
    try:
        shm.set_shared_memory_region(handles[0], [q])
        client.register_system_shared_memory("tin", key, q.nbytes)
        client.register_system_shared_memory("tout", key + "o", q.shape[0] * 12)
        assert {r["name"] for r in client.get_system_shared_memory_status()} == {"tin", "tout"}
        tensor = triton.InferInput("queries", list(q.shape), "FP32")
        tensor.set_shared_memory("tin", q.nbytes)
        output = triton.InferRequestedOutput("rgb", binary_data=True)
        output.set_shared_memory("tout", q.shape[0] * 12)
        result = client.infer("rand16", [tensor], outputs=[output])
        assert result.get_output("rgb")["shape"] == [q.shape[0], 3]
        rgb = shm.get_contents_as_numpy(handles[1], np.float32, [q.shape[0], 3])
        np.testing.assert_array_equal(rgb, reference.evaluate("rand16", q))
        client.unregister_system_shared_memory()
        assert client.get_system_shared_memory_status() == []
    finally:
        for handle in handles:
            shm.destroy_shared_memory_region(handle)


def test_a_stalled_register_is_408(serve, shm_object):
    """A client that states a register body and never sends it is cut off after the body timeout."""
    import socket

    server = serve(allow_shared_memory="true", body_timeout_s="1")
    host, port = server.host_port.split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        sock.sendall(b"POST /v2/systemsharedmemory/region/r/register HTTP/1.1\r\nHost: x\r\n"
                     b"Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{")
        reply = b""
        while chunk := sock.recv(4096):  # until the server closes the connection
            reply += chunk
    reply = reply.decode()
    assert reply.startswith("HTTP/1.1 408") and "not complete after 1 s" in reply


def test_auto_takes_shared_memory_where_the_server_offers_it_on_this_machine(serve, reference, monkeypatch):
    """`protocol="auto"` (`neumip render`'s default): shared memory from a loopback server that lists the extension,
    msgpack from one that does not, from a host elsewhere (no question asked), and from one that cannot open the
    client's objects (here: made outside /dev/shm); the same bits every way."""
    import httpx

    from neumip.client import shared_memory as S
    from neumip.client.http import MaterialClient, MsgpackCodec

    q = C.random_queries(2000, seed=5)
    expected = reference.evaluate("rand16", q)
    allowed, refused = serve(allow_shared_memory="true"), serve()
    for server, chosen in ((allowed, S.SharedMemoryCodec), (refused, MsgpackCodec)):
        with MaterialClient(server.url, protocol="auto") as client:
            np.testing.assert_array_equal(client.evaluate("rand16", q), expected)
            assert type(client.codec.chosen) is chosen
    asked = []

    def elsewhere(request):
        asked.append(request.url.path)
        body = np.abs(np.asarray(q[:, :3]))  # any answer of the right shape
        from neumip.core import wire
        return httpx.Response(200, content=wire.encode_response(body.astype(np.float32)))

    with MaterialClient("http://10.1.2.3:8000", protocol="auto", transport=httpx.MockTransport(elsewhere)) as client:
        client.evaluate("rand16", q)
        assert type(client.codec.chosen) is MsgpackCodec and asked == ["/v1/materials/rand16/evaluate"]
    monkeypatch.setattr(S, "SHM_DIR", Path(os.environ.get("TMPDIR", "/tmp")))  # objects the server cannot find
    with MaterialClient(allowed.url, protocol="auto") as client:
        np.testing.assert_array_equal(client.evaluate("rand16", q), expected)
        assert type(client.codec.chosen) is MsgpackCodec


def test_a_chunked_register_body_is_refused_as_it_passes_its_limit(serve):
    """A register body sent chunked, without a length, gets its 413 once it passes 4 kB, not after the body
    timeout or the JSON limit (16 MB reserved 16 times over)."""
    import socket

    server = serve(allow_shared_memory="true", body_timeout_s="60")
    host, port = server.host_port.split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        sock.sendall(b"POST /v2/systemsharedmemory/region/r/register HTTP/1.1\r\nHost: x\r\n"
                     b"Content-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n"
                     + b"%x\r\n" % 5000 + b"{" + b" " * 4999 + b"\r\n")  # never the last chunk
        reply = b""
        while b"}" not in reply.partition(b"\r\n\r\n")[2]:  # the status line, the headers, the JSON error
            reply += sock.recv(4096) or b"}"
    assert reply.startswith(b"HTTP/1.1 413") and b"4096" in reply


def test_a_client_registers_its_regions_again_once_the_server_forgot_them(serve, reference, monkeypatch):
    """Another client unregistering every region (as Triton's examples do at start), or a server restarted: the
    next evaluation registers the client's regions anew and answers; `auto` takes msgpack where they cannot be."""
    import httpx

    from neumip.client.http import MaterialClient, MsgpackCodec, ServerError

    server = serve(allow_shared_memory="true")
    q = C.random_queries(3000, seed=8)
    expected = reference.evaluate("rand16", q)
    for protocol in ("shm", "auto"):
        with MaterialClient(server.url, protocol=protocol) as client:
            np.testing.assert_array_equal(client.evaluate("rand16", q), expected)
            assert httpx.post(f"{server.url}{REGIONS}/unregister").status_code == 200
            np.testing.assert_array_equal(client.evaluate("rand16", q), expected)
            listed = httpx.get(f"{server.url}{REGIONS}/status").json()
            assert len(listed) == 2 and all(r["name"].startswith(f"neumip-{os.getpid()}-") for r in listed)
    with MaterialClient(server.url, protocol="auto") as client:
        client.evaluate("rand16", q)
        assert httpx.post(f"{server.url}{REGIONS}/unregister").status_code == 200

        request = MaterialClient._request

        def restarted_without_shared_memory(self, method, path, *args, **kwargs):  # as such a server answers
            if path.startswith(REGIONS):
                raise ServerError("shared memory is off: NEUMIP_ALLOW_SHARED_MEMORY", 403)
            return request(self, method, path, *args, **kwargs)

        monkeypatch.setattr(MaterialClient, "_request", restarted_without_shared_memory)
        np.testing.assert_array_equal(client.evaluate("rand16", q), expected)
        assert type(client.codec.chosen) is MsgpackCodec
    assert not list(SHM.glob(f"neumip-{os.getpid()}-*"))


def test_a_full_dev_shm_is_an_error_not_a_crash(monkeypatch):
    """The client takes its objects' pages when it makes them: a full /dev/shm is an OSError saying so (and the
    object is removed), never a SIGBUS at the first copy into the mapping."""
    import errno

    from neumip.client import shared_memory as S

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(S.os, "posix_fallocate", full)
    with pytest.raises(OSError, match="do not fit in /dev/shm") as raised:
        S.SharedBuffer(1 << 20)
    assert raised.value.errno == errno.ENOSPC
    assert not list(SHM.glob(f"neumip-{os.getpid()}-*"))
