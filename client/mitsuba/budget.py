"""Scene footprint analysis (`neumip budget`): which pyramid levels a scene's renders read.

The scene is rendered by its own `neumip_path` integrator (the same footprints as a real render:
ray differentials at the first hit, the ray cone after bounces, the same two queries per shading
point) with a `PreviewRecorder` as the evaluator: it answers every query with the material's preview
Lambertian (``preview_albedo / pi``, no neural evaluation) and keeps each query's footprint sigma
(tile units, ``uv_scale`` applied). A few samples per pixel suffice: they are traced with the
footprints of a render at the scene's own spp (or ``render_spp``), which is what sets each sample's
share of the pixel footprint (`contract.sample_footprint`).

Per material, `material_budget` turns the footprints into what a model of finest resolution R reads:
the level of detail ``log2(sigma R)`` (`contract.level_of_detail`), whose floor is the finer of the
two levels a trilinear lookup reads. The finest level that matters is the finest level L such that at
least ``coverage`` of the queries have a level >= L (they read L or coarser; a model trimmed to L
answers them bit-identically, `neumip trim`). The recommended finest training resolution is the
power of two at which that same quantile of the *pixel* footprint (a query's sigma divided by its
sample's share) reads level 0 (``2^ceil(log2(1 / sigma))``): a model coarser than that magnifies its
finest level in the scene's closest pixels ("too coarse"). Queries read finer levels than their pixel
(each of many samples reads 1/8 of it at 64 spp), but the pixel averages what lies below it.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.config import BASE_CHANNELS, same_footprint_level
from neumip.core.contract import sample_footprint
from neumip.core.modelfile import read_model_file

from neumip.client.mitsuba.bsdf import mi
from neumip.client.mitsuba.render import RenderConfig, render_scene
from neumip.client.mitsuba.shading import neural_bsdfs

log = logging.getLogger(__name__)


class PreviewRecorder:
    """A `contract.Evaluator` that answers the preview Lambertian and records each query's sigma."""

    def __init__(self, scene: mi.Scene) -> None:
        self.albedo: dict[str, float] = {}
        for bsdf in neural_bsdfs(scene):
            self.albedo.setdefault(bsdf.material, bsdf.preview_albedo)
        self.sigmas: dict[str, list[np.ndarray]] = {name: [] for name in self.albedo}

    def materials(self) -> list[str]:
        return sorted(self.albedo)

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        """Query groups (N, 5 + 2 K) -> (N, 3 K) preview answers; keeps a copy of the sigma column
        (one footprint per group: a group reads the textures once)."""
        self.sigmas[material].append(np.array(queries[:, C.SIGMA], dtype=np.float32))
        answers = C.RGB_DIM * C.group_lights(queries.shape[1])
        return np.full((queries.shape[0], answers), self.albedo[material] / math.pi, dtype=C.DTYPE)

    def footprints(self, material: str) -> np.ndarray:
        """(N,) float32 sigma of every query recorded for ``material``."""
        parts = self.sigmas.get(material) or [np.zeros(0, np.float32)]
        return np.concatenate(parts)


def trace_footprints(scene: mi.Scene, spp: int = 4, seed: int = 0,
                     render_spp: int | None = None) -> dict[str, np.ndarray]:
    """Render ``scene`` at ``spp`` with the preview answers and the footprints of a render at
    ``render_spp`` (default: ``spp``, as `render_scene`) -> material -> (N,) query sigmas."""
    recorder = PreviewRecorder(scene)
    render_scene(scene, recorder, RenderConfig(spp=spp, seed=seed, footprint_spp=render_spp))
    return {name: recorder.footprints(name) for name in recorder.materials()}


