"""Neural shading in bulk: per material and bounce, one kernel or at most two evaluation calls for a
whole wavefront.

`NeuralShading` finds the scene's `neumip` surfaces and, per bounce, collects every shading query
that lands on them (all lanes of the wavefront) and hands the RGB answers back as per-lane drjit
arrays. Two ways, by the evaluator bound:

- **In the kernel** (`client.kernel.KernelMaterials`, the in-process default): per material, its lanes are
  compressed (`dr.compress`) and one kernel over them gathers their columns and computes every light's
  answer from the material's ONNX graph (`KernelMaterial.answers`); the answers are scattered back to
  their lanes, one evaluation a bounce for all materials (a material on nearly every lane is computed
  on all of them, without the compaction). Nothing leaves drjit.
- **Buffered** (`contract.Evaluator`: in-process `LocalMaterials`, the ONNX graph in ONNX Runtime, or
  the HTTP `MaterialClient`). A shading point with two or more valid light directions goes as one
  query group (`contract`: the offset and the lookups run once for its K answers); one with a single
  valid direction sends that single query. Per material and call, its lanes are compressed and two
  small kernels over them write its groups ((n, 5 + 2 K) rows) or its single queries ((n, 7)) into a
  drjit buffer that numpy reads without a copy; a material's answers are copied into drjit once and
  read per lane with gathers that run inside the integrator's next kernel. The answers are checked
  here (`contract.as_rgb`: shape and finiteness), once, whatever the evaluator.

The query columns come out of the integrator's one kernel per bounce either way.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from neumip.core import contract as C
from neumip.core.errors import NeumipError

from neumip.client.mitsuba.bsdf import NeuMIPBSDF, dr, mi

log = logging.getLogger(__name__)

DENSE_LANES = 0.95
"""In the kernel, a material whose lanes are at least this share of the wavefront is computed on every
lane instead of its lanes compacted. Compaction (compress, gathers, scatters) costs a few ns a lane; a
trained material's arithmetic tens of times more (`benchmarks/bench_render.py` prints both), so the
lanes computed in vain must be few."""

MAX_SIGMA = 1.0e3
"""Footprints (tile units) are clamped here; a non-finite footprint reads the coarsest level."""


@dataclass
class ShadingStats:
    """What the neural evaluation cost over a render."""

    queries: int = 0
    """Queries answered by the evaluator (a group of K lights counts K; `contract`). In the kernel, every
    light of a lane with any valid light is computed, so this counts K per such lane."""
    calls: int = 0
    """Evaluator calls made (per material and bounce with neural hits: one for its query groups, one
    for its single queries; in the kernel, one kernel per material and bounce)."""
    seconds: float = 0.0
    """Wall time inside the evaluator, including (for HTTP) encoding and transfer; in the kernel, the
    material kernels' (lane compaction, column gathers, the material's arithmetic)."""
    per_material: dict[str, int] = field(default_factory=dict)
    """Queries answered per material name."""

    def add(self, material: str, rows: int, seconds: float) -> None:
        self.queries += rows
        self.calls += 1
        self.seconds += seconds
        self.per_material[material] = self.per_material.get(material, 0) + rows


class KernelMaterial(Protocol):
    """A material whose answers are drjit arithmetic on the lanes (`client.kernel.KernelMaterial`)."""

    def answers(self, columns: list[mi.Float]) -> list[list[mi.Float]]:
        """Query-group columns (contract order, 5 + 2 K Floats) -> per light, its RGB (3 Floats)."""


@runtime_checkable
class InKernelEvaluator(Protocol):
    """An evaluator that computes its answers inside the renderer's kernels
    (`client.kernel.KernelMaterials`), instead of answering query buffers (`contract.Evaluator`)."""

    def materials(self) -> list[str]:
        """The material names it serves."""

    def kernel(self, material: str) -> KernelMaterial:
        """The material `material`, ready to be traced into a bounce's kernel."""


