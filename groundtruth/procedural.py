"""Procedural periodic microgeometry: height and reflectance maps of one tile, pure numpy.

Every generator is ``generator(resolution, rng, **params) -> dict`` returning, for an
``R x R`` tile (``R = resolution``, ``arr[row, col]`` at ``(u, v) = ((col + .5) / R, (row + .5) / R)``):

- ``height``     (R, R) float32, unitless (the description's ``height_scale`` turns it into tile units)
- ``base_color`` (R, R, 3) float32, linear RGB in [0, 1]
- ``roughness``  (R, R) float32 in [0, 1]
- ``metallic``   (R, R) float32 in [0, 1]

All maps tile seamlessly (period 1 in u and v). Parameters are keyword arguments with defaults; a
material description's ``[procedural]`` table passes them through.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

Maps = dict[str, np.ndarray]


# --- periodic building blocks ----------------------------------------------------------------------


def grid(resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """(R, R) u and v coordinates of the texel centres of one tile."""
    c = (np.arange(resolution, dtype=np.float64) + 0.5) / resolution
    u, v = np.meshgrid(c, c)
    return u, v


def fractal_noise(resolution: int, rng: np.random.Generator, slope: float = 2.0, lowest: int = 1) -> np.ndarray:
    """(R, R) periodic noise with power spectrum ~ 1/f^slope (f >= lowest cycles per tile), in [0, 1]."""
    f = np.fft.fftfreq(resolution) * resolution
    freq = np.hypot(f[:, None], f[None, :])
    amplitude = np.where(freq >= lowest, np.maximum(freq, 1e-9) ** (-slope / 2), 0.0)
    spectrum = amplitude * np.fft.fft2(rng.standard_normal((resolution, resolution)))
    return _normalise(np.real(np.fft.ifft2(spectrum)))


def voronoi(resolution: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Periodic Voronoi of (P, 2) points in [0, 1)^2: (R, R) distance to the nearest and second
    nearest point, and (R, R) index of the nearest."""
    u, v = grid(resolution)
    f1 = np.full(u.shape, np.inf)
    f2 = np.full(u.shape, np.inf)
    nearest = np.zeros(u.shape, dtype=np.int64)
    for index, (px, py) in enumerate(points):
        dx = np.abs(u - px)
        dy = np.abs(v - py)
        d = np.hypot(np.minimum(dx, 1 - dx), np.minimum(dy, 1 - dy))  # wrap-around distance
        closer = d < f1
        f2 = np.where(closer, f1, np.minimum(f2, d))
        f1 = np.where(closer, d, f1)
        nearest = np.where(closer, index, nearest)
    return f1, f2, nearest


def relaxed_points(count: int, rng: np.random.Generator, iterations: int = 2) -> np.ndarray:
    """(count, 2) well-spread periodic points (Lloyd relaxation on a coarse grid)."""
    points = rng.random((count, 2))
    for _ in range(iterations):
        _, _, nearest = voronoi(64, points)
        u, v = grid(64)
        for i in range(count):
            mask = nearest == i
            if mask.any():  # circular mean keeps the wrap-around
                for axis, coord in enumerate((u, v)):
                    angle = 2 * np.pi * coord[mask]
                    points[i, axis] = (np.arctan2(np.sin(angle).mean(), np.cos(angle).mean()) / (2 * np.pi)) % 1
    return points


def smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0, 1)
    return t * t * (3 - 2 * t)


def _normalise(x: np.ndarray) -> np.ndarray:
    lo, hi = x.min(), x.max()
    return ((x - lo) / (hi - lo if hi > lo else 1.0)).astype(np.float64)


def _mix(a: tuple[float, ...], b: tuple[float, ...], t: np.ndarray) -> np.ndarray:
    """(R, R, 3) linear blend of two RGB colours by (R, R) weight t."""
    a_, b_ = np.asarray(a), np.asarray(b)
    return a_ + (b_ - a_) * t[:, :, None]