@dataclass
class ModelFacts:
    """What the budget needs to know of a material's model (from its ONNX metadata)."""

    resolution: int
    """Texels per side of the model's finest level (level 0)."""
    channels: int
    """Feature channels per pyramid texel."""
    bytes: int
    """Size of the model file."""
    finest_level: int = 0
    """Finest level the model still holds (> 0 for a trimmed model)."""
    maps_resolution: int = 0
    """Texels per side at which the model reads the material's own maps (its classical base's or relief's
    pyramid, `MaterialConfig.base` / `relief`), 0: none."""
    lod_bias: int = 0
    """Levels the model raises every footprint's level of detail by (`MaterialConfig.lod_bias`)."""
    base_resolution: int = 0
    """Texels per side of the finest level of its base maps' pyramid (`MaterialConfig.base`), 0: none."""
    relief_resolution: int = 0
    """Texels per side of the finest level of its relief's height pyramid (`MaterialConfig.relief`), 0: none."""
    offset_channels: int = 0
    """Channels of its neural offset texture (one level at `resolution`), 0: no offset."""
    half_textures: bool = False
    """Its latents, offset texture and base maps are stored in float16 (`MaterialConfig.half_textures`)."""
    offset_mip: bool = False
    """Its offset is read as a mip pyramid at the footprint (`MaterialConfig.offset_mip`), so a trim cuts it too."""
    base_channels: int = BASE_CHANNELS
    """Channels its base atlas stores a texel (those that vary between texels, and the horizons)."""

    @property
    def value_bytes(self) -> int:
        """Bytes of one stored value of the latents, the offset texture, the base maps and the relief's heights."""
        return 2 if self.half_textures else 4

    def pyramids(self) -> dict[str, tuple[int, int]]:
        """Each pyramid the model reads, by its initializer's name -> (resolution, bytes a texel): the latents, the
        offset's mip pyramid (`offset_mip`), the base maps', the relief's heights. `neumip trim` cuts them all."""
        out = {W.PYRAMID: (self.resolution, self.value_bytes * self.channels)}
        if self.offset_channels and self.offset_mip:
            out[W.OFFSET_TEXTURE] = (self.resolution, self.value_bytes * self.offset_channels)
        if self.base_resolution:
            out[W.BASE] = (self.base_resolution, self.value_bytes * self.base_channels)
        if self.relief_resolution:
            out[W.RELIEF] = (self.relief_resolution, self.value_bytes)
        return out

    def stored_texels(self, name: str, level: int) -> int:
        """Texels the file stores of pyramid `name` when it holds its levels `level`..: all of them, but the offset's
        mip pyramid whole (`level` 0) is its finest level alone (`core.weights.offset_levels_derived`)."""
        sizes = _level_sizes(self.pyramids()[name][0])
        return sizes[0] ** 2 if name == W.OFFSET_TEXTURE and level == 0 else sum(s * s for s in sizes[level:])


@dataclass
class MaterialBudget:
    """The levels one material's queries read in a scene, and what that asks of its model."""

    material: str
    queries: int
    """Queries recorded for the material (all bounces)."""
    resolution: int
    """Finest resolution of the model the levels refer to."""
    level_range: tuple[int, int]
    """Finest and coarsest level any query read (a query reads floor(level) and the next level)."""
    histogram: list[float]
    """Share of the queries whose finer level read is 0, 1, ..., log2(resolution)."""
    finest_level: int
    """Finest level that matters: at least ``coverage`` of the queries read it or coarser."""
    coverage: float
    magnified: float
    """Share of the queries whose pixel footprint is finer than level 0 (the finest level is magnified)."""
    recommended_resolution: int
    """Finest training resolution at which the scene's closest pixel footprints (the same quantile)
    read level 0."""
    too_coarse: bool
    """True where the recommended resolution is finer than the model's: its latent pyramid's, or the maps'
    it reads where finer (`maps_resolution`)."""
    maps_resolution: int = 0
    """Texels per side at which the model reads the material's maps (base, relief), 0: none."""
    model_bytes: int | None = None
    """The model file's size now (None: no model file for this material)."""
    foreign_graph: bool = False
    """Whether the model file is a graph without neumip metadata (made by another tool): it has no
    pyramid to budget, so the levels refer to a `DEFAULT_RESOLUTION` one, as for no model file."""
    trimmed_bytes: int | None = None
    """About its size after trimming every pyramid to ``finest_level``'s footprint (`neumip trim`)."""
    pyramid_levels: dict[str, int] | None = None
    """Each pyramid's finest level a trim to ``finest_level`` keeps, by its initializer's name: the latents'
    (``pyramid``: ``finest_level``), the base maps' (``base_maps``) and the relief's (``relief_heights``) at their
    own resolutions (the same footprint)."""
    offset_bytes: int | None = None
    """Bytes a trim keeps whole for the neural offset (its texture and quad index table: every query reads it at
    the finest resolution), 0 without one or with its mip pyramid (`MaterialConfig.offset_mip`)."""

    def to_dict(self) -> dict:
        return asdict(self)


