"""Stability at the edges of the query domain, and a render out to the horizon.

Query sweeps (pure numpy around an evaluator), each averaged over the same random positions:
- grazing: the view's zenith from 0 to 89.9 degrees (light at 45 degrees);
- sigma: from 1e-4 finest texels to 100 tiles, log-spaced; the largest relative step between
  neighbouring sigmas (where levels are blended) is the figure of merit;
- position: ``u + k`` for ``k`` up to 1e6 tiles against ``u`` (periodicity and float32 rounding),
  and the step across the tile seam;
- sub-texel: ``u`` moved across one finest texel at sigma 0 (close-ups below one texel).
"""

from __future__ import annotations

import math

import numpy as np

from neumip.core import contract as C

POSITIONS = 64
"""Random positions each sweep point is averaged over."""


def _positions(n: int = POSITIONS) -> np.ndarray:
    return np.random.default_rng(7).uniform(0, 1, (n, 2))


def _queries(uv: np.ndarray, sigma, wi: tuple[float, float], wo) -> np.ndarray:
    n = uv.shape[0]
    wo = np.broadcast_to(np.asarray(wo, np.float64), (n, 2))
    return C.pack_queries(uv[:, 0], uv[:, 1], np.broadcast_to(sigma, (n,)), np.tile(wi, (n, 1)), wo)


