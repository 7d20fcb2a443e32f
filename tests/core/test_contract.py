"""The query contract: validation and level of detail."""

import numpy as np
import pytest

from neumip.core import contract as C


def good(n=4):
    q = np.zeros((n, 7), np.float32)
    q[:, C.SIGMA] = 0.01
    return q


@pytest.mark.parametrize(
    "data, message",
    [
        (np.zeros((3, 6), np.float32), r"shape \(N, 7\)"),
        (np.zeros((7,), np.float32), r"shape \(N, 7\)"),
        (np.zeros((2, 7), dtype="U3"), "numeric"),
    ],
)
def test_shape_and_dtype_errors(data, message):
    with pytest.raises(C.QueryError, match=message):
        C.as_queries(data)


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("column", range(7))
def test_non_finite_values_are_rejected_with_position(value, column):
    q = good()
    q[2, column] = value
    with pytest.raises(C.QueryError, match=f"row 2 column {C.QUERY_FIELDS[column]}"):
        C.as_queries(q)


def test_directions_outside_unit_disk_are_rejected_but_rounding_is_tolerated():
    q = good()
    q[1, C.WO_X] = 1.0 + C.DIRECTION_TOLERANCE / 4  # rounding: accepted (grazing)
    C.as_queries(q)
    q[3, C.WI_X], q[3, C.WI_Y] = 0.8, 0.8
    with pytest.raises(C.QueryError, match="wi must be .* row 3"):
        C.as_queries(q)


def test_float64_and_int_are_converted_and_empty_is_fine():
    assert C.as_queries(np.zeros((2, 7))).dtype == np.float32
    assert C.as_queries(np.zeros((0, 7))).shape == (0, 7)


def test_level_of_detail_convention():
    lod = C.level_of_detail(np.array([0.0, -5, 1 / 512, 1 / 256, 4 / 256, 1.0, 1e20]), 256)
    np.testing.assert_allclose(lod, [0, 0, 0, 0, 2, 8, 8])
    assert C.sigma_for_level(3, 256) == 8 / 256


def test_query_groups_widths_values_and_ungroup():
    assert [C.group_width(k) for k in (1, 2, 3)] == [7, 9, 11]
    assert [C.group_lights(w) for w in (7, 9, 11)] == [1, 2, 3]
    for width in (5, 6, 8, C.group_width(C.MAX_LIGHTS) + 2):
        with pytest.raises(C.QueryError, match="5 \\+ 2 K"):
            C.group_lights(width)
    q = C.random_queries(4, seed=3)
    groups = np.concatenate([q, q[::-1, 3:5]], axis=1)
    with pytest.raises(C.QueryError, match="shape"):
        C.as_queries(groups)  # single queries only unless groups are allowed
    assert C.as_queries(groups, groups=True).shape == (4, 9)
    singles = C.ungroup(groups)
    np.testing.assert_array_equal(singles[0::2], q)
    np.testing.assert_array_equal(singles[1::2, [C.WI_X, C.WI_Y]], q[::-1, 3:5])
    np.testing.assert_array_equal(singles[1::2, [C.U, C.V, C.SIGMA, C.WO_X, C.WO_Y]], q[:, [0, 1, 2, 5, 6]])
    bad = groups.copy()
    bad[2, 8] = np.inf
    with pytest.raises(C.QueryError, match="row 2 column wi_y of light 2"):
        C.as_queries(bad, groups=True)
    bad[2, 7:9] = 0.9
    with pytest.raises(C.QueryError, match="wi of light 2 .* row 2"):
        C.as_queries(bad, groups=True)
    assert C.as_rgb(np.zeros((4, 6)), 4, lights=2).shape == (4, 6)
    with pytest.raises(C.QueryError, match="shape"):
        C.as_rgb(np.zeros((4, 3)), 4, lights=2)


def test_version_problem_names_the_upgrade_of_a_version_1_file():
    """The one message every loader gives a model file of another contract version."""
    assert C.CONTRACT_VERSION == "2" and C.version_problem({C.META_CONTRACT: "2"}, "m.onnx") is None
    old = C.version_problem({C.META_CONTRACT: "1"}, "models/old.onnx")
    assert "version 1" in old and "`neumip export models/old.onnx -o NEW.onnx`" in old
    assert "no neumip.contract_version" in C.version_problem({}, "m.onnx")
    other = C.version_problem({C.META_CONTRACT: "99"}, "m.onnx")
    assert "version '99'" in other and "reads version 2" in other


def test_sampling_lobe_metadata():
    """The model's sampling lobe: absent or weight 0 is the cosine alone; a malformed one is an engine problem."""
    assert C.sampling_lobe({}) is None
    lobe = C.SamplingLobe(0.2, 0.5)
    assert C.sampling_lobe({C.META_SAMPLING: lobe.to_json()}) == lobe
    assert C.sampling_lobe({C.META_SAMPLING: C.SamplingLobe(0.2, 0.0).to_json()}) is None
    for bad in ('{"alpha": 0.2}', "not json", '{"alpha": 0, "weight": 0.5}', '{"alpha": 0.2, "weight": 1}',
                '{"alpha": "0.2", "weight": 0.5}', '{"alpha": NaN, "weight": 0.5}', "[1, 2]",
                '{"alpha": true, "weight": 0.5}', '{"alpha": 1' + "0" * 400 + ', "weight": 0.5}',
                "[" * 100_000 + "]" * 100_000):
        with pytest.raises(C.SamplingLobeError, match="neumip.sampling"):
            C.sampling_lobe({C.META_SAMPLING: bad})
        problem = C.engine_problem({C.META_CONTRACT: C.CONTRACT_VERSION, C.META_SAMPLING: bad})
        assert problem and "neumip.sampling" in problem
    assert C.engine_problem({C.META_CONTRACT: C.CONTRACT_VERSION, C.META_SAMPLING: lobe.to_json()}) is None