def material_budget(material: str, sigma: np.ndarray, resolution: int, coverage: float = 0.999,
                    sample_share: float = 1.0, maps_resolution: int = 0, lod_bias: int = 0) -> MaterialBudget:
    """Levels read by queries of footprints ``sigma`` (N,) on a model of finest ``resolution`` and level-of-detail
    bias ``lod_bias``, which reads the material's maps at ``maps_resolution`` (0: none; a finer one resolves the
    closest pixels too).

    ``sample_share``: the share of the pixel footprint each query read (`contract.sample_footprint`
    of the render's spp). The levels read (and so the trim) follow the queries; the resolution a
    scene needs follows the pixel footprint ``sigma / sample_share``: detail finer than a pixel is
    averaged by the pixel's samples, so it need not be resolved by the model. (After a bounce the
    ray cone's spread is not a share of anything, so those footprints come out coarser than they
    are; they are the widest anyway and do not reach the closest quantile.)
    """
    if not 0 < coverage <= 1:
        raise ValueError(f"coverage must be in (0, 1], got {coverage}")
    levels = int(math.log2(resolution))
    sigma = np.asarray(sigma, np.float64)
    if sigma.size == 0:
        return MaterialBudget(material, 0, resolution, (levels, levels), [0.0] * (levels + 1), levels, coverage,
                              0.0, 1, False, maps_resolution)
    lod = C.level_of_detail(sigma, resolution, lod_bias)
    finer = np.floor(lod).astype(np.int64)
    coarser = np.minimum(finer + (lod > finer), levels)
    histogram = np.bincount(finer, minlength=levels + 1) / sigma.size
    # the (1 - coverage) quantile of the footprint: `coverage` of the queries are at least this wide
    closest = float(np.quantile(sigma, 1.0 - coverage, method="lower"))
    finest = int(np.floor(C.level_of_detail(np.asarray([closest]), resolution, lod_bias)[0]))
    pixel = sigma / sample_share
    recommended = 2 ** max(0, math.ceil(math.log2(1.0 / max(closest / sample_share, 2.0**-24))))
    return MaterialBudget(
        material=material,
        queries=int(sigma.size),
        resolution=resolution,
        level_range=(int(finer.min()), int(coarser.max())),
        histogram=[float(h) for h in histogram],
        finest_level=finest,
        coverage=coverage,
        magnified=float(np.mean(pixel * resolution < 1.0)),
        recommended_resolution=int(recommended),
        too_coarse=recommended > max(resolution, maps_resolution),
        maps_resolution=maps_resolution,
    )


def model_facts(path: Path) -> ModelFacts | None:
    """Resolution, channels, bytes and trim of the model at ``path`` (its ONNX metadata, read by
    `core.modelfile.read_model_file`: ModelError for a file it refuses); None for a graph without
    neumip metadata (made by another tool: no pyramid)."""
    file = read_model_file(path, initializers=True)
    config = file.config
    if config is None:
        return None
    base = file.initializers.get(W.BASE)
    return ModelFacts(config.resolution, config.channels, file.size, file.finest_level,
                      max(config.base, config.relief), config.lod_bias, config.base, config.relief,
                      config.offset_channels if config.offset else 0, config.half_textures, config.offset_mip,
                      BASE_CHANNELS if base is None else base.shape[1])


