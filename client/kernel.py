"""In-kernel evaluation: a material's exported weights traced as drjit arithmetic.

The buffered path (`shading.NeuralShading` with `LocalMaterials` or a server) copies each bounce's
queries out of drjit, runs the ONNX graph, and copies the answers back. `KernelMaterials` instead
reads the same ``.onnx`` file's weights (`neumip.training.export_read.read_model`) and writes the
material's arithmetic - the offset lookup, its MLP and the parallax shift, the trilinear pyramid
lookup, the decoder and its head - as drjit operations on the lanes themselves: the weights are
literals of the kernel, the textures two flat arrays read with `dr.gather`. drjit's LLVM backend
compiles it, once per material (cached on disk like every drjit kernel), into one vectorised
kernel per bounce that also gathers the lanes' queries and scatters the answers: no buffers, no
copies, no separate inference engine.

It computes what the ONNX graph computes, in another order of float operations: answers agree with
ONNX Runtime's to about 5e-6 (the parity tolerance of the export is 1e-5;
tests/client/test_kernel.py checks it on random queries of several model layouts). Each lane
is computed alone, so an answer does not depend on the batch it is in. The ONNX file stays the one
artifact: ONNX Runtime runs its graph, this module reads its weights.

As an `Evaluator` (`evaluate(material, queries)`), it also answers numpy query buffers and query
groups: how the server's ``kernel`` engine answers, and how its answers are compared with ONNX
Runtime's.

Needs drjit and onnx (the ``kernel`` extra), not Mitsuba. The arrays are those of a drjit backend
namespace chosen at construction: ``drjit.llvm.ad`` by default, the renderer passes its Mitsuba
variant's (`namespace_of(mi.Float)`; ``mi.Float`` in ``llvm_ad_rgb`` is ``drjit.llvm.ad.Float``).
"""

from __future__ import annotations

import functools
import gc
import importlib
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from neumip.core import contract as C
from neumip.client.local import ModelError, ModelFolder
from neumip.client.mitsuba.runtime import ensure_llvm

ensure_llvm(required=False)  # drjit's LLVM backend loads libLLVM, and one older than 16 aborts the process
try:
    import drjit as dr
    import onnx
except ImportError as exc:
    raise ImportError(f"{exc.name or exc} is not installed: pip install 'neumip[kernel]'") from exc

log = logging.getLogger(__name__)

Rgb = list  # three Floats: one answer per lane
Float = object
"""A drjit Float array type of the material's backend (`KernelMaterial.backend.Float`)."""

DEFAULT_BACKEND = "drjit.llvm.ad"


def namespace_of(array_type: type) -> ModuleType:
    """The drjit backend namespace of an array type: ``drjit.llvm.ad`` for ``mi.Float`` in
    ``llvm_ad_rgb``, ``drjit.cuda.ad`` in ``cuda_ad_rgb``."""
    return importlib.import_module(array_type.__module__)


DRJIT_LOCK = threading.RLock()
"""Held around every drjit operation of this module's materials - building one, evaluating it,
recording or replaying its frozen call, freeing its arrays - so that they run one at a time in this
process. drjit 1.5 deadlocks (holding the GIL: the whole process stops) or aborts when one thread
records a frozen function while another does other drjit work: four threads calling two materials
hung or crashed in 2 runs of 3, and a server thread loading a material while its engine thread
answered hung in 1 run of 3 (`tests/server/test_engine.py`). Re-entrant: `answers` runs inside `run`."""


@dataclass
class Textures:
    """A material's tables in drjit memory (a PyTree: the frozen function's inputs)."""

    pyramid: Float
    """The levels' texels, (T, C) flat, levels from the file's finest to 1 x 1."""
    offset: Float
    """The offset texture, (R * R, C_offset) flat (one unused element without an offset)."""
    sizes: object
    """Texels per side of each level (UInt32)."""
    starts: object
    """Each level's first row in `pyramid` (levels finer than the file's finest are not stored)."""


