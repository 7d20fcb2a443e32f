"""The classical base of a material with `MaterialConfig.base` (issue 25, lever 2): its maps, prefiltered
into a pyramid, and the microfacet BSDF the decoder corrects.

With a base the answer is ``base(maps, wi, wo) * exp(c) + a``: c (a log-scale factor per channel) and
a (an additive term per channel) are the decoder's outputs, whose last layer starts at zero, so an
untrained material answers the base. The base is the principled BSDF the ground truth's maps drive
(the classical material C of the report), evaluated on a pyramid of its maps so that a coarse level
answers a prefiltered version of it:

====  =======================================================================================
 0-2  diffuse colour: base colour x (1 - metallic)
 3-5  specular F0: 0.08 specular x (1 - metallic) + base colour x metallic
 6-7  the mean slopes dh/du, dh/dv of the height (tile units), the normal map's
 8    alpha^2 = roughness^4, plus the slopes' variance within the texel (LEAN mapping: a texel
      over bumps answers a wider lobe, not a flatter one)
 9-   sin of the horizon's elevation towards each of BASE_HORIZONS azimuths (`maps.horizon_angles`,
      averaged over the texel): the height field's own shadows, which C lacks
====  =======================================================================================

Each level is the area average of the finest one's colour channels and of the height's slopes and their
squares. The BSDF, on the normal n = normalize(-dh/du, -dh/dv, 1), under unit irradiance on the
reference plane (`contract`)::

    base = (kd / pi * max(n.wi, 0) + D G1(n.wi) G1(n.wo) F / (4 max(n.wo, BASE_COS_FLOOR))) * S(g) / max(wi_z, BASE_WI_FLOOR)

times the visibility V(wi) of the light above the horizon (horizon mapping: the sine of the horizon's
elevation towards wi's azimuth, interpolated between its two nearest azimuths by weights max(cos(phi -
phi_j) - cos(45 deg), 0), normalised; V = clamp((wi_z - sin(horizon)) / BASE_SHADOW_SOFTNESS + 1/2, 0, 1)),
with the GGX distribution D, Smith's G1 and Schlick's Fresnel on h.wi, and the shadow terminator's
softening of a normal map (Chiang, Li and Burley 2019): g = min(1, wi_z / max(n.wi n_z, BASE_COS_FLOOR)),
S(g) = g + g^2 - g^3, on the terms `MaterialConfig.terminator` names (both by default; the specular lobe only;
none). Without it a bump's side facing a grazing light answers up to 1 / wi_z times its flat value (the
report's 85-degree light: 11x), as a lit face of the real geometry does; the horizon's visibility is then its
only shadow. `base_maps` is numpy; `base_answer`
torch; `export_base.base_answer` writes the same formula into the graph.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from neumip.core import contract as C
from neumip.core.config import (BASE_ALPHA2_FLOOR, BASE_AZIMUTH_FLOOR, BASE_AZIMUTH_KERNEL, BASE_AZIMUTHS,
                                BASE_CHANNELS, BASE_COS_FLOOR, BASE_HORIZONS, BASE_LOG_CEILING, BASE_SHADOW_SOFTNESS,
                                BASE_WI_FLOOR, HALF_FLOOR, MaterialConfig)

from neumip.training.model.maps import finest_statistics, horizon_angles, resize
from neumip.groundtruth.description import Microgeometry

DIELECTRIC_F0 = 0.08
"""Mitsuba's principled BSDF: a dielectric's F0 is 0.08 x specular (0.04 at the default 0.5)."""


def base_resolution(geo: Microgeometry) -> int:
    """The base pyramid's finest resolution for `geo`: its largest map's side, up to a power of two."""
    if geo.bsdf is not None:
        raise ValueError("a base needs the principled maps; this material has a homogeneous [bsdf]")
    side = max(a.shape[0] for a in (geo.height, geo.base_color, geo.roughness, geo.metallic))
    return 1 << max(0, math.ceil(math.log2(side)))


def base_maps(geo: Microgeometry, resolution: int, energy: bool = False) -> list[np.ndarray]:
    """The base's pyramid for `geo` with a finest level of `resolution` texels per side: one
    (S, S, BASE_CHANNELS) float32 array per level, finest first (the table in the module docstring); `energy`:
    its coarse levels rescaled by `keep_energy` (`MaterialConfig.base_energy`)."""
    if geo.bsdf is not None:
        raise ValueError("a base needs the principled maps; this material has a homogeneous [bsdf]")
    colour = resize(np.broadcast_to(geo.base_color, geo.base_color.shape[:2] + (3,)), resolution).astype(np.float64)
    metal = resize(geo.metallic, resolution).astype(np.float64)[..., None]
    rough = resize(geo.roughness, resolution).astype(np.float64)
    finest = np.concatenate([colour * (1 - metal), DIELECTRIC_F0 * geo.specular * (1 - metal) + colour * metal,
                             (rough**4)[..., None]], axis=2)  # (R, R, 7): kd, F0, alpha^2
    stats = finest_statistics(geo)[..., 1:6]  # slopes and their raw second moments
    horizons = np.sin(horizon_angles(geo.height.astype(np.float64), BASE_HORIZONS) * (np.pi / 2))
    out = []
    for size in MaterialConfig(resolution=resolution).level_sizes():
        colours = resize(finest, size).astype(np.float64)
        m = resize(stats, size).astype(np.float64)
        sx, sy = m[..., 0], m[..., 1]
        variance = np.maximum(m[..., 2] - sx * sx, 0.0) + np.maximum(m[..., 3] - sy * sy, 0.0)
        level = np.concatenate([colours[..., :6], sx[..., None], sy[..., None], (colours[..., 6] + variance)[..., None],
                                resize(horizons, size)], axis=2)
        out.append(level.astype(np.float32))
    assert out[0].shape[2] == BASE_CHANNELS
    return keep_energy(out) if energy else out


ENERGY_PAIRS = 8
"""Direction pairs per finest texel on which `keep_energy` compares a coarse texel with its finest texels."""
ENERGY_MAX_ZENITH_DEG = 85.0
"""Their largest zenith angle (uniform in solid angle up to it: the report's views and lights lie within)."""


def energy_pairs(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """`n` direction pairs (wi, wo), each (n, 2) float64, independent and uniform in solid angle up to
    `ENERGY_MAX_ZENITH_DEG`."""
    rng = np.random.default_rng(seed)
    cos = 1.0 - (1.0 - math.cos(math.radians(ENERGY_MAX_ZENITH_DEG))) * rng.random((2, n))
    phi = 2 * math.pi * rng.random((2, n))
    r = np.sqrt(1.0 - cos * cos)
    return tuple(torch.from_numpy(np.stack([r[k] * np.cos(phi[k]), r[k] * np.sin(phi[k])], 1)) for k in (0, 1))


def keep_energy(levels: list[np.ndarray], pairs: int = ENERGY_PAIRS, seed: int = 0) -> list[np.ndarray]:
    """The base pyramid `levels` (finest first) with each coarser texel's colour and F0 channels scaled by s =
    sum of its finest texels' answers / sum of its own answers (luminance, the same `pairs` random direction pairs
    per finest texel, uniform in solid angle up to `ENERGY_MAX_ZENITH_DEG`, no terminator softening), so that its
    answer keeps their mean energy. Scaling F0 scales the specular term but for Schlick's grazing part."""
    res = levels[0].shape[0]
    wi, wo = energy_pairs(res * res * pairs, seed)
    luminance = torch.tensor(C.LUMINANCE, dtype=torch.float64)

    def answers(level: np.ndarray) -> torch.Tensor:
        """(res, res) sums of each finest texel's pairs, answered by `level`'s texel that covers it."""
        f = res // level.shape[0]
        cover = np.repeat(np.repeat(level.astype(np.float64), f, 0), f, 1).reshape(res * res, -1)
        rows = torch.from_numpy(cover).repeat_interleave(pairs, 0)
        return (base_answer(rows, wi, wo, "none") @ luminance).reshape(res, res, pairs).sum(2)

    fine = answers(levels[0]).numpy()
    out = [levels[0]]
    for level in levels[1:]:
        size, f = level.shape[0], res // level.shape[0]
        want = fine.reshape(size, f, size, f).sum((1, 3))
        have = answers(level).numpy().reshape(size, f, size, f).sum((1, 3))
        scale = np.where(have > 0, want / np.maximum(have, 1e-30), 1.0)
        scaled = level.astype(np.float64)
        scaled[..., :6] *= scale[..., None]
        out.append(scaled.astype(np.float32))
    return out


def lift(w: torch.Tensor) -> torch.Tensor:
    """(N, 2) x, y of unit vectors -> (N, 3) with z = sqrt(max(1 - x^2 - y^2, 0))."""
    return torch.cat([w, torch.sqrt(torch.clamp(1.0 - (w * w).sum(1, keepdim=True), min=0.0))], dim=1)


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(1, keepdim=True)


def half_direction(wi3: torch.Tensor, wo3: torch.Tensor) -> torch.Tensor:
    """(N, 3) unit wi, wo -> (N, 3) h = (wi + wo) / sqrt(max(|wi + wo|^2, HALF_FLOOR))."""
    total = wi3 + wo3
    return total / torch.sqrt(torch.clamp(_dot(total, total), min=HALF_FLOOR))


def smith_g1(cos: torch.Tensor, alpha2: torch.Tensor) -> torch.Tensor:
    """Smith's masking of GGX: 2 c / (c + sqrt(alpha^2 + (1 - alpha^2) c^2)), for c >= 0."""
    return 2.0 * cos / (cos + torch.sqrt(alpha2 + (1.0 - alpha2) * cos * cos))


def base_normal(features: torch.Tensor) -> torch.Tensor:
    """(N, BASE_CHANNELS) looked-up base maps -> (N, 3) the normal normalize(-dh/du, -dh/dv, 1) of their mean slopes."""
    slopes = features[:, 6:8]
    n = torch.cat([-slopes, torch.ones_like(slopes[:, :1])], dim=1)
    return n / torch.sqrt(_dot(n, n))


def base_answer(features: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, terminator: str = "all",
                lit: torch.Tensor | None = None) -> torch.Tensor:
    """(N, BASE_CHANNELS) looked-up base maps, (N, 2) wi, wo -> (N, 3) the base's answer (module docstring); S(g)
    multiplies the terms `terminator` names (`MaterialConfig.terminator`: "all", "specular", "none"). `lit`: the
    light's visibility where the decoder's input computed it (`light_visibility`), else computed here."""
    wi3, wo3 = lift(wi), lift(wo)
    n = base_normal(features)
    h = half_direction(wi3, wo3)
    alpha2 = torch.clamp(features[:, 8:9], min=BASE_ALPHA2_FLOOR)
    cos_i = torch.clamp(_dot(n, wi3), min=0.0)
    cos_o = torch.clamp(_dot(n, wo3), min=0.0)
    cos_h = torch.clamp(_dot(n, h), min=0.0)
    d = cos_h * cos_h * (alpha2 - 1.0) + 1.0
    distribution = alpha2 / (math.pi * d * d)
    f0 = features[:, 3:6]
    schlick = (1.0 - torch.clamp(_dot(h, wi3), min=0.0, max=1.0)) ** 5
    fresnel = f0 + (1.0 - f0) * schlick
    specular = distribution * smith_g1(cos_i, alpha2) * smith_g1(cos_o, alpha2) * fresnel / (
        4.0 * torch.clamp(cos_o, min=BASE_COS_FLOOR))
    diffuse = features[:, 0:3] * (cos_i / math.pi)
    wi_z = wi3[:, 2:3]
    g = torch.clamp(wi_z / torch.clamp(cos_i * n[:, 2:3], min=BASE_COS_FLOOR), max=1.0)
    soften = g * (1.0 + g - g * g)
    if terminator == "all":
        reflected = (diffuse + specular) * soften
    elif terminator == "specular":
        reflected = diffuse + specular * soften
    else:
        reflected = diffuse + specular
    lit = visibility(features[:, 9:], wi, wi_z) if lit is None else lit
    return reflected * lit / torch.clamp(wi_z, min=BASE_WI_FLOOR)


def light_visibility(features: torch.Tensor, wi: torch.Tensor) -> torch.Tensor:
    """(N, BASE_CHANNELS) looked-up base maps, (N, 2) wi -> (N, 1) the base's visibility of the light (the decoder's
    input with `MaterialConfig.visibility_input`)."""
    return visibility(features[:, 9:], wi, lift(wi)[:, 2:3])


def frame_inputs(features: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """(N, BASE_CHANNELS) looked-up base maps, (N, 2) wi, wo -> (N, 6) wi and wo in the shading frame of the base's
    normal n (`MaterialConfig.local_frame`): (w.t, w.b, w.n) each, the tangents those of Frisvad's basis (Duff et
    al. 2017, n_z > 0 here): with a = 1 / (1 + n_z), t = (1 - n_x^2 a, -n_x n_y a, -n_x), b = (-n_x n_y a,
    1 - n_y^2 a, -n_y); a flat texel's frame is the plane's."""
    n = base_normal(features)
    nx, ny, nz = n[:, 0:1], n[:, 1:2], n[:, 2:3]
    a = 1.0 / (1.0 + nz)
    cross = -nx * ny * a
    t = torch.cat([1.0 - nx * nx * a, cross, -nx], dim=1)
    b = torch.cat([cross, 1.0 - ny * ny * a, -ny], dim=1)
    wi3, wo3 = lift(wi), lift(wo)
    return torch.cat([_dot(wi3, t), _dot(wi3, b), _dot(wi3, n), _dot(wo3, t), _dot(wo3, b), _dot(wo3, n)], dim=1)


def visibility(horizons: torch.Tensor, wi: torch.Tensor, wi_z: torch.Tensor) -> torch.Tensor:
    """(N, BASE_HORIZONS) sines of the horizon, (N, 2) wi, (N, 1) its z -> (N, 1) the light's visibility."""
    r = torch.sqrt(torch.clamp((wi * wi).sum(1, keepdim=True), min=BASE_AZIMUTH_FLOOR * BASE_AZIMUTH_FLOOR))
    azimuths = torch.tensor(BASE_AZIMUTHS, dtype=wi.dtype, device=wi.device).T  # (2, BASE_HORIZONS)
    kernel = torch.clamp(wi @ azimuths / r - BASE_AZIMUTH_KERNEL, min=0.0)
    weights = kernel / torch.clamp(kernel.sum(1, keepdim=True), min=BASE_AZIMUTH_FLOOR)
    horizon = (weights * horizons).sum(1, keepdim=True)
    return torch.clamp((wi_z - horizon) / BASE_SHADOW_SOFTNESS + 0.5, min=0.0, max=1.0)


def corrected(base: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """(N, 3) base answers, (N, BASE_OUTPUTS) decoder outputs -> (N, 3) base * exp(c) + a (before the ReLU)."""
    return base * torch.exp(torch.clamp(out[:, :3], max=BASE_LOG_CEILING)) + out[:, 3:]