def _level_sizes(resolution: int) -> list[int]:
    return [resolution >> level for level in range(int(math.log2(resolution)) + 1)]


def pyramid_levels(facts: ModelFacts, finest_level: int) -> dict[str, int]:
    """Each pyramid's finest level that `neumip trim` keeps for latent level K = ``finest_level``
    (`core.config.same_footprint_level`): the level of the same footprint at the pyramid's own resolution, clamped
    at 0; at K = 0 (every query, the finest too) all of it."""
    levels = int(math.log2(facts.resolution))
    return {name: same_footprint_level(levels, int(math.log2(res)), finest_level)
            for name, (res, _) in facts.pyramids().items()}


def _quad_vector_bytes(facts: ModelFacts, levels: dict[str, int]) -> int:
    """The int32 vectors the graph computes each pyramid's quad index table from, kept from `levels` on: two of
    S + 2 entries per level (`training/export/lookup.quad_vectors`)."""
    return sum(8 * (s + 2) for name, (res, _) in facts.pyramids().items() for s in _level_sizes(res)[levels[name]:])


MIP_LEVEL_GRAPH_BYTES = {False: 455, True: 505}
"""About the bytes of graph that derive one level of a whole offset mip pyramid at load (`training/export/lookup.mip_const`:
9 nodes, 11 with the float16 rounding; measured on 16^2 to 256^2 pyramids), which a trimmed model stores as texels."""


def trimmed_size(facts: ModelFacts, finest_level: int) -> int:
    """About the bytes of the model trimmed to ``finest_level`` (`neumip trim`): every pyramid loses the stored
    texels of its levels finer than the same footprint (`pyramid_levels`, `ModelFacts.stored_texels`), and the vectors of its quad index
    table shrink to the levels kept."""
    before, after = pyramid_levels(facts, facts.finest_level), pyramid_levels(facts, max(finest_level, facts.finest_level))
    texels = sum(texel_bytes * (facts.stored_texels(name, before[name]) - facts.stored_texels(name, after[name]))
                 for name, (_, texel_bytes) in facts.pyramids().items())
    if before.get(W.OFFSET_TEXTURE) == 0 < after.get(W.OFFSET_TEXTURE, 0):  # its levels stored, no longer derived
        texels += MIP_LEVEL_GRAPH_BYTES[facts.half_textures] * int(math.log2(facts.resolution))
    return facts.bytes - texels - _quad_vector_bytes(facts, before) + _quad_vector_bytes(facts, after)


def offset_size(facts: ModelFacts) -> int:
    """Bytes of the paper's single-level neural offset texture (and its quad table's vectors), which `neumip trim`
    keeps whole; 0 without one, or with its mip pyramid (`ModelFacts.offset_mip`: trimmed as the others)."""
    if not facts.offset_channels or facts.offset_mip:
        return 0
    r = facts.resolution
    return facts.value_bytes * facts.offset_channels * r * r + 8 * (r + 2)


@dataclass
class SceneBudget:
    """The budget of every neural material of one scene."""

    materials: list[MaterialBudget] = field(default_factory=list)
    spp: int = 4
    """Samples per pixel traced."""
    render_spp: int = 4
    """Samples per pixel of the render whose footprints were traced."""

    def to_json(self) -> str:
        materials = [m.to_dict() for m in self.materials]
        return json.dumps({"spp": self.spp, "render_spp": self.render_spp, "materials": materials}, indent=2)


DEFAULT_RESOLUTION = 64
"""Finest resolution the levels refer to for a material that has no model file (the shipped size)."""