class KernelMaterial:
    """One material's weights, ready to be traced: `answers` writes its arithmetic on drjit arrays."""

    def __init__(self, path: str | Path, backend: ModuleType | None = None, data: bytes | None = None) -> None:
        """Read the model file `path` (from `data`, its bytes already read, if given); raises
        ModelError if it cannot be served. `backend`: drjit namespace of the arrays (default
        ``drjit.llvm.ad``)."""
        from neumip.core import head
        from neumip.training.export import _depth_weights
        from neumip.training.export_read import ModelLayoutError, read_model

        path = Path(path)
        try:
            model = onnx.load_model_from_string(data) if data is not None else onnx.load(str(path))
            self.config, self.weights, self.metadata, self.finest = read_model(model)
        except OSError as exc:
            raise ModelError(f"{path.name}: cannot read: {exc.strerror or exc}") from exc
        except ModelLayoutError as exc:
            raise ModelError(f"{path.name}: {exc}") from exc
        except Exception as exc:  # onnx's parser raises its own types for a corrupt file
            raise ModelError(f"{path.name}: cannot load ONNX model: {exc}") from exc
        bad = [name for name, value in self.weights.items() if not np.isfinite(value).all()]
        if bad:
            raise ModelError(f"{path.name}: non-finite weights in {', '.join(sorted(bad))}")
        if self.config.offset:  # offset_scale folded into the offset MLP's last layer, as in the graph
            self.weights = _depth_weights(self.weights, self.config)
        self.backend = backend or importlib.import_module(DEFAULT_BACKEND)
        """The drjit namespace whose arrays `answers` takes and gives (``drjit.llvm.ad``)."""
        jit = self.backend
        self.name = path.stem
        self.head = self.config.head
        self.yuv_to_rgb = head.YUV_TO_RGB
        self.shadow_floor = head.SHADOW_FLOOR
        first = self.config.level_starts()[self.finest]
        with DRJIT_LOCK:
            self.textures = Textures(
                jit.Float(self.weights["pyramid"].ravel()),
                jit.Float(self.weights["offset_texture"].ravel() if self.config.offset else [0.0]),
                jit.UInt32(self.config.level_sizes()),
                jit.UInt32([max(s - first, 0) for s in self.config.level_starts()]),
            )
            self._frozen = dr.freeze(self._trace)

    def __del__(self) -> None:
        """Free the drjit arrays under `DRJIT_LOCK`, whichever thread drops the material last (at
        interpreter exit the lock may already be gone: drjit frees them then)."""
        if DRJIT_LOCK is None:
            return
        with DRJIT_LOCK:
            self.__dict__.pop("textures", None)
            self.__dict__.pop("_frozen", None)

    @property
    def traces(self) -> int:
        """How often the arithmetic was traced: once per number of lights, unless a call's inputs
        changed the frozen function's layout (see `dr.freeze`)."""
        return self._frozen.n_recordings

    def answers(self, u: Float, v: Float, sigma: Float, wo: tuple[Float, Float],
                lights: list[tuple[Float, Float]]) -> list[Rgb]:
        """RGB for each light direction ``(wi_x, wi_y)`` in ``lights`` of the shading points (u, v,
        sigma, wo), evaluated: a query group (`contract`): the offset and the lookup run once, the
        decoder once per light.

        The arithmetic is traced once per number of lights and replayed after (`dr.freeze`): a traced
        material is thousands of operations, whose tracing and code generation cost several
        milliseconds a call (a multi-bounce, multi-material render makes hundreds of calls).

        Calls run one at a time (`DRJIT_LOCK`), without Python's cyclic garbage collector: drjit
        aborts the process when an array made from numpy memory (this class's textures are) is freed
        while a frozen function records, as a collection of unreachable materials did."""
        columns = [u, v, sigma, *wo] + [c for wi in lights for c in wi]
        with DRJIT_LOCK:
            collecting = gc.isenabled()
            gc.disable()
            try:
                flat = self._frozen(self.textures, columns)
            finally:
                if collecting:
                    gc.enable()
        return [flat[j * C.RGB_DIM:(j + 1) * C.RGB_DIM] for j in range(len(lights))]

    def evaluate(self, queries: np.ndarray) -> np.ndarray:
        """(N, 7) queries -> (N, 3) float32 RGB; query groups (N, 5 + 2 K) -> (N, 3 K) (checked:
        `contract.as_queries`, then `run`)."""
        return self.run(C.as_queries(queries, groups=True))

    def run(self, queries: np.ndarray) -> np.ndarray:
        """`evaluate` of queries already checked (`contract.as_queries`: a C-contiguous (N, 5 + 2 K)
        float32 array of finite values), as a server's are when they reach the engine. All of it holds
        `DRJIT_LOCK`: the upload, the gathers and the read-back are drjit work too."""
        jit = self.backend
        if not len(queries):
            return np.zeros((0, C.RGB_DIM * C.group_lights(queries.shape[1])), C.DTYPE)
        with DRJIT_LOCK:
            # one upload, then the columns gathered in drjit memory (columns made from numpy arrays
            # each made the frozen trace record again, call after call)
            flat, width = jit.Float(queries.reshape(-1)), queries.shape[1]
            row = dr.arange(jit.UInt32, len(queries)) * width
            columns = [dr.gather(jit.Float, flat, row + i) for i in range(width)]
            lights = [(columns[C.WI_X], columns[C.WI_Y])]
            lights += [(columns[i], columns[i + 1]) for i in range(C.QUERY_DIM, queries.shape[1], 2)]
            rgb = [c for answer in self.answers(columns[C.U], columns[C.V], columns[C.SIGMA],
                                                (columns[C.WO_X], columns[C.WO_Y]), lights) for c in answer]
            dr.eval(rgb)
            answers = np.stack([np.asarray(c) for c in rgb], axis=1)
            del flat, row, columns, lights, rgb  # freed under the lock too
        return answers

    # --- the material's stages (drjit arrays in, drjit arrays out) --------------------------------

    def _trace(self, textures: Textures, columns: list[Float]) -> list[Float]:
        """columns (u, v, sigma, wo_x, wo_y, then wi_x, wi_y of each light) -> the lights' RGB, flat.
        Reads the textures only from ``textures`` (a frozen function's inputs)."""
        cfg = self.config
        u, v, sigma = columns[:3]
        wo = (columns[3], columns[4])
        lights = [(columns[i], columns[i + 1]) for i in range(5, len(columns), 2)]
        if cfg.offset:
            features = _blend(textures.offset, cfg.offset_channels,
                              *_taps(self.backend, _wrap(u), _wrap(v), cfg.resolution, 0))
            depth = self._mlp(features + list(wo), "offset_mlp")[0]  # offset_scale folded in
            # sqrt(max(1 - (x^2 + y^2), min_cos^2)), the graph's order and rounding (`export._parallax`):
            # near the horizon wo_z is a small difference, whose rounding the shift multiplies
            with dr.scoped_set_flag(dr.JitFlag.FastMath, False):  # GPU: sqrt.rn, div.rn, not approx
                r2 = _product(wo[0], wo[0]) + _product(wo[1], wo[1])
                wo_z = dr.sqrt(dr.maximum(1.0 - r2, float(np.float32(cfg.offset_min_cos) ** 2)))
                shift = depth / wo_z
            u, v = u + _product(shift, wo[0]), v + _product(shift, wo[1])
        features = self._lookup(textures, _wrap(u), _wrap(v), sigma)
        # decoder: inputs (features, wi_x, wi_y, wo_x, wo_y); the wi-free part of layer 0 is shared
        w0, b0 = self.weights["decoder.0.weight"], self.weights["decoder.0.bias"]
        shared = _dense(features + list(wo), np.delete(w0, [cfg.channels, cfg.channels + 1], 1), b0)
        out = []
        for wi in lights:
            first = _dense(list(wi), w0[:, cfg.channels:cfg.channels + 2], None, shared)
            if cfg.layers > 1:
                first = [dr.maximum(x, 0.0) for x in first]
            out += self._head(self._mlp(first, "decoder", start=1))
        # Tie every answer to its lane: where the weights make an answer independent of the query
        # (a constant material), drjit folds it to a literal, which a frozen function would replay at
        # its first call's width. A lane whose position is not finite (`evaluate` refuses such
        # queries; a mesh's uv may hold them) answers 0.
        lane = dr.isfinite(u) & dr.isfinite(v)
        return [dr.select(lane, x, 0.0) for x in out]

    def _lookup(self, textures: Textures, u: Float, v: Float, sigma: Float) -> list[Float]:
        """Trilinear lookup of wrapped (u, v) at footprint sigma: the two nearest levels' bilinear taps
        (levels below the file's finest level read that level)."""
        cfg, jit = self.config, self.backend
        lod = dr.clip(dr.log2(dr.maximum(sigma, 1e-38) * cfg.resolution), float(self.finest), float(cfg.levels))
        lo = dr.floor(lod)
        t = lod - lo
        lo_level = jit.UInt32(lo)
        hi_level = dr.minimum(lo_level + 1, cfg.levels)
        rows, weights = [], []
        for level, share in ((lo_level, 1.0 - t), (hi_level, t)):
            size = dr.gather(jit.UInt32, textures.sizes, level)
            r, w = _taps(jit, u, v, size, dr.gather(jit.UInt32, textures.starts, level))
            rows += r
            weights += [x * share for x in w]
        return _blend(textures.pyramid, cfg.channels, rows, weights)

    def _mlp(self, x: list[Float], prefix: str, start: int = 0) -> list[Float]:
        """Layers start.. of MLP `prefix`: ReLU after every layer but the last."""
        layers = self.config.layers
        for i in range(start, layers):
            x = _dense(x, self.weights[f"{prefix}.{i}.weight"], self.weights[f"{prefix}.{i}.bias"])
            if i < layers - 1:
                x = [dr.maximum(value, 0.0) for value in x]
        return x

    def _head(self, out: list[Float]) -> Rgb:
        """The decoder's outputs -> RGB >= 0 (`core.head`)."""
        if self.head == "yuv":
            shadow = [self.shadow_floor + dr.rcp(1.0 + dr.exp(-s)) for s in out[3:]]
            yuv = _dense(out[:3], self.yuv_to_rgb.astype(np.float32), None)
            out = [(dr.exp(x) - 1.0) * m for x, m in zip(yuv, shadow)]
        return [dr.maximum(x, 0.0) for x in out]


