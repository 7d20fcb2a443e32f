"""The wire formats: msgpack bit-exact round trips, the zero-copy layout and malformed bodies; the v2
binary-tensor request and answer."""

import msgpack
import numpy as np
import pytest

from neumip.core import contract as C
from neumip.core import wire
from neumip.core.contract import random_queries


def test_wire_roundtrip_is_bit_exact():
    q = np.random.default_rng(0).uniform(-0.5, 0.5, (1000, 7)).astype(np.float32)
    np.testing.assert_array_equal(wire.decode_request(wire.encode_request(q)), q)
    rgb = np.random.default_rng(1).uniform(0, 1, (1000, 3)).astype(np.float32)
    np.testing.assert_array_equal(wire.decode_response(wire.encode_response(rgb)), rgb)


def test_query_groups_travel_with_their_width_stated_or_read_from_the_byte_count():
    """(N, 5 + 2 K) groups and (N, 3 K) answers, as packb writes them or not, with "lights" (what the
    client sends) or without (older clients: the width from the byte count); bad counts are named."""
    for lights, n in ((2, 1), (2, 37), (3, 70000), (64, 3)):
        extra = [random_queries(n, seed=j)[:, C.WI_X:C.WI_Y + 1] for j in range(1, lights)]
        q = np.ascontiguousarray(np.hstack([random_queries(n, seed=0), *extra]))
        packed = msgpack.packb({"n": n, "lights": lights, "queries": q.tobytes()})
        assert wire.encode_request(q) == packed
        for body in (packed, msgpack.packb({"queries": q.tobytes(), "n": n}), msgpack.packb({"n": n, "queries": q.tobytes()}),
                     msgpack.packb({"queries": q.tobytes(), "lights": lights, "n": n})):
            np.testing.assert_array_equal(wire.decode_request(body), q)
        rgb = np.random.default_rng(n).random((n, 3 * lights), dtype=np.float32)
        body, view = wire.response_buffer(n, lights)
        view[...] = rgb
        assert bytes(body) == wire.encode_response(rgb) == msgpack.packb({"n": n, "rgb": rgb.tobytes()})
        np.testing.assert_array_equal(wire.decode_response(body), rgb)
    assert wire.decode_request(wire.encode_request(np.zeros((0, 9), np.float32))).shape == (0, 9)
    assert wire.decode_request(msgpack.packb({"n": 0, "queries": b""})).shape == (0, 7)
    for body, message in (
        (msgpack.packb({"n": 2, "queries": b"\0" * 2 * 8 * 4}), "8 float32 per row for n=2"),
        (msgpack.packb({"n": 2, "queries": b"\0" * (2 * 9 * 4 + 4)}), "not n=2 rows"),
        (msgpack.packb({"n": 0, "queries": b"\0" * 4}), "n=0 rows need 0"),
        (msgpack.packb({"n": 1, "queries": np.zeros((1, 5 + 2 * 65), np.float32).tobytes()}), "K <= 64"),
    ):
        with pytest.raises(C.QueryError, match=message):
            wire.decode_request(body)
    with pytest.raises(C.QueryError, match="multiple of n x 12 bytes"):
        wire.decode_response(msgpack.packb({"n": 2, "rgb": b"\0" * 2 * 4 * 4}))


@pytest.mark.parametrize(
    "body, message",
    [
        (b"\xc1garbage", "not valid msgpack"),
        (msgpack.packb([1, 2]), "must be a map"),
        (msgpack.packb({"n": 2, "queries": b"\0" * 55}), "holds 55 bytes"),
        (msgpack.packb({"n": -1, "queries": b""}), "non-negative"),
        (msgpack.packb({"n": 1, "queries": "text"}), "must be binary"),
    ],
)
def test_malformed_wire_bodies(body, message):
    with pytest.raises(C.QueryError, match=message):
        wire.decode_request(body)


