"""The sampling lobe of a material made from maps: where a renderer should sample its directions.

A neural material is sampled as a mixture of the cosine and one GGX lobe about the mirror direction
(`contract.SamplingLobe`, `client.mitsuba.bsdf`). The lobe comes from the maps the material was
made from: each texel's principled lobe (``alpha = roughness^2``, Mitsuba's convention) tilted by its
height slope, which at the macro normal widens it to about ``sqrt(alpha^2 + |grad h|^2)``.

A GGX lobe wider than ``SHARP_ALPHA`` is no peakier than the cosine it would be mixed with (its pdf at
the mirror direction, ``1 / (4 pi alpha^2)``, falls below the cosine's ``1 / pi`` at alpha 0.5), so only
the texels sharper than that count: the lobe is sampled with probability ``min(MAX_WEIGHT, their
share)``, with their median width. A material with no sharp texel (rough stone, foam, cloth) keeps
the cosine alone. Measured in `benchmarks/results/sampling.txt`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from neumip.core.contract import SamplingLobe

from .description import Microgeometry
from .mesh import height_gradient

SHARP_ALPHA = 0.5
"""Widest lobe (GGX alpha at the macro normal) that is peakier than the cosine."""
MAX_WEIGHT = 0.5
"""Largest probability of sampling the lobe: the cosine keeps at least as much (a defensive mixture)."""
MIN_ALPHA = 0.02
"""Narrowest lobe sampled: a mirror-like texel's lobe is still sampled as this wide."""


def sampling_lobe(geo: Microgeometry) -> SamplingLobe | None:
    """The lobe for a material of these maps, or None where the cosine alone is as good.

    A material of one homogeneous Mitsuba BSDF (``[bsdf]``) in place of the principled maps has a lobe
    where that BSDF gives a numeric ``alpha`` sharper than ``SHARP_ALPHA`` (a rough conductor or
    plastic), sampled with probability ``MAX_WEIGHT``; a diffuse one has none.
    """
    if geo.bsdf is not None:
        alpha = geo.bsdf.get("alpha")
        if isinstance(alpha, (int, float)) and 0 < alpha < SHARP_ALPHA:
            return SamplingLobe(max(MIN_ALPHA, float(alpha)), MAX_WEIGHT)
        return None
    height = np.asarray(geo.height, np.float64)
    tilt2 = (height_gradient(height) ** 2).sum(-1) if height.shape[0] > 1 else np.zeros((1, 1))
    roughness, tilt2 = np.broadcast_arrays(np.asarray(geo.roughness, np.float64), tilt2)
    width = np.sqrt(roughness**4 + tilt2)
    sharp = width[width < SHARP_ALPHA]
    if not sharp.size:
        return None
    weight = min(MAX_WEIGHT, sharp.size / width.size)
    return SamplingLobe(round(max(MIN_ALPHA, float(np.median(sharp))), 4), round(weight, 4))


def material_lobe(name_or_toml: str | Path) -> SamplingLobe | None:
    """`sampling_lobe` of a library material or description file (its maps built or read)."""
    from .description import find_description, resolve

    return sampling_lobe(resolve(find_description(name_or_toml)))
