"""The `neumip_path` integrator: a wavefront path tracer with buffered neural-material queries.

Each bounce of the Python loop below is one wavefront over every lane of the image (`mi.render`
calls `sample()` once with all rays). Per bounce, every shading query that lands on a `neumip`
surface - two per shading point, as in the paper: the next-event light direction and the
sampled direction (the paper's cosine, mixed with the model's sampling lobe where it declares one:
`bsdf`) - is collected and evaluated per material (`shading.NeuralShading`): in a kernel over
that material's lanes, its ONNX graph traced into it (`engines.kernel.KernelMaterials`), or through
an evaluator in at most two calls: the shading points where both directions count as query groups
of two, the others' single queries. Stock Mitsuba BSDFs on other shapes are called as the stock
`path` integrator calls them; next-event estimation goes to all of Mitsuba's emitters with MIS (power
heuristic) against BSDF sampling.

Next-event estimation at neural surfaces. The stock `path` picks one emitter per shading point (in
proportion to its `sampling_weight`), and its choice is noise: under a sun and a dim sky, a sample
that picks the sky loses the sun. A query group answers K directions for about the price of one
(the offset and the lookups run once), so at neural surfaces of a scene with at most
`MAX_ALL_EMITTERS` emitters every emitter gets a direction of its own (`PathConfig.all_emitters`):
each is one more shadow ray and one more decoder pass. Its MIS weight uses that emitter's own pdf,
and so does a later emission hit of the sampled direction (`prev_all`). Stock BSDFs keep the one
choice. The extra samples are drawn after the bounce's stock dimensions, so those stay where the
stock `path` draws them.

Kernels per bounce. drjit evaluates only what a barrier asks for and traces again whatever a later
barrier needs, so a bounce computes everything that does not depend on the neural answers (the
intersection, emission, emitter and BSDF samples, the next ray, the query columns) and schedules all
of it into one kernel; the neural answers then enter one small kernel that finishes the bounce (NEE,
throughput, Russian roulette). The next ray is spawned from the stored interaction, so it is not
stored itself.

Footprint (sigma) of a query. The contract's sigma is the standard deviation of a Gaussian
footprint. A pixel's footprint is the std of its reconstruction filter, ``filter_std`` pixels
(`filter_std_px`: 0.5 px for the film's default gaussian filter, 0.29 px for a box). Each of a
pixel's ``n`` samples reads a share of it: ``filter_std * sample_footprint(n)``, with
``contract.sample_footprint(n) = max(1/8, 1/sqrt(n))``, the rule of pbrt-v4 (Mitsuba's own textures use
1/sqrt(n) unclamped). The samples are spread over the filter and averaged, so the image is already
the material filtered by the pixel; a query that read the whole pixel footprint would filter it a
second time (a sqrt(2) wider blur; client/mitsuba/README.md, "Rendering"). At 1 spp a sample reads the whole
footprint (no aliasing); the 1/8 floor keeps the lookups prefiltered enough that high spp does not
fall back to aliased finest-level reads.
``n`` is the whole render's spp (`bind`), not one pass's.
- first hit: ``filter_std * sample_footprint(n) * max(|duv/dx|, |duv/dy|)``, the derivatives being
  the pixel spacing in shape uv units (isotropic, larger axis; `mi.render` shrinks differentials by
  1/sqrt(spp of the pass), which is undone first);
- later hits (no differentials exist): a ray cone (Akenine-Moller et al. 2019). The cone leaves the
  camera with the pixel's angular size times the same share; its width grows by ``spread * distance``
  along each segment, and every non-specular bounce adds ``footprint_spread`` radians to the spread
  (a specular bounce keeps it). The width at a hit, divided by the world length of one uv unit
  ``sqrt(|dp/du x dp/dv|)``, is sigma. Indirect light is smooth, so erring coarse is cheap.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

from neumip.core.contract import sample_footprint

from neumip.client.mitsuba.bsdf import dr, mi
from neumip.client.mitsuba.shading import NeuralShading, query_frame, to_query

from mitsuba.ad.integrators.common import mis_weight  # noqa: E402,I001 (needs a variant set first)

log = logging.getLogger(__name__)

PLUGIN_NAME = "neumip_path"

MAX_ALL_EMITTERS = 4
"""Most emitters a scene may have for `PathConfig.all_emitters` to sample each one at neural surfaces (a
query group then has one light per emitter plus the sampled direction); above it, one is chosen."""


@dataclass
class PathConfig:
    """Light transport settings of `neumip_path` (scene properties of the same names)."""

    max_depth: int = 6
    """Longest path in vertices (1 = direct emission only); -1 means unbounded."""
    rr_depth: int = 4
    """Depth from which Russian roulette may end paths."""
    hide_emitters: bool = False
    """Hide directly visible emitters (as the stock `path` integrator's option)."""
    footprint_spread: float = 0.1
    """Radians the footprint cone widens per non-specular bounce (see the module docstring)."""
    all_emitters: bool = True
    """At neural surfaces, next-event estimation samples every emitter of a scene with at most
    `MAX_ALL_EMITTERS` (one direction each, in the same query group), not one chosen at random: no
    light-choice noise, at the cost of a shadow ray and a decoder pass per emitter (see the module
    docstring). False: one emitter, as the stock `path` integrator chooses it."""

    @classmethod
    def from_properties(cls, props: mi.Properties) -> "PathConfig":
        cfg = cls(
            max_depth=int(props.get("max_depth", cls.max_depth)),
            rr_depth=int(props.get("rr_depth", cls.rr_depth)),
            hide_emitters=bool(props.get("hide_emitters", cls.hide_emitters)),
            footprint_spread=float(props.get("footprint_spread", cls.footprint_spread)),
            all_emitters=bool(props.get("all_emitters", cls.all_emitters)),
        )
        if cfg.max_depth < -1 or cfg.max_depth == 0:
            raise ValueError(f"neumip_path: max_depth must be -1 or >= 1, got {cfg.max_depth}")
        if cfg.rr_depth < 1:
            raise ValueError(f"neumip_path: rr_depth must be >= 1, got {cfg.rr_depth}")
        if cfg.footprint_spread < 0:
            raise ValueError(f"neumip_path: footprint_spread must be >= 0, got {cfg.footprint_spread}")
        return cfg


def filter_std_px(rfilter: mi.ReconstructionFilter) -> float:
    """Standard deviation, in pixels, of a film's reconstruction filter (one axis).

    gaussian: ``radius / 4`` (Mitsuba truncates it at 4 std: 0.5 px by default); box of radius r:
    uniform on [-r, r], ``r / sqrt(3)``; tent: ``r / sqrt(6)``. Other filters (mitchell,
    catmullrom, lanczos: negative lobes, main lobe about a pixel wide) use 0.5.
    """
    name, radius = rfilter.class_name(), float(rfilter.radius())
    if name == "GaussianFilter":
        return radius / 4
    if name == "BoxFilter":
        return radius / math.sqrt(3)
    if name == "TentFilter":
        return radius / math.sqrt(6)
    log.debug("reconstruction filter %s: footprint std taken as 0.5 px", name)
    return 0.5


class EvaluatorNotBound(RuntimeError):
    """`neumip_path` was asked to render before an evaluator was bound to it."""


class NeuMIPPathIntegrator(mi.SamplingIntegrator):
    """Path tracer whose neural-surface shading is evaluated in bulk, per material, once per bounce."""

    def __init__(self, props: mi.Properties) -> None:
        mi.SamplingIntegrator.__init__(self, props)
        self.config = PathConfig.from_properties(props)
        self.shading: NeuralShading | None = None
        self.filter_std = 0.5
        """Std (pixels) of the bound scene's reconstruction filter: the footprint of a pixel."""
        self.footprint_spp: int | None = None
        """spp of the whole render, which sets each sample's footprint (None: the sampler's count)."""

    def bind(self, scene: mi.Scene, evaluator, footprint_spp: int | None = None) -> NeuralShading:
        """Use ``evaluator`` (a `contract.Evaluator`) for the neural materials of ``scene``.

        ``footprint_spp``: the spp the whole render will have when it is made of several `mi.render`
        passes (see `sample_footprint`); by default each pass's own sample count is used.
        """
        self.shading = NeuralShading(scene, evaluator)
        self.filter_std = filter_std_px(scene.sensors()[0].film().rfilter()) if scene.sensors() else 0.5
        self.footprint_spp = footprint_spp
        return self.shading

    def sample(self, scene, sampler, ray, medium=None, active=True):
        if self.shading is None:
            raise EvaluatorNotBound(
                "neumip_path has no evaluator: call integrator.bind(scene, evaluator) or render with "
                "neumip.client.mitsuba.render.render_scene"
            )
        cfg, shading = self.config, self.shading
        width = dr.width(ray.d)
        max_depth = cfg.max_depth if cfg.max_depth > 0 else 2**31 - 1
        ctx = mi.BSDFContext()
        pass_spp = sampler.sample_count()
        # undo `mi.render`'s 1/sqrt(spp) shrink of the differentials, then take one sample's share
        spp_scale = math.sqrt(pass_spp) * sample_footprint(self.footprint_spp or pass_spp)

        # --- per-lane state --------------------------------------------------------------------
        active = mi.Bool(active) | dr.zeros(mi.Bool, width)
        L = dr.zeros(mi.Spectrum, width)
        beta = dr.full(mi.Spectrum, 1.0, width)
        eta = dr.full(mi.Float, 1.0, width)
        # As the stock `path`: an environment makes every camera ray valid (alpha = 1).
        valid_ray = dr.full(mi.Bool, (not cfg.hide_emitters) and scene.environment() is not None, width)
        prev_si = dr.zeros(mi.Interaction3f, width)  # only what emitter pdfs need, not a full si
        prev_bsdf_pdf = dr.full(mi.Float, 1.0, width)
        prev_bsdf_delta = dr.full(mi.Bool, True, width)
        emitters = scene.emitters()
        all_emitters = bool(cfg.all_emitters and shading.bsdfs and 1 < len(emitters) <= MAX_ALL_EMITTERS)
        prev_all = dr.zeros(mi.Bool, width)  # the previous vertex sampled every emitter (a neural surface)
        # Footprint cone: world width at the current ray's origin and angular spread (radians).
        cone_width = dr.zeros(mi.Float, width)
        filter_std = self.filter_std
        cone_spread = (
            dr.norm(ray.d_x - ray.d) * spp_scale * filter_std if ray.has_differentials else dr.zeros(mi.Float, width)
        )
        first_ray = ray
        ray = mi.Ray3f(ray)
        ray_d = ray.d  # after the first bounce a ray is spawned from prev_si along ray_d

        for depth in range(max_depth):
            # --- intersect ---------------------------------------------------------------------
            if depth > 0:
                ray = prev_si.spawn_ray(ray_d)
            si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=depth == 0, active=active)

            # --- emission hit by the previous BSDF sample (MIS against NEE) ----------------------
            if not (cfg.hide_emitters and depth == 0):
                ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
                em_pdf = scene.pdf_emitter_direction(prev_si, ds, active & ~prev_bsdf_delta)
                if all_emitters:  # every emitter was sampled there: its own pdf, without the choice of one
                    own_pdf = ds.emitter.pdf_direction(prev_si, ds, active & prev_all & ~prev_bsdf_delta)
                    em_pdf = dr.select(prev_all, own_pdf, em_pdf)
                em_pdf = dr.select(prev_bsdf_delta, 0.0, em_pdf)
                mis_bsdf = mis_weight(prev_bsdf_pdf, em_pdf)
                emitted = ds.emitter.eval(si, active & (prev_bsdf_pdf > 0))
                L = dr.select(active, L + beta * mis_bsdf * emitted, L)

            active_next = active & si.is_valid() & (depth + 1 < max_depth)

            # --- footprint of this hit -----------------------------------------------------------
            cone_width = cone_width + cone_spread * si.t
            if depth == 0 and first_ray.has_differentials:
                si.compute_uv_partials(first_ray)
                sigma_uv = dr.maximum(dr.norm(si.duv_dx), dr.norm(si.duv_dy)) * spp_scale * filter_std
            else:
                uv_length = dr.sqrt(dr.norm(dr.cross(si.dp_du, si.dp_dv)))
                sigma_uv = cone_width / uv_length

            # --- stock BSDFs: emitter sample, BSDF eval + sample ---------------------------------
            bsdf = si.bsdf()
            hits = shading.classify(si, active_next) if shading.bsdfs else None
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            if all_emitters:  # neural lanes sample every emitter below instead
                active_em &= ~hits.any
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
            active_em &= ds.pdf != 0.0
            wo_light = si.to_local(ds.d)
            sample1, sample2 = sampler.next_1d(), sampler.next_2d()
            bsdf_val, bsdf_pdf, bs, bsdf_weight = bsdf.eval_pdf_sample(
                ctx, si, wo_light, sample1, sample2, active_next
            )
            rr_sample = sampler.next_1d()  # drawn where the stock `path` draws it: the dimensions agree

            # --- neural surfaces: this bounce's queries (scheduled, evaluated below) -------------
            queries, lights = None, []
            if hits is not None:
                front = mi.Frame3f.cos_theta(si.wi) > 0
                # NEE: (direction, where it counts, its term without the neural answer f) per light sample
                if all_emitters:  # one towards each emitter
                    lights = [_emitter_sample(scene, emitter, si, bsdf, ctx, sampler.next_2d(), beta,
                                              active_next & hits.any & front) for emitter in emitters]
                else:  # the stock sample of one emitter
                    cos_light = mi.Frame3f.cos_theta(wo_light)
                    ok = active_em & hits.any & front & (cos_light > 0)
                    mis = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, bsdf_pdf))
                    lights = [(wo_light, ok, dr.select(ok, beta * em_weight * cos_light * mis, 0.0))]
                active_em &= ~hits.any  # the stock NEE below is for stock BSDFs only
                sample_ok = front & (mi.Frame3f.cos_theta(bs.wo) > 0) & (bs.pdf > 0)
                # Mitsuba's shading frame (y = n x dp_du) -> the contract's (x along +u, y along +v).
                frame = query_frame(si)
                queries = shading.queries(
                    hits, si.uv, sigma_uv, to_query(si, frame, si.wi),
                    [(to_query(si, frame, wo), ok) for wo, ok, _ in lights]
                    + [(to_query(si, frame, bs.wo), sample_ok)],
                )
                # BTF under unit irradiance is used like a BRDF: f * cos for NEE, f * cos / pdf for the
                # sampled direction (pi f where the cosine is sampled); f multiplies in once it is known.
                sampled = dr.select(bs.pdf > 0, mi.Frame3f.cos_theta(bs.wo) / bs.pdf, 0.0)
                bsdf_weight = dr.select(hits.any, sampled, bsdf_weight)

            # --- next-event estimation at stock BSDFs ---------------------------------------------
            mis_em = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, bsdf_pdf))
            nee = beta * bsdf_val * em_weight * mis_em

            # --- continue along the sampled direction -------------------------------------------
            ray_d = si.to_world(bs.wo)
            beta = beta * bsdf_weight
            eta = eta * bs.eta
            valid_ray |= active & si.is_valid() & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            prev_si = mi.Interaction3f(si.t, si.time, si.wavelengths, si.p, si.n)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            if all_emitters:
                prev_all = hits.any
            cone_spread = dr.select(prev_bsdf_delta, cone_spread, cone_spread + cfg.footprint_spread)

            # --- one kernel: everything above that the rest of the bounce needs --------------------
            # (the intersection is traced once; the neural queries come out of the same kernel)
            dr.schedule(L, nee, beta, eta, active_em, active_next, valid_ray, ray_d, prev_si, prev_bsdf_pdf,
                        prev_bsdf_delta, prev_all, cone_width, cone_spread, rr_sample,
                        [term for _, _, term in lights])
            sampler.schedule_state()
            if queries is not None:
                dr.schedule(hits.any)
                if dr.any(hits.any):
                    *rho_lights, rho_sample = shading.evaluate(queries)
                    # each light sample's term times its answer (zero where it does not count)
                    L = L + sum((term * rho for (_, _, term), rho in zip(lights, rho_lights)), mi.Spectrum(0.0))
                    beta = dr.select(hits.any, beta * rho_sample, beta)
            L = dr.select(active_em, L + nee, L)

            # --- Russian roulette ----------------------------------------------------------------
            beta_max = dr.max(beta * dr.square(eta))
            rr_active = mi.Bool(depth >= cfg.rr_depth)
            rr_prob = dr.minimum(beta_max, 0.95)
            beta = dr.select(rr_active & active_next, beta * dr.rcp(rr_prob), beta)
            active = active_next & (~rr_active | (rr_sample < rr_prob)) & (beta_max != 0.0)

            dr.eval(L, beta, active)
            if not dr.any(active):
                break

        return L, valid_ray, []