def test_wire_parts_are_the_msgpack_bodies():
    """The zero-copy pieces the client sends and the server fills are exactly `msgpack.packb`'s bodies,
    across the bin8/bin16/bin32 and fixint/uint8/uint16/uint32 boundaries of the header."""
    for n in (0, 1, 9, 36, 37, 127, 128, 2340, 2341, 9362, 9363, 65536, 70000):
        q = random_queries(n, seed=n)
        packed = msgpack.packb({"n": n, "lights": 1, "queries": q.tobytes()})
        header, rows = wire.encode_request_parts(q)
        assert header + bytes(rows) == wire.encode_request(q) == packed
        np.testing.assert_array_equal(wire.decode_request(packed), q)
        if n:  # a view of the body, not a copy: read by the fast path
            assert np.shares_memory(wire.decode_request(packed), np.frombuffer(packed, np.uint8))
        rgb = np.random.default_rng(n).random((n, 3), dtype=np.float32)
        body, view = wire.response_buffer(n)
        view[...] = rgb
        assert bytes(body) == wire.encode_response(rgb) == msgpack.packb({"n": n, "rgb": rgb.tobytes()})
        np.testing.assert_array_equal(wire.decode_response(body), rgb)


def test_decode_still_takes_other_msgpack_layouts_and_refuses_broken_ones():
    q = random_queries(5, seed=1)
    swapped = msgpack.packb({"queries": q.tobytes(), "n": 5})  # keys in the other order: msgpack path
    np.testing.assert_array_equal(wire.decode_request(swapped), q)
    good = wire.encode_request(q)
    for broken in (good + b"\x00", good[:-1], b"\x82\xa1n\xcf" + b"\xff" * 8):
        with pytest.raises(C.QueryError, match="not valid msgpack"):
            wire.decode_request(broken)


def test_v2_binary_request_and_answer():
    import json

    q = random_queries(5, seed=3)
    headers, parts = wire.encode_infer_request(q)
    body = b"".join(bytes(part) for part in parts)
    length = int(headers[wire.INFER_HEADER_LENGTH])
    assert int(headers["Content-Length"]) == len(body)
    head = json.loads(body[:length])
    assert head["inputs"][0]["shape"] == [5, 7] and head["outputs"][0]["parameters"]["binary_data"] is True
    np.testing.assert_array_equal(np.frombuffer(body[length:], np.float32).reshape(5, 7), q)
    rgb = np.random.default_rng(0).random((5, 3), dtype=np.float32)
    out = {"name": "rgb", "datatype": "FP32", "shape": [5, 3], "parameters": {"binary_data_size": rgb.nbytes}}
    answer_head = json.dumps({"model_name": "m", "outputs": [out]}).encode()
    answer = answer_head + rgb.tobytes()
    np.testing.assert_array_equal(wire.decode_infer_response(answer, str(len(answer_head))), rgb)
    groups = np.hstack([q, q[:, C.WI_X:C.WI_Y + 1]])  # (5, 9) -> (5, 6)
    headers, parts = wire.encode_infer_request(groups)
    assert json.loads(bytes(parts[0]))["inputs"][0]["shape"] == [5, 9]
    rgb6 = np.hstack([rgb, rgb])
    out6 = {**out, "shape": [5, 6], "parameters": {"binary_data_size": rgb6.nbytes}}
    head6 = json.dumps({"model_name": "m", "outputs": [out6]}).encode()
    np.testing.assert_array_equal(wire.decode_infer_response(head6 + rgb6.tobytes(), str(len(head6))), rgb6)
    for broken, length_header, message in (
        (head6.replace(b"[5, 6]", b"[5, 5]") + rgb6.tobytes()[:-20], str(len(head6)), "N, 3 K"),
        (answer, None, "no valid"),
        (answer, "\u00b2", "no valid"),  # a superscript two: str.isdigit takes it, int refuses it
        (answer[:-4], str(len(answer_head)), "holds 56 bytes"),
        (b"{}" + rgb.tobytes(), "2", "not an infer response"),
        (answer_head.replace(b"FP32", b"FP64") + rgb.tobytes(), str(len(answer_head)), "not FP32"),
    ):
        with pytest.raises(C.QueryError, match=message):
            wire.decode_infer_response(broken, length_header)