def _product(a: Float, b: Float) -> Float:
    """a * b rounded on its own, as the ONNX graph rounds it, also where it is added to something next:
    on the CUDA backend ptxas fuses a product and a following sum into one fma (drjit emits them
    without a rounding mode), whose single rounding differs from ONNX Runtime's two. There the product
    is an fma with 0 (kept: constant propagation off), which rounds like a product and is not fused."""
    if dr.backend_v(a) != dr.JitBackend.CUDA:
        return a * b
    with dr.scoped_set_flag(dr.JitFlag.ConstantPropagation, False):
        return dr.fma(a, b, 0.0)


def _wrap(u: Float) -> Float:
    """Position -> position in [0, 1] (period 1); a non-finite one -> 0, so that its taps stay in
    their table (its lane answers 0: `KernelMaterial._trace`)."""
    wrapped = u - dr.floor(u)
    return dr.select(dr.isfinite(wrapped), wrapped, 0.0)


def _taps(jit: ModuleType, u: Float, v: Float, size, start) -> tuple[list, list[Float]]:
    """Rows (UInt32) and weights of the 4 bilinear taps of wrapped (u, v) on a ``size`` x ``size``
    level whose first row is ``start``; texel centres at (i + 0.5) / size, wrapping around. ``jit``:
    the arrays' drjit namespace."""
    sizef = jit.Float(size)
    x, y = u * sizef - 0.5, v * sizef - 0.5
    x0f, y0f = dr.floor(x), dr.floor(y)
    fx, fy = x - x0f, y - y0f
    size_i = jit.Int32(size)
    x0, y0 = jit.Int32(x0f), jit.Int32(y0f)
    x0, y0 = dr.select(x0 < 0, x0 + size_i, x0), dr.select(y0 < 0, y0 + size_i, y0)  # x0 >= -1
    x1 = dr.select(x0 + 1 >= size_i, 0, x0 + 1)
    y1 = dr.select(y0 + 1 >= size_i, 0, y0 + 1)
    start_i = jit.Int32(start)
    rows = [jit.UInt32(start_i + y * size_i + x) for y in (y0, y1) for x in (x0, x1)]
    weights = [wy * wx for wy in (1.0 - fy, fy) for wx in (1.0 - fx, fx)]
    return rows, weights