def _maps(height, base_color, roughness, metallic=0.0) -> Maps:
    shape = height.shape
    return {
        "height": height.astype(np.float32),
        "base_color": np.clip(base_color, 0, 1).astype(np.float32),
        "roughness": np.clip(np.broadcast_to(roughness, shape), 0, 1).astype(np.float32),
        "metallic": np.clip(np.broadcast_to(metallic, shape), 0, 1).astype(np.float32),
    }


# --- generators ------------------------------------------------------------------------------------


def yarn(
    resolution: int,
    rng: np.random.Generator,
    threads: int = 6,
    width: float = 0.42,
    undulation: float = 0.35,
    plies: int = 3,
    twist: float = 2.5,
    warp_color: tuple[float, float, float] = (0.45, 0.08, 0.06),
    weft_color: tuple[float, float, float] = (0.75, 0.62, 0.35),
) -> Maps:
    """Plain-woven fabric: `threads` round, twisted yarns per tile each way, going over and under.

    width: yarn half-width as a fraction of the yarn spacing; undulation: over/under amplitude
    relative to the yarn radius; plies/twist: fibre-ply stripes per yarn and their slant.
    """
    u, v = grid(resolution)
    layers = []
    for along, across, sign, colour in ((v, u, 1.0, warp_color), (u, v, -1.0, weft_color)):
        index = np.floor(across * threads)
        offset = across * threads - index - 0.5  # in [-0.5, 0.5) yarn spacings
        profile = np.sqrt(np.clip(1 - (offset / width) ** 2, 0, 1))  # round cross-section
        wave = sign * undulation * np.cos(np.pi * (along * threads - 0.5 - index))
        ply = 0.5 + 0.5 * np.cos(2 * np.pi * (plies * offset / (2 * width) + twist * along * threads))
        surface = np.where(profile > 0, profile * (0.85 + 0.15 * ply) + wave, -np.inf)
        tint = np.asarray(colour) * (0.7 + 0.3 * ply)[:, :, None]
        layers.append((surface, tint, ply))
    (warp, warp_rgb, warp_ply), (weft, weft_rgb, weft_ply) = layers
    top = warp >= weft
    floor = -undulation - 0.2
    height = np.maximum(np.maximum(warp, weft), floor)
    gap = np.isinf(np.maximum(warp, weft))
    colour = np.where(top[:, :, None], warp_rgb, weft_rgb)
    colour = np.where(gap[:, :, None], 0.1 * np.asarray(weft_color), colour)
    fuzz = fractal_noise(resolution, rng, slope=1.0, lowest=threads)
    roughness = 0.65 + 0.25 * fuzz - 0.1 * np.where(top, warp_ply, weft_ply)
    return _maps(_normalise(height), colour * (0.85 + 0.3 * fuzz[:, :, None]), roughness)


def rock(
    resolution: int,
    rng: np.random.Generator,
    slope: float = 3.2,
    ridges: float = 0.5,
    strata: int = 5,
    dark: tuple[float, float, float] = (0.12, 0.10, 0.08),
    light: tuple[float, float, float] = (0.55, 0.50, 0.44),
) -> Maps:
    """Rough rock / cliff face: fractal relief with sharp ridges and terraced strata.

    slope: spectral slope of the fractal (higher is smoother); ridges: blend towards ridged noise;
    strata: number of terrace steps over the height range.
    """
    base = fractal_noise(resolution, rng, slope=slope)
    ridged = 1 - np.abs(2 * fractal_noise(resolution, rng, slope=slope) - 1)
    height = (1 - ridges) * base + ridges * ridged
    terrace = np.floor(height * strata) / strata
    step = height * strata - np.floor(height * strata)
    height = _normalise(terrace + smoothstep(0.6, 1.0, step) / strata)
    detail = fractal_noise(resolution, rng, slope=1.2, lowest=4)
    colour = _mix(dark, light, np.clip(0.6 * height + 0.5 * detail - 0.1, 0, 1))
    return _maps(_normalise(height + 0.03 * detail), colour, 0.75 + 0.2 * detail)