def test_a_body_that_states_its_lights_must_hold_exactly_n_rows_of_them():
    """With "lights", a wrong n is an error naming both counts, where the byte count alone reads another
    width: 9 plain queries (63 float32) with n = 7 read as 7 groups of two lights."""
    nine = np.random.default_rng(5).uniform(-0.5, 0.5, (9, 7)).astype(np.float32)  # 63 float32, any 2 in the disk
    misread = msgpack.packb({"n": 7, "queries": nine.tobytes()})  # no "lights": read as 7 groups of 2
    assert wire.decode_request(misread).shape == (7, 9)
    for body in (wire.encode_request(nine).replace(b"\xa1n\x09", b"\xa1n\x07"),  # the client's layout
                 msgpack.packb({"lights": 1, "n": 7, "queries": nine.tobytes()})):  # another layout
        with pytest.raises(C.QueryError, match=r"holds 252 bytes, but n=7 rows of 1 light\(s\) \(7 float32 each\) need 196"):
            wire.decode_request(body)
    groups = np.hstack([nine, nine[:, C.WI_X:C.WI_Y + 1]])  # (9, 9)
    with pytest.raises(C.QueryError, match="n=9 rows of 3 light"):
        wire.decode_request(msgpack.packb({"n": 9, "lights": 3, "queries": groups.tobytes()}))
    for lights in (0, 65, -1, True, 2.0, "2", None):
        body = msgpack.packb({"n": 9, "lights": lights, "queries": groups.tobytes()})
        with pytest.raises(C.QueryError, match="'lights' must be an integer from 1 to 64"):
            wire.decode_request(body)



def test_the_v2_infer_halves_are_inverse_pairs():
    """The client's request decodes on the server side to the same queries, and the server's answer head with
    the binary RGB decodes on the client side to the same answers."""
    import json

    from neumip.core.contract import random_queries

    queries = random_queries(64, seed=2)
    headers, parts = wire.encode_infer_request(queries)
    body = b"".join(bytes(p) for p in parts)
    request = wire.decode_infer_request(body, int(headers[wire.INFER_HEADER_LENGTH]))
    assert request.binary_output and request.id is None
    np.testing.assert_array_equal(request.queries, queries)
    rgb = np.abs(queries[:, :3]).astype(np.float32)
    header = json.dumps(wire.infer_response_head("m", "1", request, rgb)).encode()
    np.testing.assert_array_equal(wire.decode_infer_response(header + rgb.tobytes(), str(len(header))), rgb)
    with pytest.raises(C.QueryError, match="not valid JSON"):
        wire.decode_infer_request(b"{" + body, int(headers[wire.INFER_HEADER_LENGTH]) + 1)


def test_shared_memory_infer_request_and_answer_round_trip():
    """A request whose rows lie in shared memory decodes to where they lie (no queries yet), and the answer's
    head, which says where the answers went, decodes on the client side; half a reference is refused."""
    import json

    queries_at, answers_at = wire.SharedMemoryRef("in", 9 * 4 * 10, 64), wire.SharedMemoryRef("out", 6 * 4 * 10)
    headers, parts = wire.encode_shared_infer_request((10, 9), queries_at, answers_at)
    request = wire.decode_infer_request(b"".join(parts), None)
    assert request.queries is None and request.shape == (10, 9)
    assert (request.input_region, request.output_region) == (queries_at, answers_at)
    head = wire.infer_response_head("m", "1", request, np.zeros((10, 6), np.float32))
    assert "data" not in head["outputs"][0]
    assert wire.decode_shared_infer_response(json.dumps(head).encode()) == ((10, 6), answers_at)
    head["outputs"][0]["parameters"]["shared_memory_byte_size"] = 4
    with pytest.raises(C.QueryError, match="says it takes 4 bytes"):
        wire.decode_shared_infer_response(json.dumps(head).encode())
    for broken in ({"parameters": ["in"]}, {"shape": 10}):  # malformed answers: a QueryError, nothing else
        with pytest.raises(C.QueryError):
            wire.decode_shared_infer_response(json.dumps({**head, "outputs": [{**head["outputs"][0], **broken}]}).encode())
    half = json.loads(b"".join(parts))
    del half["inputs"][0]["parameters"]["shared_memory_region"]
    with pytest.raises(C.QueryError, match="must name a registered region"):
        wire.decode_infer_request(json.dumps(half).encode(), None)
    wrong = json.loads(b"".join(parts))
    wrong["inputs"][0]["shape"] = [11, 9]
    with pytest.raises(C.QueryError, match="FP32 needs"):
        wire.decode_infer_request(json.dumps(wrong).encode(), None)