def _mean_lum(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array(C.LUMINANCE)


def grazing_sweep(evaluate, points: int) -> dict:
    """Mean luminance against the view zenith (0..89.9 degrees), footprint 1 finest texel of a 64^2 level."""
    uv = _positions()
    wi = (math.sin(math.radians(45)), 0.0)
    angles = np.linspace(0.0, 89.9, points)
    values = []
    for a in angles:
        rgb = evaluate(_queries(uv, 1 / 64, wi, (0.0, math.sin(math.radians(a)))))
        values.append(float(_mean_lum(rgb).mean()))
    values = np.array(values)
    at80 = values[np.argmin(np.abs(angles - 80))]
    return {"angle_deg": angles.tolist(), "mean": values.tolist(), "finite": bool(np.all(np.isfinite(values))),
            "ratio_89_9_to_80": float(values[-1] / at80) if at80 > 0 else None,
            "max_over_min": float(values.max() / max(values.min(), 1e-12))}


def sigma_sweep(evaluate, points: int, resolution: int) -> dict:
    """Mean luminance against sigma; the largest relative step between neighbouring sigmas."""
    uv = _positions()
    wi, wo = (0.5, 0.2), (-0.3, 0.4)
    sigmas = np.logspace(math.log10(1e-4 / resolution), 2, points * 2)
    values = np.array([float(_mean_lum(evaluate(_queries(uv, s, wi, wo))).mean()) for s in sigmas])
    steps = np.abs(np.diff(values)) / np.maximum(values[:-1], 1e-12)
    worst = int(np.argmax(steps))
    level = C.level_of_detail(np.array([sigmas[worst]]), resolution)[0]
    return {"sigma": sigmas.tolist(), "mean": values.tolist(), "largest_step": float(steps[worst]),
            "at_sigma": float(sigmas[worst]), "at_level": float(level),
            "median_step": float(np.median(steps))}


def position_sweep(evaluate) -> dict:
    """Largest relative change of the answer when u, v move by k whole tiles (k up to 1e6), and across the seam."""
    uv = _positions()
    wi, wo = (0.5, 0.2), (-0.3, 0.4)
    base = evaluate(_queries(uv, 0.0, wi, wo))
    scale = max(float(np.abs(base).mean()), 1e-12)
    shifts = [0, 1, 10, 100, 1e3, 1e4, 1e5, 1e6]
    worst = []
    for k in shifts:
        moved = evaluate(_queries(uv + k, 0.0, wi, wo))
        worst.append(float(np.abs(moved - base).max() / scale))
    eps = 1e-5
    seam_y = np.random.default_rng(3).uniform(0, 1, POSITIONS)
    left = evaluate(_queries(np.stack([np.full(POSITIONS, 1 - eps), seam_y], 1), 0.0, wi, wo))
    right = evaluate(_queries(np.stack([np.full(POSITIONS, eps), seam_y], 1), 0.0, wi, wo))
    inner_l = evaluate(_queries(np.stack([np.full(POSITIONS, 0.5 - eps), seam_y], 1), 0.0, wi, wo))
    inner_r = evaluate(_queries(np.stack([np.full(POSITIONS, 0.5 + eps), seam_y], 1), 0.0, wi, wo))
    return {"shift_tiles": shifts, "max_rel_change": worst,
            "seam_step": float(np.abs(left - right).max() / scale),
            "interior_step": float(np.abs(inner_l - inner_r).max() / scale)}


SUBTEXEL_RANGE_FLOOR = 0.01
"""The sub-texel sweep's range is at least this fraction of its mean luminance, so that a texel the model answers
flat (steps of rounding over a range of rounding) reads near 0, not near 1."""


def subtexel_sweep(evaluate, points: int, resolution: int) -> dict:
    """Luminance as u crosses one finest texel at sigma 0: largest step between neighbours / the texel's range, the
    range at least `SUBTEXEL_RANGE_FLOOR` of the mean (a texel the model answers flat has no steps to speak of)."""
    v = 0.37
    us = 0.5 + np.linspace(0, 1, points) / resolution
    rgb = evaluate(_queries(np.stack([us, np.full(points, v)], 1), 0.0, (0.5, 0.2), (-0.3, 0.4)))
    lum = _mean_lum(rgb)
    span = max(float(lum.max() - lum.min()), SUBTEXEL_RANGE_FLOOR * float(np.abs(lum).mean()), 1e-12)
    return {"u": us.tolist(), "luminance": lum.tolist(),
            "largest_step_over_range": float(np.abs(np.diff(lum)).max() / span)}


def sweeps(evaluator, name: str, points: int, resolution: int) -> dict:
    def evaluate(q):
        return evaluator.evaluate(name, np.ascontiguousarray(q, np.float32)).astype(np.float64)

    return {"grazing": grazing_sweep(evaluate, points), "sigma": sigma_sweep(evaluate, points, resolution),
            "position": position_sweep(evaluate), "subtexel": subtexel_sweep(evaluate, points, resolution)}


# --- a plane out to the horizon ---------------------------------------------------------------------


def horizon_scene(mi, film, material_bsdf, integrator: str, theta: float = 80.0, fov: float = 24.0,
                  height: float = 1.0) -> dict:
    """A huge plane seen from ``height`` tiles above it, looking ``theta`` degrees from the normal:
    the footprint grows from a few texels at the bottom of the image to whole tiles at the horizon."""
    from neumip.report.views import ENV_RADIANCE, HORIZON_SUN_DIRECTION, HORIZON_SUN_IRRADIANCE

    t = math.radians(theta)
    half = 1 << 15
    bsdf = material_bsdf(2.0 * half)
    return {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": 5},
        "sensor": {
            "type": "perspective", "fov": fov, "fov_axis": "y",
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, height], target=[0, math.tan(t) * height, 0],
                                                       up=[0, 0, 1]),
            "film": {"type": "hdrfilm", "width": film.width, "height": film.height, "pixel_format": "rgb"},
        },
        "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([half, half, 1.0]), "bsdf": bsdf},
        "sun": {"type": "directional", "direction": list(HORIZON_SUN_DIRECTION),
                "irradiance": {"type": "rgb", "value": HORIZON_SUN_IRRADIANCE}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": ENV_RADIANCE}},
    }


def row_banding(image: np.ndarray) -> dict:
    """Bands or pops between levels show as jumps in the rows' mean luminance: the largest relative
    jump between neighbouring rows (over the plane's rows), against the median jump."""
    lum = image[..., :3] @ np.array(C.LUMINANCE)
    rows = lum.mean(axis=1)
    keep = rows > 0.05 * np.median(rows)
    rows = rows[keep] if keep.sum() > 4 else rows
    jumps = np.abs(np.diff(rows)) / np.maximum(rows[1:], 1e-12)
    return {"row_mean": rows.tolist(), "largest_jump": float(jumps.max()), "median_jump": float(np.median(jumps))}
