"""`NeuralShading.evaluate` moves queries and answers in bulk: each material's query groups reach its
evaluator in one (n, 9) buffer (lanes in order), and every answer comes back to the lane and light
that asked, zero elsewhere, with one evaluator call per material."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.client import contract as C
from neumip.client.mitsuba.bsdf import dr, mi
from neumip.client.mitsuba.shading import NeuralQueries, NeuralShading

WIDTH = 1000


class Echo:
    """Answers light j of each group with (u, v, sigma) + 1 + j and keeps the buffers it was sent."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, np.ndarray]] = []

    def materials(self) -> list[str]:
        return ["a", "b"]

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        self.calls.append((material, np.array(queries)))
        lights = C.group_lights(queries.shape[1])
        return np.concatenate([queries[:, :3] + 1.0 + j for j in range(lights)], axis=1)


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
    masks = {"a": rng.random((2, WIDTH)) < 0.4, "b": rng.random((2, WIDTH)) < 0.3}  # (light, lane)
    masks["b"] &= ~(masks["a"][0] | masks["a"][1])  # a lane hits one material
    masks["b"][1] = False  # material b: only light 0 asks
    return columns, masks


def queries(columns, masks) -> NeuralQueries:
    return NeuralQueries([mi.Float(c) for c in columns],
                         {m: (mi.Bool(k[0] | k[1]), [mi.Bool(x) for x in k]) for m, k in masks.items()})


def test_rows_and_answers_land_on_their_lanes(lanes):
    columns, masks = lanes
    evaluator = Echo()
    out = shading(evaluator).evaluate(queries(columns, masks))

    assert [m for m, _ in evaluator.calls] == ["a", "b"]  # one call per material
    for material, rows in evaluator.calls:
        np.testing.assert_array_equal(rows, columns[:, masks[material][0] | masks[material][1]].T)
    for k in range(2):
        got = np.stack([np.asarray(c) for c in (out[k].x, out[k].y, out[k].z)], axis=1)
        asked = masks["a"][k] | masks["b"][k]
        np.testing.assert_array_equal(got[asked], columns[:3, asked].T + 1.0 + k)
        assert not got[~asked].any()


def test_no_rows_no_call(lanes):
    columns, _ = lanes
    evaluator = Echo()
    out = shading(evaluator).evaluate(queries(columns, {"a": np.zeros((2, WIDTH), bool)}))
    assert evaluator.calls == []
    assert dr.all(out[0] == 0, axis=None) and dr.all(out[1] == 0, axis=None)


def test_bad_answers_are_refused(lanes):
    columns, masks = lanes

    class Short(Echo):
        def evaluate(self, material, queries):
            return super().evaluate(material, queries)[:, :-1]

    with pytest.raises(C.QueryError, match="shape"):
        shading(Short()).evaluate(queries(columns, {"a": masks["a"]}))