def _emitter_sample(scene, emitter, si, bsdf, ctx, sample, beta, active):
    """Next-event estimation towards one ``emitter`` at neural lanes ``active``: ``(wo, valid, term)``,
    the direction (shading frame), where it counts (the emitter sampled, unoccluded, above the
    horizon) and its contribution without the neural answer: ``beta * cos * L / pdf * mis``, the MIS
    weight against the neural BSDF's sampling (power heuristic) with the emitter's own pdf."""
    ds, weight = emitter.sample_direction(si, sample, active)
    ok = active & (ds.pdf > 0)
    wo = si.to_local(ds.d)
    cos = mi.Frame3f.cos_theta(wo)
    ok &= cos > 0
    ok &= ~scene.ray_test(si.spawn_ray_to(ds.p), active=ok)
    if mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta):  # no BSDF sample reaches it: no MIS
        return wo, ok, dr.select(ok, beta * weight * cos, 0.0)
    mis = mis_weight(ds.pdf, bsdf.pdf(ctx, si, wo, ok))
    return wo, ok, dr.select(ok, beta * weight * cos * mis, 0.0)


def register() -> None:
    """Register the integrator under ``neumip_path`` (vectorized variants only; idempotent)."""
    if not dr.is_jit_v(mi.Float):
        raise RuntimeError(f"neumip_path needs a vectorized (llvm/cuda) variant, not {mi.variant()}")
    mi.register_integrator(PLUGIN_NAME, lambda props: NeuMIPPathIntegrator(props))


register()
