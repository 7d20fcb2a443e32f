"""`NeuralShading.evaluate` moves queries and answers in bulk: per material, the lanes whose two
lights both count reach its evaluator as one (n, 9) buffer of query groups, the lanes where one
counts as one (n, 7) buffer of its single queries (lanes in order in both), and every answer comes
back to the lane and light that asked, zero elsewhere."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.core import contract as C
from neumip.client.mitsuba.bsdf import dr, mi
from neumip.client.mitsuba.shading import NeuralQueries, NeuralShading

WIDTH = 1000


class Echo:
    """Answers each light with (u + wi_x, v + wi_y, sigma) + 1 and keeps the buffers it was sent."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, np.ndarray]] = []

    def materials(self) -> list[str]:
        return ["a", "b"]

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        self.calls.append((material, np.array(queries)))
        singles = C.ungroup(queries)
        answers = singles[:, [C.U, C.V, C.SIGMA]] + 1.0
        answers[:, :2] += singles[:, [C.WI_X, C.WI_Y]]
        return answers.reshape(len(queries), -1)


def shading(evaluator) -> NeuralShading:
    scene = mi.load_dict({
        "type": "scene",
        "a": {"type": "rectangle", "bsdf": {"type": "neumip", "material": "a"}},
        "b": {"type": "sphere", "center": [0, 0, 3], "bsdf": {"type": "neumip", "material": "b"}},
    })
    return NeuralShading(scene, evaluator)


@pytest.fixture
def lanes():
    rng = np.random.default_rng(0)
    columns = rng.uniform(-0.7, 0.7, (C.group_width(2), WIDTH)).astype(np.float32)  # (column, lane)
    ok = rng.random((2, WIDTH)) < 0.6  # (light, lane): that light counts
    material = rng.choice(["a", "b", "-"], WIDTH, p=[0.4, 0.3, 0.3])
    return columns, ok, {m: material == m for m in ("a", "b")}


def queries(columns, ok, hit) -> NeuralQueries:
    every, one = ok[0] & ok[1], ok[0] ^ ok[1]
    single = np.where(ok[0], single_rows(columns, 0), single_rows(columns, 1))  # the valid light's
    masks = {m: (mi.Bool(h & every), mi.Bool(h & one)) for m, h in hit.items()}
    return NeuralQueries([mi.Float(c) for c in columns], [mi.Float(c) for c in single],
                         [mi.Bool(k) for k in ok], masks)


def single_rows(columns, light: int) -> np.ndarray:
    """(7, lanes): the single query of `light` at every lane."""
    wi = [C.WI_X, C.WI_Y] if light == 0 else [C.QUERY_DIM, C.QUERY_DIM + 1]
    return columns[[C.U, C.V, C.SIGMA, *wi, C.WO_X, C.WO_Y]]


def test_rows_and_answers_land_on_their_lanes(lanes):
    columns, ok, hit = lanes
    evaluator = Echo()
    out = shading(evaluator).evaluate(queries(columns, ok, hit))

    every, one = ok[0] & ok[1], ok[0] ^ ok[1]
    # per material: its groups, then its single queries (lanes in order)
    assert [(m, q.shape[1]) for m, q in evaluator.calls] == [("a", 9), ("a", 7), ("b", 9), ("b", 7)]
    for i, m in enumerate(("a", "b")):
        groups, singles = evaluator.calls[2 * i][1], evaluator.calls[2 * i + 1][1]
        np.testing.assert_array_equal(groups, columns[:, hit[m] & every].T)
        single = np.where(ok[0], single_rows(columns, 0), single_rows(columns, 1))
        np.testing.assert_array_equal(singles, single[:, hit[m] & one].T)
    for j in range(2):
        got = np.stack([np.asarray(c) for c in (out[j].x, out[j].y, out[j].z)], axis=1)
        asked = (hit["a"] | hit["b"]) & ok[j]
        want = single_rows(columns, j)[:3].T + 1.0
        want[:, :2] += single_rows(columns, j)[3:5].T
        np.testing.assert_array_equal(got[asked], want[asked])
        assert not got[~asked].any()


def test_no_rows_no_call(lanes):
    columns, ok, _ = lanes
    evaluator = Echo()
    out = shading(evaluator).evaluate(queries(columns, ok, {"a": np.zeros(WIDTH, bool)}))
    assert evaluator.calls == []
    assert dr.all(out[0] == 0, axis=None) and dr.all(out[1] == 0, axis=None)


def test_bad_answers_are_refused(lanes):
    columns, ok, hit = lanes

    class Short(Echo):
        def evaluate(self, material, queries):
            return super().evaluate(material, queries)[:, :-1]

    with pytest.raises(C.QueryError, match="shape"):
        shading(Short()).evaluate(queries(columns, ok, {"a": hit["a"]}))