@runtime_checkable
class DeclaresLobes(Protocol):
    """An evaluator that knows each material's sampling lobe (`contract.SamplingLobe`, from the model
    file's metadata): `client.kernel.KernelMaterials`, `client.local.LocalMaterials`, and over HTTP
    `client.http.MaterialClient` and `FallbackEvaluator`."""

    def sampling(self, material: str) -> C.SamplingLobe | None:
        """The lobe the material's model declares (None: the cosine alone)."""


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

    def __init__(self, scene: mi.Scene, evaluator: C.Evaluator | InKernelEvaluator) -> None:
        self.bsdfs = neural_bsdfs(scene)
        self.evaluator = evaluator
        self.in_kernel = isinstance(evaluator, InKernelEvaluator)
        """Whether the answers are computed inside drjit's kernels (`InKernelEvaluator`)."""
        self.stats = ShadingStats()
        missing = sorted({b.material for b in self.bsdfs} - set(evaluator.materials()))
        if missing:
            known = ", ".join(evaluator.materials()) or "none"
            raise LookupError(
                f"the scene uses neural material(s) {', '.join(missing)} that the evaluator does not "
                f"serve (it has: {known})"
            )
        if isinstance(evaluator, DeclaresLobes):  # the model's sampling lobe, where the scene does not set one
            for bsdf in self.bsdfs:
                if not bsdf.lobe_fixed:
                    bsdf.set_lobe(evaluator.sampling(bsdf.material))

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
        a query group (`contract`: the shading point once, every wi; an invalid one as (0, 0), its
        answer unused) where two or more lights are valid, a single query where one is (a group would
        evaluate an unused light); in the kernel, a group wherever any light is valid (the kernel
        computes them all).

        ``uv`` (shape uv), ``sigma`` (footprint std in shape uv units), ``wo`` (towards the viewer)
        and each ``wi`` (towards the light) are per-lane, directions in the `query_frame`. The columns
        and masks are only scheduled (`dr.schedule`): they are computed in the kernel that evaluates
        the caller's other per-bounce state, so the intersection is traced once.
        """
        u, v = uv.x * hits.uv_scale, uv.y * hits.uv_scale
        sigma = sigma * hits.uv_scale
        sigma = dr.select(dr.isfinite(sigma), dr.clip(sigma, 0.0, MAX_SIGMA), MAX_SIGMA)
        valid = [ok for _, ok in lights]
        count = sum((mi.UInt32(ok) for ok in valid[1:]), mi.UInt32(valid[0]))
        wis = [(dr.select(ok, wi.x, 0.0), dr.select(ok, wi.y, 0.0)) for wi, ok in lights]  # (0, 0) if not
        columns = [u, v, sigma, *wis[0], wo.x, wo.y] + [c for wi in wis[1:] for c in wi]
        if self.in_kernel:  # one kernel computes every light of a lane: no single queries
            masks = {material: (mask & (count > 0), mi.Bool(False)) for material, mask in hits.mask.items()}
            dr.schedule(columns, valid, [group for group, _ in masks.values()])
            return NeuralQueries(columns, [], valid, masks)
        single_wi = lights[-1][0]
        for wi, ok in reversed(lights[:-1]):  # the one valid light's wi where there is one
            single_wi = dr.select(ok, wi, single_wi)
        single = [u, v, sigma, single_wi.x, single_wi.y, wo.x, wo.y]
        masks = {material: (mask & (count > 1), mask & (count == 1)) for material, mask in hits.mask.items()}
        dr.schedule(columns, single[C.WI_X:C.WI_Y + 1], valid, list(masks.values()))
        return NeuralQueries(columns, single, valid, masks)

    def evaluate(self, queries: NeuralQueries) -> list[mi.Color3f]:
        """Evaluate ``queries`` -> one Color3f per light: the answer on lanes whose light is valid,
        zero elsewhere. In the kernel where the evaluator offers it (`client.kernel.KernelMaterials`),
        otherwise through the evaluator in at most two calls per material."""
        if self.in_kernel:
            return self._evaluate_in_kernel(queries)
        return self._evaluate_buffered(queries)

    def _evaluate_in_kernel(self, queries: NeuralQueries) -> list[mi.Color3f]:
        """Per material, one kernel computes every light's answer (the material's arithmetic traced by
        `KernelMaterial.answers`) on its lanes with a valid light. Where they are a small part of the
        wavefront, they are taken first (`dr.compress`): the kernel gathers their columns and scatters
        the answers back. Where they are nearly all of it (`DENSE_LANES`: a first hit on a surface
        that fills the view), the kernel runs over the whole wavefront and the other lanes' answers are
        dropped, which costs less than the compaction."""
        width = dr.width(queries.columns[0])
        cols = queries.columns
        out = [[dr.zeros(mi.Float, width) for _ in range(C.RGB_DIM)] for _ in range(queries.lights)]
        start, computed = time.perf_counter(), {}
        for material, (group, single) in queries.masks.items():
            mask = group | single
            count = dr.count(mask)[0]
            if not count:
                continue
            kernel = self.evaluator.kernel(material)
            if count >= DENSE_LANES * width:
                for j, rgb in enumerate(kernel.answers(cols)):
                    out[j] = [dr.select(mask, x, o) for x, o in zip(rgb, out[j])]
            else:
                lanes = dr.compress(mask)
                if count == 1:  # `dr.freeze` would record a width-1 call anew: take the lane twice
                    lanes = dr.gather(mi.UInt32, lanes, dr.zeros(mi.UInt32, 2))
                for j, rgb in enumerate(kernel.answers([dr.gather(mi.Float, c, lanes) for c in cols])):
                    for ch in range(C.RGB_DIM):
                        dr.scatter(out[j][ch], rgb[ch], lanes)
            computed[material] = count * queries.lights
        if not computed:
            return [dr.zeros(mi.Color3f, width) for _ in range(queries.lights)]
        dr.eval(out)
        dr.sync_thread()
        seconds = (time.perf_counter() - start) / len(computed)
        for material, answers in computed.items():
            self.stats.add(material, answers, seconds)
        # lanes of no material kept their zeros; a computed lane's invalid light is dropped here
        return [dr.select(ok, mi.Color3f(*rgb), 0.0) for rgb, ok in zip(out, queries.valid)]

    def _evaluate_buffered(self, queries: NeuralQueries) -> list[mi.Color3f]:
        """At most two evaluator calls per material (its groups, its single queries).

        Each call's rows are written by drjit into one buffer that numpy reads without a copy
        (groups: (n, 5 + 2 K), single queries: (n, 7), lanes in order); a material's answers are
        copied into drjit once and read back with one gather per light and channel that runs in the
        caller's next kernel.
        """
        width = dr.width(queries.columns[0])
        lights = queries.lights
        out = [dr.zeros(mi.Color3f, width) for _ in range(lights)]
        for material, (group, single) in queries.masks.items():
            groups, singles = Call(queries.columns, group, lights), Call(queries.single, single, 1)
            if not groups.total + singles.total:
                continue
            answers = mi.Float(np.concatenate([self._answer(material, call) for call in (groups, singles)]))
            for j, ok in enumerate(queries.valid):  # light j: answer j of a group, or the single answer
                index = dr.select(group, groups.rows * lights + j, groups.total * lights + singles.rows)
                mask = (group | single) & ok
                rgb = mi.Color3f(*(dr.gather(mi.Float, answers, index * C.RGB_DIM + ch, mask)
                                   for ch in range(C.RGB_DIM)))
                out[j] = dr.select(mask, rgb, out[j])
        return out

    def _answer(self, material: str, call: Call) -> np.ndarray:
        """The evaluator's checked answers to the rows of ``call``, flat ((total * 3 K,) float32)."""
        if not call.total:
            return np.zeros(0, C.DTYPE)
        buffer = call.buffer()
        start = time.perf_counter()
        queries = buffer.numpy().reshape(call.total, C.group_width(call.lights))  # a view of drjit's memory
        rgb = C.as_rgb(self.evaluator.evaluate(material, queries), call.total, call.lights)
        self.stats.add(material, call.total * call.lights, time.perf_counter() - start)
        return rgb.reshape(-1)


