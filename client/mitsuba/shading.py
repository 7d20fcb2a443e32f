"""Buffered neural shading: at most two evaluation calls per material per bounce for a whole wavefront.

`NeuralShading` finds the scene's `neumip` surfaces and, per bounce, collects every shading query
that lands on them (all lanes of the wavefront), evaluates them through the bound evaluator
(`contract.Evaluator`: in-process `LocalMaterials` or the HTTP `MaterialClient`), and hands the RGB
answers back as per-lane drjit arrays. A shading point whose K light directions are all valid goes
as one query group (`contract`: the offset and the lookups run once for its K answers); where only
some are valid, their single queries go instead. The data moves in bulk: the query columns come out
of the integrator's one kernel per bounce, one more kernel per call writes a material's groups
((n, 5 + 2 K) rows) or its single queries ((n, 7)) straight into a drjit buffer that numpy reads
without a copy, and the answers are copied into drjit once and read
per lane with gathers that run inside the integrator's next kernel. The answers are checked here
(`contract.as_rgb`: shape and finiteness), once, whatever the evaluator.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

from neumip.client import contract as C
from neumip.client.errors import NeumipError

from .bsdf import NeuMIPBSDF, dr, mi

log = logging.getLogger(__name__)

MAX_SIGMA = 1.0e3
"""Footprints (tile units) are clamped here; a non-finite footprint reads the coarsest level."""


@dataclass
class ShadingStats:
    """What the neural evaluation cost over a render."""

    queries: int = 0
    """Queries answered by the evaluator (a group of K lights counts K; `contract`)."""
    calls: int = 0
    """Evaluator calls made (one per material per bounce with neural hits)."""
    seconds: float = 0.0
    """Wall time inside the evaluator, including (for HTTP) encoding and transfer."""
    per_material: dict[str, int] = field(default_factory=dict)
    """Queries answered per material name."""

    def add(self, material: str, rows: int, seconds: float) -> None:
        self.queries += rows
        self.calls += 1
        self.seconds += seconds
        self.per_material[material] = self.per_material.get(material, 0) + rows


class NestedNeuralBSDF(NeumipError, ValueError):
    """A `neumip` BSDF inside another BSDF (twosided, blend, mask...): not supported."""


def neural_bsdfs(scene: mi.Scene) -> list[NeuMIPBSDF]:
    """Every distinct `neumip` BSDF attached to a shape of ``scene`` (in shape order).

    Raises NestedNeuralBSDF where a `neumip` BSDF is wrapped in another BSDF: the integrator only
    sees a shape's own BSDF, so a wrapped neural material would silently render as its preview.
    """
    found: dict[int, NeuMIPBSDF] = {}
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if isinstance(bsdf, NeuMIPBSDF):
            found.setdefault(id(bsdf), bsdf)
        elif bsdf is not None and NeuMIPBSDF.__name__ in str(bsdf):  # nested: listed in its to_string
            raise NestedNeuralBSDF(
                f"shape {shape.id() or shape.class_name()!r}: a neumip BSDF inside "
                f"{bsdf.class_name()} is not supported; neural materials are one-sided (the back side "
                "renders black), so attach <bsdf type=\"neumip\"> to the shape directly"
            )
    return list(found.values())


def query_frame(si: mi.SurfaceInteraction3f) -> mi.Frame3f:
    """The contract's local frame at each lane of ``si``: z the shading normal, x along +u, y along +v.

    x is ``dp_du`` projected onto the tangent plane (the shading frame's own ``s`` where ``dp_du``
    vanishes, e.g. at a sphere's pole); y is ``n x x``, negated on lanes where it would point
    towards -v (Mitsuba's ``sh_frame.t`` is ``n x dp_du``, which is -v on spheres and cube faces).
    Where ``dp_du`` and ``dp_dv`` are not orthogonal, x follows u exactly and y is the unit tangent
    orthogonal to it on the +v side. ``uv_scale`` scales u and v alike, so it does not change the frame.
    The frame may be left-handed; only its axes' dot products are used.
    """
    n = si.sh_frame.n
    s = si.dp_du - n * dr.dot(n, si.dp_du)
    length = dr.norm(s)
    s = dr.select(length > 1e-6 * dr.norm(si.dp_du), s / length, si.sh_frame.s)
    t = dr.cross(n, s)
    t = dr.select(dr.dot(t, si.dp_dv) < 0, -t, t)
    return mi.Frame3f(s, t, n)


def to_query(si: mi.SurfaceInteraction3f, frame: mi.Frame3f, w: mi.Vector3f) -> mi.Vector3f:
    """A direction ``w`` in ``si``'s shading frame (as ``si.wi`` and BSDF samples are), in ``frame``.

    Both frames share the normal, so ``z`` (the cosine) is unchanged.
    """
    return frame.to_local(si.sh_frame.to_world(w))


def scene_materials(scene: mi.Scene) -> list[str]:
    """Names of the neural materials ``scene`` uses."""
    return sorted({b.material for b in neural_bsdfs(scene)})


@dataclass
class NeuralHits:
    """Per-lane facts about the neural surfaces of one bounce (all arrays of the wavefront width)."""

    mask: dict[str, mi.Bool]
    """Material name -> lanes whose hit is a front-facing neural surface of that material."""
    any: mi.Bool
    """Lanes that hit any neural surface (either side)."""
    uv_scale: mi.Float
    """Material tiles per uv unit of the hit's BSDF (0 elsewhere)."""


class NeuralShading:
    """Buffered evaluation of the neural materials of one scene through one evaluator."""

    def __init__(self, scene: mi.Scene, evaluator: C.Evaluator) -> None:
        self.bsdfs = neural_bsdfs(scene)
        self.evaluator = evaluator
        self.stats = ShadingStats()
        missing = sorted({b.material for b in self.bsdfs} - set(evaluator.materials()))
        if missing:
            known = ", ".join(evaluator.materials()) or "none"
            raise LookupError(
                f"the scene uses neural material(s) {', '.join(missing)} that the evaluator does not "
                f"serve (it has: {known})"
            )

    @property
    def materials(self) -> list[str]:
        return sorted({b.material for b in self.bsdfs})

    def classify(self, si: mi.SurfaceInteraction3f, active: mi.Bool) -> NeuralHits:
        """Which lanes of ``si`` hit which neural material."""
        ptr = si.bsdf()
        front = mi.Frame3f.cos_theta(si.wi) > 0
        any_hit = dr.zeros(mi.Bool, dr.width(active))
        scale = dr.zeros(mi.Float, dr.width(active))
        masks: dict[str, mi.Bool] = {}
        for bsdf in self.bsdfs:
            hit = active & (ptr == mi.BSDFPtr(bsdf))
            any_hit |= hit
            scale = dr.select(hit, dr.opaque(mi.Float, bsdf.uv_scale), scale)
            prev = masks.get(bsdf.material)
            masks[bsdf.material] = (hit & front) if prev is None else (prev | (hit & front))
        return NeuralHits(masks, any_hit, scale)

    def queries(
        self,
        hits: NeuralHits,
        uv: mi.Point2f,
        sigma: mi.Float,
        wo: mi.Vector3f,
        lights: list[tuple[mi.Vector3f, mi.Bool]],
    ) -> NeuralQueries:
        """This bounce's queries for each (wi, valid) in ``lights`` at every neural lane, scheduled:
        a query group (`contract`: the shading point once, every wi) where every light is valid, the
        single queries of the valid lights elsewhere (a group would evaluate an unused light).

        ``uv`` (shape uv), ``sigma`` (footprint std in shape uv units), ``wo`` (towards the viewer)
        and each ``wi`` (towards the light) are per-lane, directions in the `query_frame`. The columns
        and masks are only scheduled (`dr.schedule`): they are computed in the kernel that evaluates
        the caller's other per-bounce state, so the intersection is traced once.
        """
        u, v = uv.x * hits.uv_scale, uv.y * hits.uv_scale
        sigma = sigma * hits.uv_scale
        sigma = dr.select(dr.isfinite(sigma), dr.clip(sigma, 0.0, MAX_SIGMA), MAX_SIGMA)
        columns = [u, v, sigma, lights[0][0].x, lights[0][0].y, wo.x, wo.y]
        columns += [c for wi, _ in lights[1:] for c in (wi.x, wi.y)]
        every = lights[0][1]
        for _, ok in lights[1:]:
            every = every & ok
        masks = {material: (mask & every, [mask & ok & ~every for _, ok in lights])
                 for material, mask in hits.mask.items()}
        dr.schedule(columns, [m for group, singles in masks.values() for m in [group, *singles]])
        return NeuralQueries(columns, masks)

    def evaluate(self, queries: NeuralQueries) -> list[mi.Color3f]:
        """Evaluate ``queries`` in at most two evaluator calls per material (its groups, its single
        queries) -> one Color3f per light: the answer on lanes whose light is valid, zero elsewhere.

        Each call's rows are written by drjit into one buffer that numpy reads without a copy
        (groups: (n, 5 + 2 K), lanes in order; single queries: (n, 7), light by light, lanes in
        order); the answers are read back with a gather per lane that runs in the caller's next
        kernel.
        """
        width = dr.width(queries.columns[0])
        lights = queries.lights
        out = [dr.zeros(mi.Color3f, width) for _ in range(lights)]
        for material, (group, singles) in queries.masks.items():
            for entries, masks, k in (([queries.columns], [group], lights), (queries.singles(), singles, 1)):
                rows, total = _row_numbers(masks)
                if total == 0:
                    continue
                answers = self._answer(material, _query_buffer(entries, rows, masks, total), total, k)
                for j in range(lights):  # light j: a group's answer j, or the single query of entry j
                    index, mask = ((rows[0] * k + j, masks[0]) if k > 1 else (rows[j], masks[j]))
                    rgb = mi.Color3f(*(dr.gather(mi.Float, answers, index * C.RGB_DIM + ch, mask)
                                       for ch in range(C.RGB_DIM)))
                    out[j] = dr.select(mask, rgb, out[j])
        return out

    def _answer(self, material: str, buffer: mi.Float, rows: int, lights: int) -> mi.Float:
        """The evaluator's checked answers to ``rows`` rows of ``buffer`` (groups of ``lights``), flat."""
        start = time.perf_counter()
        queries = buffer.numpy().reshape(rows, C.group_width(lights))  # a view of drjit's memory
        rgb = C.as_rgb(self.evaluator.evaluate(material, queries), rows, lights)
        self.stats.add(material, rows * lights, time.perf_counter() - start)
        return mi.Float(rgb.reshape(-1))


@dataclass
class NeuralQueries:
    """One bounce's neural queries (lazy drjit arrays)."""

    columns: list[mi.Float]
    """A query group's 5 + 2 K columns in contract order, for every lane of the wavefront."""
    masks: dict[str, tuple[mi.Bool, list[mi.Bool]]]
    """Material name -> the lanes whose group goes to that material (every light valid), and per
    light the lanes whose single query goes to it (that light valid, not every light)."""

    @property
    def lights(self) -> int:
        return C.group_lights(len(self.columns))

    def singles(self) -> list[list[mi.Float]]:
        """Per light, the 7 columns of its single query (`contract.ungroup`, lazily)."""
        c = self.columns
        wis = [c[C.WI_X:C.WI_Y + 1]] + [c[C.QUERY_DIM + 2 * j:C.QUERY_DIM + 2 * j + 2] for j in range(self.lights - 1)]
        return [c[:C.WI_X] + wi + c[C.WO_X:C.QUERY_DIM] for wi in wis]


def _query_buffer(entries: list[list[mi.Float]], rows: list[mi.UInt32], masks: list[mi.Bool], total: int):
    """A (total * W) Float, W the width of each entry: row ``rows[k][lane]`` holds the columns
    ``entries[k]`` of each lane set in ``masks[k]``.

    One kernel: a symbolic loop over the W columns scatters one value per entry and lane each turn
    (separate `dr.scatter` calls into one array would each launch a kernel of their own).
    """
    width = len(entries[0])
    buffer = dr.empty(mi.Float, total * width)

    def scatter_column(col: mi.UInt32) -> tuple[mi.UInt32]:
        for columns, row, mask in zip(entries, rows, masks):
            value = columns[-1]
            for k in range(width - 2, -1, -1):
                value = dr.select(col == k, columns[k], value)
            dr.scatter(buffer, value, row * width + col, mask)
        return (col + 1,)

    dr.while_loop((mi.UInt32(0),), lambda col: col < width, scatter_column)
    dr.eval(buffer)
    return buffer


def _row_numbers(masks: list[mi.Bool]) -> tuple[list[mi.UInt32], int]:
    """Rows of a buffer that holds the set lanes of each mask in turn (lane order): per mask, each
    lane's row (meaningful where the mask is set), and the total row count."""
    rows, total = [], 0
    for mask in masks:
        before = dr.prefix_sum(mi.UInt32(mask))  # exclusive
        n = int(before.numpy()[-1]) + int(mask.numpy()[-1]) if dr.width(mask) else 0  # mask: evaluated
        rows.append(before + total)
        total += n
    return rows, total