def test_queries_group_two_or_more_valid_lights_and_send_one_alone():
    """`NeuralShading.queries` with three lights: a lane with two or more valid lights is a group (the
    invalid light's wi sent as (0, 0), NaN or not), a lane with one is that light's single query, a
    lane with none or off the material sends nothing."""
    from neumip.client.mitsuba.shading import NeuralHits

    nan = float("nan")
    ok = np.array([[1, 1, 0, 0, 1], [1, 0, 1, 0, 1], [0, 0, 0, 0, 1]], bool)  # (light, lane)
    hit = np.array([1, 1, 1, 1, 0], bool)  # lane 4 is not on the material
    wis = [mi.Vector3f([0.1 * j + 0.01] * 5, [0.2] * 5, [0.9] * 5) for j in range(3)]
    wis[2] = mi.Vector3f([nan] * 5, [nan] * 5, [nan] * 5)  # light 2 counts nowhere on the material
    hits = NeuralHits({"a": mi.Bool(hit)}, mi.Bool(hit), mi.Float([2.0] * 5))
    q = shading(Echo()).queries(hits, mi.Point2f([0.25] * 5, [0.5] * 5), mi.Float([0.01] * 5),
                                mi.Vector3f([0.3] * 5, [0.0] * 5, [0.95] * 5),
                                [(wi, mi.Bool(k)) for wi, k in zip(wis, ok)])
    group, single = (np.asarray(m) for m in q.masks["a"])
    np.testing.assert_array_equal(group, [1, 0, 0, 0, 0])
    np.testing.assert_array_equal(single, [0, 1, 1, 0, 0])
    columns = np.array([np.asarray(c) for c in q.columns])
    singles = np.array([np.asarray(c) for c in q.single])
    assert columns.shape == (C.group_width(3), 5)
    np.testing.assert_allclose(columns[[C.U, C.V, C.SIGMA], 0], [0.5, 1.0, 0.02])  # times uv_scale
    np.testing.assert_allclose(columns[[C.WI_X, C.QUERY_DIM, C.QUERY_DIM + 2], 0], [0.01, 0.11, 0.0])
    np.testing.assert_allclose(singles[[C.WI_X, C.WI_Y], 1], [0.01, 0.2])  # lane 1: light 0 alone
    np.testing.assert_allclose(singles[[C.WI_X, C.WI_Y], 2], [0.11, 0.2])  # lane 2: light 1 alone
    np.testing.assert_allclose(singles[[C.WO_X, C.WO_Y], 2], [0.3, 0.0])


class EchoKernel(Echo):
    """`Echo`'s answers as drjit arithmetic on the lanes (an in-kernel evaluator, as `KernelMaterials`);
    records the lane count of each material's kernel."""

    def __init__(self) -> None:
        super().__init__()
        self.widths: list[tuple[str, int]] = []

    def kernel(self, material: str) -> "EchoKernel.Material":
        return EchoKernel.Material(material, self.widths)

    class Material:
        def __init__(self, name, widths):
            self.name, self.widths = name, widths

        def answers(self, columns):
            u, v, sigma = columns[:3]
            lights = [columns[C.WI_X:C.WI_Y + 1]] + [columns[i:i + 2] for i in range(C.QUERY_DIM, len(columns), 2)]
            self.widths.append((self.name, dr.width(u)))
            return [[u + 1.0 + wi[0], v + 1.0 + wi[1], sigma + 1.0] for wi in lights]


@pytest.mark.parametrize("dense", [False, True])
def test_in_kernel_answers_land_on_their_lanes(lanes, dense):
    """In the kernel, every light of a lane with any valid light is computed; the answers land on their
    lane and light, zero elsewhere. A material on a small share of the wavefront runs over its own
    lanes only (compacted); one on nearly every lane (`DENSE_LANES`) over the whole wavefront."""
    columns, ok, hit = lanes
    if dense:  # material a on 98 % of the lanes, each with a valid light
        hit, ok = {"a": np.arange(WIDTH) % 50 != 0}, np.stack([ok[0] | ~ok[1], ok[1]])
    evaluator = EchoKernel()
    out = shading(evaluator).evaluate(queries(columns, ok, hit))

    anyok = ok[0] | ok[1]
    want_widths = [(m, WIDTH if dense else int((h & anyok).sum())) for m, h in hit.items()]
    assert evaluator.widths == want_widths
    assert evaluator.calls == []  # nothing left drjit
    for j in range(2):
        got = np.stack([np.asarray(c) for c in (out[j].x, out[j].y, out[j].z)], axis=1)
        asked = np.any(list(hit.values()), axis=0) & ok[j]
        want = single_rows(columns, j)[:3].T + 1.0
        want[:, :2] += single_rows(columns, j)[3:5].T
        np.testing.assert_array_equal(got[asked], want[asked])
        assert not got[~asked].any()