@dataclass
class NeuralQueries:
    """One bounce's neural queries (lazy drjit arrays, one entry per lane of the wavefront)."""

    columns: list[mi.Float]
    """A query group's 5 + 2 K columns in contract order."""
    single: list[mi.Float]
    """The 7 columns of the single query of the one valid light (where there is one; none in the kernel)."""
    valid: list[mi.Bool]
    """Per light, the lanes where it counts."""
    masks: dict[str, tuple[mi.Bool, mi.Bool]]
    """Material name -> the lanes whose group (two or more valid lights) goes to it, and those whose
    single query (one valid light) does (in the kernel: every lane with a valid light, and none)."""

    @property
    def lights(self) -> int:
        return C.group_lights(len(self.columns))


class Call:
    """One evaluator call's rows: the set lanes of ``mask`` in lane order, each its ``columns`` (the
    5 + 2 K of a group of ``lights``, or the 7 of a single query)."""

    def __init__(self, columns: list[mi.Float], mask: mi.Bool, lights: int) -> None:
        self.columns, self.mask, self.lights = columns, mask, lights
        self.rows, self.total = _row_numbers(mask)

    def buffer(self) -> mi.Float:
        """A (total * W) Float, W = len(columns): the columns of each set lane, one row per lane.

        The set lanes are often few (one material's hits, a small part of the wavefront), so their
        indices are taken first (`dr.compress`), one kernel over them alone gathers the columns, and
        one more interleaves them: a symbolic loop over the columns writes one value per row each
        turn (separate `dr.scatter` calls would each launch a kernel of their own).
        """
        width = len(self.columns)
        lanes = dr.compress(self.mask)
        columns = [dr.gather(mi.Float, column, lanes) for column in self.columns]
        dr.eval(columns)  # one kernel over the set lanes
        row = dr.arange(mi.UInt32, self.total)
        buffer = dr.empty(mi.Float, self.total * width)

        def scatter_column(col: mi.UInt32) -> tuple[mi.UInt32]:
            value = columns[-1]
            for k in range(width - 2, -1, -1):
                value = dr.select(col == k, columns[k], value)
            dr.scatter(buffer, value, row * width + col)
            return (col + 1,)

        dr.while_loop((mi.UInt32(0),), lambda col: col < width, scatter_column)
        dr.eval(buffer)
        return buffer


def _row_numbers(mask: mi.Bool) -> tuple[mi.UInt32, int]:
    """Rows of a buffer that holds the set lanes of ``mask`` (lane order): each lane's row
    (meaningful where the mask is set), and the row count."""
    last = dr.width(mask) - 1
    if last < 0:
        return mi.UInt32(), 0
    before = dr.prefix_sum(mi.UInt32(mask))  # exclusive
    return before, int(before[last]) + int(mask[last])  # one element read each