def turtle(
    resolution: int,
    rng: np.random.Generator,
    plates: int = 10,
    groove: float = 0.025,
    dome: float = 0.6,
    rings: float = 40.0,
    amber: tuple[float, float, float] = (0.45, 0.22, 0.05),
    brown: tuple[float, float, float] = (0.09, 0.05, 0.02),
) -> Maps:
    """Turtle-shell plates (scutes): raised, domed polygonal plates separated by deep grooves.

    plates: plates per tile; groove: groove half-width in tile units; dome: plate curvature;
    rings: growth-ring frequency (per tile unit) in the colour.
    """
    centres = relaxed_points(plates, rng)
    f1, f2, nearest = voronoi(resolution, centres)
    edge = (f2 - f1) / 2  # distance to the plate boundary
    plate_size = np.sqrt(1.0 / plates)
    domed = 1 - dome * (f1 / plate_size) ** 2
    height = np.where(edge < groove, 0.0, 0.25 + 0.75 * domed * smoothstep(groove, 3 * groove, edge))
    shade = rng.random(plates)[nearest]
    growth = 0.5 + 0.5 * np.cos(2 * np.pi * rings * edge)
    colour = _mix(brown, amber, np.clip(0.4 * shade + 0.5 * growth * smoothstep(0, 0.1, edge), 0, 1))
    colour = np.where((edge < groove)[:, :, None], np.asarray(brown) * 0.5, colour)
    roughness = np.where(edge < groove, 0.8, 0.3 + 0.15 * growth)
    return _maps(_normalise(height), colour, roughness)


def foam(
    resolution: int,
    rng: np.random.Generator,
    pits: int = 60,
    radius: tuple[float, float] = (0.03, 0.08),
    depth: float = 1.0,
    colour: tuple[float, float, float] = (0.8, 0.76, 0.62),
) -> Maps:
    """Cellular foam: a bumpy surface riddled with round pits (open cells) of random size.

    pits: number of pits per tile; radius: (min, max) pit radius in tile units; depth: pit depth
    relative to its radius (1 = hemispherical).
    """
    u, v = grid(resolution)
    centres = relaxed_points(pits, rng, iterations=1)
    radii = rng.uniform(*radius, pits)
    surface = 0.15 * fractal_noise(resolution, rng, slope=1.5, lowest=2)
    cavity = np.zeros_like(u)
    for (px, py), r in zip(centres, radii):
        dx = np.abs(u - px)
        dy = np.abs(v - py)
        d2 = np.minimum(dx, 1 - dx) ** 2 + np.minimum(dy, 1 - dy) ** 2
        cavity = np.maximum(cavity, depth * np.sqrt(np.clip(r * r - d2, 0, None)) / radius[1])
    height = _normalise(surface - cavity)
    grime = fractal_noise(resolution, rng, slope=1.0, lowest=8)
    tint = np.asarray(colour) * (0.8 + 0.2 * grime)[:, :, None]
    tint = tint * (1 - 0.35 * (cavity > 0))[:, :, None]
    return _maps(height, tint, 0.85 + 0.1 * grime)


def flat(resolution: int, rng: np.random.Generator, colour: tuple[float, float, float] = (0.5, 0.5, 0.5)) -> Maps:
    """A flat plane of uniform colour (mostly useful with a homogeneous BSDF)."""
    shape = (resolution, resolution)
    return _maps(np.zeros(shape), np.broadcast_to(np.asarray(colour), (*shape, 3)), 1.0)


GENERATORS: dict[str, Callable[..., Maps]] = {
    "yarn": yarn,
    "rock": rock,
    "turtle": turtle,
    "foam": foam,
    "flat": flat,
}
"""Procedural generators by name (the ``generator`` key of a description's ``[procedural]`` table)."""
