"""The decoder's output head: how the last layer's outputs become RGB (torch-free constants).

Two heads (`MaterialConfig.head`):
- "relu" (the paper): 3 outputs, RGB = max(out, 0).
- "yuv" (the authors' code): 6 outputs. The first 3 are YUV in log space: RGB = exp(YUV_TO_RGB @ yuv) - 1;
  the other 3 are a shadow mask 0.1 + sigmoid(s) multiplying that colour; then max(., 0). The log
  space suits high-dynamic-range values (a glint 100x brighter than its surround is a difference of
  ~5 in the output, not of 100), and the mask lets occlusion darken without moving the colour.

Training (`material.py`) and the ONNX export (`graph.py`) both compute these formulas; the matrix
and the bias that makes a head answer a given colour live here once.
"""

from __future__ import annotations

import math

import numpy as np

HEADS = ("relu", "yuv")
"""Names of the output heads."""

SHADOW_FLOOR = 0.1
"""The shadow mask is SHADOW_FLOOR + sigmoid(s): in (0.1, 1.1)."""

RGB_TO_YUV = np.array(
    [[0.299, 0.587, 0.114], [-0.14713, -0.28886, 0.436], [0.615, -0.51499, -0.10001]], np.float64
)
"""BT.601 analogue YUV from RGB (rows: Y, U, V)."""

YUV_TO_RGB = np.linalg.inv(RGB_TO_YUV)
"""RGB from YUV (the exact inverse of RGB_TO_YUV)."""


def outputs(head: str) -> int:
    """Width of the decoder's last layer for `head`."""
    return {"relu": 3, "yuv": 6}[head]


def answer_bias(head: str, rgb) -> np.ndarray:
    """Last-layer bias with which the head answers `rgb` (3 values >= 0) when the layer's weights are 0.

    yuv: the shadow mask is set to exactly 1 (sigmoid(s) = 0.9) and the colour to log1p(rgb) in YUV.
    """
    rgb = np.asarray(rgb, np.float64).reshape(3)
    if head == "relu":
        return rgb.astype(np.float32)
    yuv = RGB_TO_YUV @ np.log1p(np.maximum(rgb, 0.0))
    shadow = math.log((1.0 - SHADOW_FLOOR) / SHADOW_FLOOR)  # logit(0.9)
    return np.concatenate([yuv, np.full(3, shadow)]).astype(np.float32)
