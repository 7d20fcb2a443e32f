"""The sampling lobe of a material made from maps: where a renderer should sample its directions.

A neural material is sampled as a mixture of the cosine and one GGX lobe about the mirror direction
(`contract.SamplingLobe`, `client.mitsuba.bsdf`). The lobe comes from the maps the material was
made from: each texel's principled lobe (``alpha = roughness^2``, Mitsuba's convention) tilted by its
height slope, which at the macro normal widens it to about ``sqrt(alpha^2 + |grad h|^2)``.

A GGX lobe wider than ``SHARP_ALPHA`` is no peakier than the cosine it would be mixed with (its pdf at
the mirror direction, ``1 / (4 pi alpha^2)``, falls below the cosine's ``1 / pi`` at alpha 0.5), so only
the texels sharper than that count: the lobe is sampled with probability ``min(MAX_WEIGHT, their
share)``, with their median width. A material with no sharp texel (rough stone, foam, cloth) keeps
the cosine alone, as does one whose sharp share is below ``MIN_WEIGHT``. The lobe's energy (the
specular's share) is not weighed: a smooth dielectric with a 4 % specular still gets its lobe, which
under diffuse light costs up to 2x the cosine's noise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from neumip.core.contract import SamplingLobe

from neumip.groundtruth.description import Microgeometry
from neumip.groundtruth.images import resample_periodic
from neumip.groundtruth.mesh import height_gradient

SHARP_ALPHA = 0.5
"""Widest lobe (GGX alpha at the macro normal) that is peakier than the cosine."""
MAX_WEIGHT = 0.5
"""Largest probability of sampling the lobe: the cosine keeps at least as much (a defensive mixture)."""
MIN_WEIGHT = 0.05
"""A sharp share below this declares no lobe: the cosine alone."""
MIN_ALPHA = 0.02
"""Narrowest lobe sampled: a mirror-like texel's lobe is still sampled as this wide."""
DEFAULT_BSDF_ALPHA = 0.1
"""Alpha of a Mitsuba ``rough*`` BSDF that gives none (Mitsuba's own default)."""


def sampling_lobe(geo: Microgeometry) -> SamplingLobe | None:
    """The lobe for a material of these maps, or None where the cosine alone is as good.

    A material of one homogeneous Mitsuba BSDF (``[bsdf]``) in place of the principled maps has that
    BSDF's alpha everywhere (``rough*`` without one: `DEFAULT_BSDF_ALPHA`; a smooth ``conductor`` or
    ``plastic``: `MIN_ALPHA`; a diffuse one: no lobe), tilted by the height as the maps are. A roughness
    map of another size than the height is resampled to it.
    """
    height = np.asarray(geo.height, np.float64)
    tilt2 = (height_gradient(height) ** 2).sum(-1) if height.shape[0] > 1 else np.zeros((1, 1))
    if geo.bsdf is not None:
        alpha = _bsdf_alpha(geo.bsdf)
        if alpha is None:
            return None
        alpha2 = np.full(tilt2.shape, alpha**2)
    else:
        roughness = np.asarray(geo.roughness, np.float64)
        if roughness.shape != (1, 1) and tilt2.shape != (1, 1) and roughness.shape != tilt2.shape:
            roughness = resample_periodic(roughness, tilt2.shape[0]).astype(np.float64)
        alpha2, tilt2 = np.broadcast_arrays(roughness**4, tilt2)
    width = np.sqrt(alpha2 + tilt2)
    sharp = width[width < SHARP_ALPHA]  # (NaN texels are not sharp)
    weight = min(MAX_WEIGHT, sharp.size / width.size)
    if weight < MIN_WEIGHT:
        return None
    return SamplingLobe(round(max(MIN_ALPHA, float(np.median(sharp))), 4), round(weight, 4))


def _bsdf_alpha(bsdf: dict) -> float | None:
    """GGX alpha of a homogeneous Mitsuba BSDF dictionary (a ``twosided`` one's inner BSDF), None for
    one without a glossy reflection (diffuse, or unknown)."""
    while bsdf.get("type") in ("twosided", "mask") and isinstance(bsdf.get("bsdf"), dict):
        bsdf = bsdf["bsdf"]
    kind = str(bsdf.get("type", ""))
    if kind.startswith("rough"):
        alpha = bsdf.get("alpha", DEFAULT_BSDF_ALPHA)
        return max(MIN_ALPHA, float(alpha)) if isinstance(alpha, (int, float)) and alpha > 0 else None
    return MIN_ALPHA if kind in ("conductor", "plastic") else None


def material_lobe(name_or_toml: str | Path) -> SamplingLobe | None:
    """`sampling_lobe` of a library material or description file (its maps built or read)."""
    from neumip.groundtruth.description import find_description, resolve

    return sampling_lobe(resolve(find_description(name_or_toml)))
