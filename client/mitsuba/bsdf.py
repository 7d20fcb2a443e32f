"""The `neumip` BSDF: marks a surface as a neural material for the `neumip_path` integrator.

Scenes say ``<bsdf type="neumip"><string name="material" value="yarn"/><float name="uv_scale"
value="4"/></bsdf>`` (or the same as a dict). The plugin itself holds no network: the integrator
collects every shading query that lands on a `neumip` surface and sends them to the evaluator in bulk
once per bounce (`shading.py`). What the plugin's own `eval`/`sample` compute is a plain Lambertian preview of
albedo `preview_albedo` written in pure drjit, so that stock integrators (which trace BSDF calls
symbolically) can still render a scene that contains it; `neumip_path` uses only its cosine sampling
and replaces the value with the neural answer.
"""

from __future__ import annotations

import logging
import sys

from .runtime import DEFAULT_VARIANT, import_mitsuba

log = logging.getLogger(__name__)


def _variant() -> str:
    """The variant already set if it is a JIT one (llvm_*, cuda_*: a user's choice is kept), else
    the default llvm variant (the plugins need a vectorized variant)."""
    mitsuba = sys.modules.get("mitsuba")
    current = mitsuba.variant() if mitsuba is not None else None
    if current and current.startswith(("llvm_", "cuda_")):
        return current
    if current:
        log.info("mitsuba variant %s is not vectorized; switching to %s", current, DEFAULT_VARIANT)
    return DEFAULT_VARIANT


mi = import_mitsuba(_variant())
import drjit as dr  # noqa: E402  (drjit must be imported after the LLVM check in import_mitsuba)

PLUGIN_NAME = "neumip"


class NeuMIPBSDF(mi.BSDF):
    """A neural material placeholder: material name, uv scale, and a Lambertian preview.

    Properties:
    - ``material`` (string, required): name of the material the evaluator serves.
    - ``uv_scale`` (float, default 1, > 0): material tiles per unit of the shape's uv coordinates;
      the query position is ``uv * uv_scale`` and footprints scale the same way.
    - ``preview_albedo`` (float, default 0.5, in [0, 1]): reflectance of the stock-integrator preview.
    """

    def __init__(self, props: mi.Properties) -> None:
        mi.BSDF.__init__(self, props)
        if "material" not in props:
            raise ValueError("neumip BSDF: the 'material' property (the material's name) is required")
        self.material = str(props["material"])
        if not self.material:
            raise ValueError("neumip BSDF: 'material' must not be empty")
        self.uv_scale = float(props.get("uv_scale", 1.0))
        if not self.uv_scale > 0:
            raise ValueError(f"neumip BSDF {self.material!r}: uv_scale must be > 0, got {self.uv_scale}")
        self.preview_albedo = float(props.get("preview_albedo", 0.5))
        if not 0 <= self.preview_albedo <= 1:
            raise ValueError(
                f"neumip BSDF {self.material!r}: preview_albedo must be in [0, 1], got {self.preview_albedo}"
            )
        self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        self.m_components = [self.m_flags]

    def sample(self, ctx, si, sample1, sample2, active=True):
        """Cosine-weighted hemisphere sampling (the paper's sampling for neural materials)."""
        cos_theta_i = mi.Frame3f.cos_theta(si.wi)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
        bs.pdf = mi.warp.square_to_cosine_hemisphere_pdf(bs.wo)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        bs.sampled_component = 0
        ok = active & (cos_theta_i > 0) & (bs.pdf > 0)
        weight = dr.select(ok, mi.Spectrum(self.preview_albedo), mi.Spectrum(0.0))
        return bs, weight

    def eval(self, ctx, si, wo, active=True):
        cos_i, cos_o = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo)
        value = self.preview_albedo * dr.inv_pi * cos_o
        return dr.select(active & (cos_i > 0) & (cos_o > 0), mi.Spectrum(value), mi.Spectrum(0.0))

    def pdf(self, ctx, si, wo, active=True):
        cos_i = mi.Frame3f.cos_theta(si.wi)
        pdf = mi.warp.square_to_cosine_hemisphere_pdf(wo)
        return dr.select(active & (cos_i > 0), pdf, 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

    def traverse(self, callback):
        pass

    def to_string(self) -> str:
        return f"NeuMIPBSDF[material={self.material!r}, uv_scale={self.uv_scale}]"


def register() -> None:
    """Register the plugin under ``neumip`` (vectorized variants only; idempotent)."""
    if not dr.is_jit_v(mi.Float):
        raise RuntimeError(f"the neumip BSDF needs a vectorized (llvm/cuda) variant, not {mi.variant()}")
    mi.register_bsdf(PLUGIN_NAME, lambda props: NeuMIPBSDF(props))


register()
