"""Microgeometry from arrays: a height map with constant colour, roughness and metallic."""

from __future__ import annotations

import numpy as np

from neumip.groundtruth.description import Microgeometry


def geometry(height: np.ndarray, colour=(0.6, 0.4, 0.2), roughness=0.5, metallic=0.0, bsdf=None) -> Microgeometry:
    size = height.shape[0]
    return Microgeometry(height=height.astype(np.float32),
                         base_color=np.broadcast_to(np.asarray(colour, np.float32), (size, size, 3)).copy(),
                         roughness=np.full((size, size), roughness, np.float32),
                         metallic=np.full((size, size), metallic, np.float32), specular=0.5, bsdf=bsdf,
                         normals="smooth")
