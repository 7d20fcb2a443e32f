"""The stability sweeps' figures: a flat answer is not a discontinuity."""

from __future__ import annotations

import numpy as np

from neumip.core import contract as C
from neumip.report.stability import subtexel_sweep


def test_a_texel_answered_flat_reads_no_step_and_a_jump_reads_one():
    def flat(q):
        return np.full((len(q), 3), 0.2, np.float32) + 1e-6 * (q[:, C.U:C.U + 1] > 0.5 + 0.5 / 64)

    def jump(q):
        return np.where(q[:, C.U:C.U + 1] > 0.5 + 0.5 / 64, 0.4, 0.2).astype(np.float32) * np.ones((1, 3), np.float32)

    assert subtexel_sweep(flat, 65, 64)["largest_step_over_range"] < 1e-3
    assert subtexel_sweep(jump, 65, 64)["largest_step_over_range"] > 0.99
