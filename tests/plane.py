"""The analytic flat plane the training tests fit: a periodic albedo and a glossy lobe, known at
every level of detail."""

from __future__ import annotations

import numpy as np

from neumip.core import contract as C

PLANE_COLOR = np.array([0.9, 0.6, 0.3])
"""Base albedo of the analytic plane."""



def plane_mbtf(queries: np.ndarray) -> np.ndarray:
    """(N, 7) queries -> (N, 3) MBTF of a flat plane with a periodic albedo and a glossy lobe.

    albedo(u, v) = 0.6 + 0.3 sin(2 pi u) cos(2 pi v); a Gaussian footprint of std sigma scales the
    pattern by exp(-4 pi^2 sigma^2) (exact filtering). The glossy term peaks at wi = -wo (mirror).
    """
    u, v, sigma = (queries[:, i].astype(np.float64) for i in (C.U, C.V, C.SIGMA))
    damp = np.exp(-4 * np.pi**2 * np.maximum(sigma, 0) ** 2)
    albedo = 0.6 + 0.3 * damp * np.sin(2 * np.pi * u) * np.cos(2 * np.pi * v)
    hx = queries[:, C.WI_X] + queries[:, C.WO_X]
    hy = queries[:, C.WI_Y] + queries[:, C.WO_Y]
    gloss = 0.5 * np.exp(-(hx**2 + hy**2) / 0.08)
    rgb = albedo[:, None] * PLANE_COLOR[None, :] / np.pi + gloss[:, None]
    return rgb.astype(np.float32)
