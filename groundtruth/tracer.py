"""Path-traced MBTF queries through tiled microgeometry: a vectorized (drjit wavefront) estimator.

One sample of query ``(u, v, sigma, wi, wo)``:

1. jitter the aim point by a Gaussian of std ``sigma`` (the MBTF is the Gaussian-filtered BTF) and
   wrap it into the central tile (the material is periodic);
2. shoot a ray along ``-wo`` through the aim point on the reference plane ``z = 0`` (the top of the
   microgeometry, so nothing lies above it);
3. at every surface hit (up to ``max_depth``): next-event estimation towards the distant light from
   ``wi`` (a shadow ray, then the BSDF's ``eval``, which includes the cosine at the hit), then BSDF
   sampling for the next bounce. Hit points are shifted by whole tiles back into the central tile, so
   a modest margin of tiled geometry serves paths of any length.

The light delivers **unit irradiance on the reference plane**: its irradiance perpendicular to the
beam is ``1 / cos(theta_i)``, so a flat Lambertian plane of albedo ``a`` answers ``a / pi``.
The light is a pure directional light: it cannot be hit by sampled bounces, so no MIS is needed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from neumip.core import contract as C
from neumip.client.mitsuba.runtime import DEFAULT_VARIANT, import_mitsuba

from neumip.groundtruth.description import Microgeometry
from neumip.groundtruth.mesh import TilingConfig, query_scene

log = logging.getLogger(__name__)

PRIMARY_OFFSET = 1e-3
"""Height (tile units) above the reference plane where primary rays start."""

SIGMA_UNIFORM = 2.0
"""Footprint (tile units) from which the wrapped Gaussian is uniform: its first Fourier coefficient
is exp(-2 pi^2 sigma^2) < 1e-30."""


@dataclass
class TracerConfig:
    """Path tracing settings of the query estimator."""

    max_depth: int = 4
    """Surface interactions per path (1 = direct light only)."""
    lanes: int = 1 << 20
    """Samples traced together in one wavefront pass (memory grows with it: ~0.3 GB per million)."""
    min_cos_light: float = 1e-3
    """Floor on cos(theta_i) in the unit-irradiance factor 1 / cos(theta_i) (grazing lights)."""
    variant: str = DEFAULT_VARIANT
    """Mitsuba variant (a vectorized one: llvm_ad_rgb on CPU, cuda_ad_rgb on a GPU)."""

    def __post_init__(self) -> None:
        if self.max_depth < 1:
            raise ValueError(f"max_depth must be >= 1, got {self.max_depth}")
        if self.lanes < 1:
            raise ValueError(f"lanes must be >= 1, got {self.lanes}")


class QueryTracer:
    """Answers MBTF queries for one material; the scene is built once and reused for every call."""

    def __init__(self, geo: Microgeometry, config: TracerConfig | None = None, tiling: TilingConfig | None = None):
        self.config = config or TracerConfig()
        self.mi = import_mitsuba(self.config.variant)
        import drjit as dr

        self.dr = dr
        self.scene, self.margin = query_scene(self.mi, geo, tiling)

    def estimate(self, queries: np.ndarray, spp: int, seed: int) -> np.ndarray:
        """(N, 7) queries -> (N, 3) float32 MBTF estimates, the mean of `spp` samples each.

        Deterministic in (queries, spp, seed) and independent of how lanes are split into passes.
        Non-finite samples (numerical accidents) are left out of the mean and logged.
        """
        samples = self.samples(queries, spp, seed)  # (N, spp, 3)
        finite = np.isfinite(samples).all(axis=2)
        if not finite.all():
            log.warning("%d of %d samples were not finite and were left out", (~finite).sum(), finite.size)
            samples = np.where(finite[:, :, None], samples, 0.0)
        counts = np.maximum(finite.sum(axis=1), 1)[:, None]
        return (samples.sum(axis=1, dtype=np.float64) / counts).astype(np.float32)

    def samples(self, queries: np.ndarray, spp: int, seed: int) -> np.ndarray:
        """(N, 7) queries -> (N, spp, 3) float32 individual path samples."""
        queries = C.as_queries(queries)
        if spp < 1:
            raise ValueError(f"spp must be >= 1, got {spp}")
        n = queries.shape[0]
        out = np.empty((n, spp, C.RGB_DIM), np.float32)
        per_pass = max(1, self.config.lanes // spp)
        for lo in range(0, n, per_pass):
            hi = min(lo + per_pass, n)
            rgb = self._trace(queries[lo:hi], spp, seed, first_lane=lo * spp)  # ((hi - lo) * spp, 3)
            out[lo:hi] = rgb.reshape(hi - lo, spp, C.RGB_DIM)
        return out

    # --- one wavefront pass --------------------------------------------------------------------------

    def _trace(self, queries: np.ndarray, spp: int, seed: int, first_lane: int) -> np.ndarray:
        """(n, 7) queries -> (n * spp, 3) samples; lane ``l`` belongs to query ``l // spp``."""
        mi, dr = self.mi, self.dr
        lanes = queries.shape[0] * spp

        def column(index: int):
            return mi.Float(np.repeat(queries[:, index], spp))

        # PCG32 adds arange(lanes) to both arguments: lane l of the query set gets state seed + l and
        # stream l whatever the pass it falls in
        state = dr.opaque(mi.UInt64, (seed + first_lane) % 2**64)
        rng = mi.PCG32(lanes, state, dr.opaque(mi.UInt64, first_lane))
        wi = _unit(mi, dr, column(C.WI_X), column(C.WI_Y))
        wo = _unit(mi, dr, column(C.WO_X), column(C.WO_Y))
        light = dr.rcp(dr.maximum(wi.z, dr.opaque(mi.Float, self.config.min_cos_light)))

        # --- primary ray: Gaussian-jittered aim point, wrapped into the central tile ------------------
        jitter = mi.warp.square_to_std_normal(mi.Point2f(rng.next_float32(), rng.next_float32()))
        # sigma <= 0 is the unfiltered BTF; beyond SIGMA_UNIFORM the wrapped Gaussian is uniform over
        # the tile to float precision, and clamping keeps u + sigma * jitter accurate in float32
        sigma = dr.clip(column(C.SIGMA), 0.0, SIGMA_UNIFORM)
        aim_u = column(C.U) + sigma * jitter.x
        aim_v = column(C.V) + sigma * jitter.y
        aim = mi.Point3f(aim_u - dr.floor(aim_u), aim_v - dr.floor(aim_v), 0.0)
        lift = dr.opaque(mi.Float, PRIMARY_OFFSET) / dr.maximum(wo.z, 1e-3)
        ray = mi.Ray3f(aim + wo * lift, -wo)

        result = mi.Color3f(0.0)
        throughput = mi.Color3f(1.0)
        active = mi.Bool(True)
        ctx = mi.BSDFContext()
        for depth in range(self.config.max_depth):
            si = self.scene.ray_intersect(ray, active)
            active &= si.is_valid()
            bsdf = si.bsdf(ray)
            shift = mi.Vector3f(dr.floor(si.p.x), dr.floor(si.p.y), 0.0)  # back into the central tile

            # --- next-event estimation: the distant light from wi, unit irradiance on the plane ---
            shadow = si.spawn_ray(wi)
            shadow.o -= shift
            visible = active & ~self.scene.ray_test(shadow, active)
            f = bsdf.eval(ctx, si, si.to_local(wi), visible)  # BSDF * cos at the hit
            result += dr.select(visible, throughput * f * light, 0.0)
            if depth == self.config.max_depth - 1:
                break  # the last vertex: no further bounce to sample

            # --- BSDF sampling: the next bounce ----------------------------------------------------
            bs, weight = bsdf.sample(
                ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()), active
            )
            throughput *= weight
            active &= dr.any(throughput > 0.0)
            ray = si.spawn_ray(si.to_world(bs.wo))
            ray.o -= shift
            dr.eval(result, throughput, active, ray, rng)
            if not dr.any(active):
                break
        dr.eval(result)
        return np.stack([result.x.numpy(), result.y.numpy(), result.z.numpy()], axis=1)


def _unit(mi, dr, x, y):
    """Unit vector from its x, y (z >= 0 implied; slightly-outside inputs are renormalised)."""
    return dr.normalize(mi.Vector3f(x, y, dr.safe_sqrt(1.0 - x * x - y * y)))
