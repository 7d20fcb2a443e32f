"""The `neumip` BSDF: marks a surface as a neural material for the `neumip_path` integrator.

Scenes say ``<bsdf type="neumip"><string name="material" value="yarn"/><float name="uv_scale"
value="4"/></bsdf>`` (or the same as a dict). The plugin itself holds no network: the integrator
collects every shading query that lands on a `neumip` surface and sends them to the evaluator in bulk
once per bounce (`shading.py`). What the plugin's own `eval`/`sample` compute is a plain Lambertian preview of
albedo `preview_albedo` written in pure drjit, so that stock integrators (which trace BSDF calls
symbolically) can still render a scene that contains it; `neumip_path` uses only its sampling (and its
pdf, for MIS) and replaces the value with the neural answer.

Sampling. The paper samples a neural material's directions from the cosine. A glossy material's
answers peak about the mirror direction, which the cosine rarely hits: an environment seen in a
varnish is noisy. Where the model file declares a sampling lobe (`contract.SamplingLobe`, written at
training from the material's maps) the integrator sets it here (`set_lobe`): a GGX lobe (visible
normals, about the shading normal) sampled with probability ``weight``, the cosine otherwise; the pdf
is the mixture's. The scene's ``lobe_alpha`` / ``lobe_weight`` override it (``lobe_weight`` 0: the
cosine alone).
"""

from __future__ import annotations

import logging
import sys

from neumip.core.contract import SamplingLobe

from neumip.client.mitsuba.runtime import DEFAULT_VARIANT, import_mitsuba

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
    - ``lobe_alpha`` (float in (0, 1]) and ``lobe_weight`` (float in [0, 1), default 0.5 with an alpha):
      the sampling lobe, in place of the one the model declares; ``lobe_weight`` 0 samples the cosine.
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
        self.lobe_fixed = "lobe_alpha" in props or "lobe_weight" in props
        """Whether the scene sets the sampling lobe (the model's is then not used)."""
        self.lobe: SamplingLobe | None = None
        self._distribution = None
        if self.lobe_fixed:
            weight = float(props.get("lobe_weight", 0.5))
            alpha = float(props["lobe_alpha"]) if "lobe_alpha" in props else None
            if alpha is None and weight:
                raise ValueError(f"neumip BSDF {self.material!r}: lobe_weight {weight} needs a lobe_alpha "
                                 "(or lobe_weight 0: the cosine alone)")
            if not (0 <= weight < 1) or (alpha is not None and not 0 < alpha <= 1):
                raise ValueError(f"neumip BSDF {self.material!r}: lobe_alpha must be in (0, 1] and lobe_weight "
                                 f"in [0, 1), got {alpha} and {weight}")
            self.set_lobe(SamplingLobe(alpha, weight) if weight else None)
        self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        self.m_components = [self.m_flags]

    def set_lobe(self, lobe: SamplingLobe | None) -> None:
        """Sample ``lobe`` besides the cosine (None: the cosine alone)."""
        self.lobe = lobe
        self._distribution = (None if lobe is None
                              else mi.MicrofacetDistribution(mi.MicrofacetType.GGX, lobe.alpha, True))

    def sample(self, ctx, si, sample1, sample2, active=True):
        """A direction from the cosine, or (with probability ``lobe.weight``) from the sampling lobe."""
        cos_theta_i = mi.Frame3f.cos_theta(si.wi)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
        if self.lobe is not None:
            m, _ = self._distribution.sample(si.wi, sample2)
            bs.wo = dr.select(sample1 < self.lobe.weight, mi.reflect(si.wi, m), bs.wo)
        bs.pdf = self.pdf(ctx, si, bs.wo, active)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        bs.sampled_component = 0
        ok = active & (cos_theta_i > 0) & (bs.pdf > 0)
        # the preview's f cos / pdf (the albedo itself where the cosine alone is sampled)
        weight = self.preview_albedo * dr.inv_pi * mi.Frame3f.cos_theta(bs.wo) / dr.select(ok, bs.pdf, 1.0)
        return bs, dr.select(ok, mi.Spectrum(weight), mi.Spectrum(0.0))

    def eval(self, ctx, si, wo, active=True):
        cos_i, cos_o = mi.Frame3f.cos_theta(si.wi), mi.Frame3f.cos_theta(wo)
        value = self.preview_albedo * dr.inv_pi * cos_o
        return dr.select(active & (cos_i > 0) & (cos_o > 0), mi.Spectrum(value), mi.Spectrum(0.0))

    def pdf(self, ctx, si, wo, active=True):
        cos_i = mi.Frame3f.cos_theta(si.wi)
        pdf = mi.warp.square_to_cosine_hemisphere_pdf(wo)
        if self.lobe is not None:  # visible-normal pdf of the half vector, times its Jacobian 1 / (4 wo.m)
            m = dr.normalize(si.wi + wo)
            lobe = self._distribution.pdf(si.wi, m) / (4 * dr.abs(dr.dot(wo, m)))
            lobe = dr.select((mi.Frame3f.cos_theta(wo) > 0) & dr.isfinite(lobe), lobe, 0.0)
            pdf = dr.lerp(pdf, lobe, self.lobe.weight)
        return dr.select(active & (cos_i > 0) & (mi.Frame3f.cos_theta(wo) > 0), pdf, 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

    def traverse(self, callback):
        pass

    def to_string(self) -> str:
        return f"NeuMIPBSDF[material={self.material!r}, uv_scale={self.uv_scale}, lobe={self.lobe}]"


def register() -> None:
    """Register the plugin under ``neumip`` (vectorized variants only; idempotent)."""
    if not dr.is_jit_v(mi.Float):
        raise RuntimeError(f"the neumip BSDF needs a vectorized (llvm/cuda) variant, not {mi.variant()}")
    mi.register_bsdf(PLUGIN_NAME, lambda props: NeuMIPBSDF(props))


register()
