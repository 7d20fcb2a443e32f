"""`NeuralShading.evaluate` moves queries and answers in bulk: each material's rows reach its
evaluator in one (n, 7) buffer (entry by entry, lanes in order), and every answer comes back to the
lane and entry that asked, zero elsewhere, with one evaluator call per material."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.client import contract as C
from neumip.client.mitsuba.bsdf import dr, mi
from neumip.client.mitsuba.shading import NeuralQueries, NeuralShading

WIDTH = 1000


class Echo:
    """Answers each row with (u, v, sigma) + 1 of that row and keeps the buffers it was sent."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, np.ndarray]] = []

    def materials(self) -> list[str]:
        return ["a", "b"]

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        self.calls.append((material, np.array(queries)))
        return queries[:, :3] + 1.0


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
    columns = rng.uniform(-1, 1, (2, C.QUERY_DIM, WIDTH)).astype(np.float32)  # (entry, column, lane)
    masks = {"a": rng.random((2, WIDTH)) < 0.4, "b": rng.random((2, WIDTH)) < 0.3}
    masks["b"] &= ~masks["a"]  # a lane hits one material
    masks["b"][1] = False  # material b: only entry 0 asks
    return columns, masks


def test_rows_and_answers_land_on_their_lanes(lanes):
    columns, masks = lanes
    evaluator = Echo()
    queries = NeuralQueries(
        [[mi.Float(c) for c in entry] for entry in columns],
        {m: [mi.Bool(k) for k in mask] for m, mask in masks.items()},
    )
    out = shading(evaluator).evaluate(queries)

    assert [m for m, _ in evaluator.calls] == ["a", "b"]  # one call per material
    for material, rows in evaluator.calls:
        want = np.concatenate([columns[k][:, masks[material][k]].T for k in range(2)])
        np.testing.assert_array_equal(rows, want)
    for k in range(2):
        got = np.stack([np.asarray(c) for c in (out[k].x, out[k].y, out[k].z)], axis=1)
        asked = masks["a"][k] | masks["b"][k]
        np.testing.assert_array_equal(got[asked], columns[k][:3, asked].T + 1.0)
        assert not got[~asked].any()


def test_no_rows_no_call(lanes):
    columns, _ = lanes
    evaluator = Echo()
    none = [mi.Bool(np.zeros(WIDTH, bool))] * 2
    out = shading(evaluator).evaluate(NeuralQueries([[mi.Float(c) for c in e] for e in columns], {"a": none}))
    assert evaluator.calls == []
    assert dr.all(out[0] == 0, axis=None) and dr.all(out[1] == 0, axis=None)


def test_bad_answers_are_refused(lanes):
    columns, masks = lanes

    class Short(Echo):
        def evaluate(self, material, queries):
            return super().evaluate(material, queries)[:-1]

    with pytest.raises(C.QueryError, match="shape"):
        shading(Short()).evaluate(NeuralQueries([[mi.Float(c) for c in e] for e in columns],
                                                {"a": [mi.Bool(k) for k in masks["a"]]}))