def _blend(table: Float, channels: int, rows: list, weights: list[Float]) -> list[Float]:
    """sum_k weights[k] * table row rows[k] -> `channels` Floats (the table is (T, channels) flat)."""
    array = type(table)
    out = [array(0.0)] * channels
    for row, weight in zip(rows, weights):
        index = row * channels
        for c in range(channels):
            out[c] = dr.fma(weight, dr.gather(array, table, index + c), out[c])
    return out


def _dense(x: list[Float], weight: np.ndarray, bias: np.ndarray | None,
           start: list[Float] | None = None) -> list[Float]:
    """weight (out, in) @ x + bias (or + ``start``), the weights as kernel literals."""
    array, out = type(x[0]), []
    for j in range(weight.shape[0]):
        acc = start[j] if start is not None else array(float(bias[j]) if bias is not None else 0.0)
        for k, value in enumerate(x):
            acc = dr.fma(value, float(weight[j, k]), acc)
        out.append(acc)
    return out


class KernelMaterials:
    """The materials of a model folder (``NAME.onnx``), evaluated as drjit kernels.

    Loads each file on first use. `kernel(name)` gives the `KernelMaterial` the renderer traces into
    its bounce; `evaluate` answers numpy queries (`contract.Evaluator`). ``backend``: the drjit
    namespace of the arrays (default ``drjit.llvm.ad``; a renderer passes its variant's).
    """

    def __init__(self, folder: str | Path, backend: ModuleType | None = None) -> None:
        self.backend = backend or importlib.import_module(DEFAULT_BACKEND)
        self._models = ModelFolder(folder, functools.partial(KernelMaterial, backend=self.backend), lazy=True)
        self.folder = self._models.folder
        self.errors = self._models.errors
        """{name: reason} of the files that failed to load."""

    def materials(self) -> list[str]:
        return self._models.names()

    def kernel(self, name: str) -> KernelMaterial:
        """The material `name` (loaded on first use); raises UnknownMaterial or ModelError."""
        return self._models.get(name)

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        """(N, 7) queries -> (N, 3) float32 RGB; query groups (N, 5 + 2 K) -> (N, 3 K)."""
        return self.kernel(material).evaluate(queries)