def scene_budget(scene: mi.Scene, models: Path | None, spp: int = 4, coverage: float = 0.999,
                 seed: int = 0, render_spp: int | None = None) -> SceneBudget:
    """Trace ``scene`` and budget each neural material against its model in ``models`` (if there)."""
    render_spp = render_spp or scene.sensors()[0].sampler().sample_count()
    footprints = trace_footprints(scene, spp, seed, render_spp)
    out = SceneBudget(spp=spp, render_spp=render_spp)
    for name, sigma in footprints.items():
        path = Path(models) / f"{name}.onnx" if models else None
        present = path is not None and path.is_file()
        facts = model_facts(path) if present else None
        budget = material_budget(name, sigma, facts.resolution if facts else DEFAULT_RESOLUTION, coverage,
                                 sample_footprint(render_spp), facts.maps_resolution if facts else 0,
                                 facts.lod_bias if facts else 0)
        if facts is not None:
            budget.model_bytes = facts.bytes
            budget.trimmed_bytes = trimmed_size(facts, budget.finest_level)
            budget.pyramid_levels = pyramid_levels(facts, budget.finest_level)
            budget.offset_bytes = offset_size(facts)
        elif present:
            budget.model_bytes, budget.foreign_graph = path.stat().st_size, True
        out.materials.append(budget)
    return out


def format_budget(budget: SceneBudget, width: int = 40) -> str:
    """A human-readable report: per material the histogram and the recommendations."""
    lines = [f"footprints of a render at {budget.render_spp} spp (traced at {budget.spp} spp)"]
    for m in budget.materials:
        if m.foreign_graph:
            about = f" (a foreign graph of {m.model_bytes:,} bytes without neumip metadata: no pyramid to budget)"
        else:
            about = f" ({m.model_bytes:,} bytes)" if m.model_bytes is not None else " (no model file)"
        lines.append(f"{m.material}: {m.queries:,} queries, model {m.resolution}^2"
                     + (f" on its maps at {m.maps_resolution}^2" if m.maps_resolution else "") + about)
        lines.append(f"  levels read: {m.level_range[0]}..{m.level_range[1]}")
        for level, share in enumerate(m.histogram):
            bar = "#" * round(share * width)
            lines.append(f"  level {level:2d} ({m.resolution >> level:4d}^2) {100 * share:6.2f} % {bar}")
        lines.append(f"  finest level that matters ({100 * m.coverage:g} % of queries): {m.finest_level}")
        if m.trimmed_bytes is not None:
            maps = ", ".join(f"{name} from level {level}" for name, level in (m.pyramid_levels or {}).items()
                             if name != W.PYRAMID)
            lines.append(f"  bytes: {m.model_bytes:,} now, {m.trimmed_bytes:,} trimmed to level {m.finest_level}"
                         + (f" ({maps})" if maps else ""))
            if m.offset_bytes:
                lines.append(f"  of which the neural offset texture and its table, kept whole (every query reads "
                             f"them): {m.offset_bytes:,}")
        verdict = (f"the model ({m.resolution}^2) is too coarse for the closest views: "
                   f"{100 * m.magnified:.2f} % of queries come from pixels finer than level 0"
                   if m.too_coarse else "the model suffices" + (
                       f": its maps at {m.maps_resolution}^2 resolve the closest pixels; its latent pyramid "
                       f"({m.resolution}^2) magnifies {100 * m.magnified:.2f} % of queries"
                       if m.recommended_resolution > m.resolution else ""))
        lines.append(f"  recommended finest training resolution: {m.recommended_resolution}^2 ({verdict})")
    return "\n".join(lines)


def plot_budget(budget: SceneBudget, path: Path) -> Path:
    """Bar charts of the share of queries per level, one panel per material, written to ``path``."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise ImportError("--plot needs matplotlib: pip install 'neumip[render]'") from exc
    count = max(len(budget.materials), 1)
    fig, axes = plt.subplots(1, count, figsize=(4 * count, 3), squeeze=False)
    for ax, m in zip(axes[0], budget.materials):
        ax.bar(range(len(m.histogram)), [100 * h for h in m.histogram], color="tab:blue")
        ax.axvline(m.finest_level - 0.5, color="tab:red", linestyle="--", label=f"finest that matters: {m.finest_level}")
        ax.set_title(f"{m.material} ({m.resolution}^2)")
        ax.set_xlabel("level read (finer of the two)")
        ax.set_ylabel("% of queries")
        ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
