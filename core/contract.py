"""The query contract: the one definition of a NeuMIP shading query, shared by every part.

Training, export, the data generator, the server and the renderer all import this module; nothing
else restates the layout. A query is 7 float32 values::

    u, v, sigma, wi_x, wi_y, wo_x, wo_y

- ``u, v``: position on the material in tile units; the material repeats with period 1.
  Any finite magnitude is accepted; the model reads ``u - floor(u)``.
- ``sigma``: standard deviation of the Gaussian pixel footprint, in tile units. With a finest level of
  ``R x R`` texels (``R = 2**k``) the paper's models read the level of detail ``clamp(log2(sigma * R), 0, k)``
  (:func:`level_of_detail`): one finest texel or less reads the finest level, a whole tile or more
  reads the 1 x 1 level; a model may raise it by whole levels (`MaterialConfig.lod_bias`: its finest
  level then answers a quarter texel and less, say). ``sigma <= 0`` therefore means "finest"; huge sigma
  means "coarsest". The footprint's meaning is the same for every model: the engine need not know.
- ``wi`` (towards the light) and ``wo`` (towards the viewer): unit vectors in the local frame
  (z = normal, x along +u, y along +v), given by x and y; ``z = sqrt(1 - x^2 - y^2)``.
  ``x^2 + y^2`` up to ``1 + DIRECTION_TOLERANCE`` is accepted (a grazing direction, z = 0);
  beyond that the query is rejected.

The answer is RGB float32 >= 0: the multi-resolution BTF under unit irradiance on the reference
plane, used like a BRDF (a flat Lambertian plane of albedo ``a`` answers ``a / pi``).

Every value must be finite: NaN or Inf anywhere is an error, never a silent NaN answer.

**Query groups.** A renderer asks two or more questions at each shading point: the same ``u, v,
sigma, wo`` under several light directions (next-event estimation and the sampled direction). A group
row carries them once: the 7 columns of its first query, then ``wi_x, wi_y`` of each further light,
``5 + 2 K`` columns for ``K`` lights (:func:`group_width`). Its answer row holds the ``K`` RGB answers
in the same order, ``3 K`` columns. A model answers light ``j`` of a group with the same bits as the
single query ``(u, v, sigma, wi_j, wo)``; it evaluates the position's part (the neural offset and the
texture lookups) once per group. A plain (N, 7) buffer is a buffer of groups of one light.

**Versions.** A model file declares the contract it answers (`META_CONTRACT`). Version 2 (this one):
every model takes query groups. Version 1 files (exported before groups were part of the contract)
are refused by every engine with one error that names the command that upgrades them
(:func:`version_problem`: ``neumip export OLD.onnx -o NEW.onnx``).
"""

from __future__ import annotations

import json
import math
from typing import NamedTuple, Protocol

import numpy as np

from neumip.core.errors import NeumipError

CONTRACT_VERSION = "2"
"""Version of the query contract; travels in every model's metadata. 2: query groups are part of it."""

UPGRADABLE_VERSIONS = ("1",)
"""Older contract versions whose files `neumip export OLD.onnx -o NEW.onnx` rewrites in this one."""

QUERY_FIELDS = ("u", "v", "sigma", "wi_x", "wi_y", "wo_x", "wo_y")
"""Column order of a query row."""

RGB_FIELDS = ("r", "g", "b")
"""Column order of an answer row."""

QUERY_DIM = len(QUERY_FIELDS)
RGB_DIM = len(RGB_FIELDS)
LUMINANCE = (0.2126, 0.7152, 0.0722)
"""Rec. 709 luminance of linear RGB answers: the weights of R, G, B."""
DTYPE = np.dtype("<f4")
"""Little-endian float32: the wire and in-memory type of queries and answers."""

U, V, SIGMA, WI_X, WI_Y, WO_X, WO_Y = range(QUERY_DIM)

MAX_LIGHTS = 64
"""Most lights a query group may carry."""

DIRECTION_TOLERANCE = 1e-3
"""How far ``x^2 + y^2`` of a direction may exceed 1 (rounding) before the query is rejected."""

# Names of the ONNX graph's tensors and metadata keys (the exported format's half of the contract).
ONNX_INPUT = "queries"
ONNX_OUTPUT = "rgb"
META_CONTRACT = "neumip.contract_version"
META_CONFIG = "neumip.config"
META_DESCRIPTION = "neumip.description"
META_VALIDATION = "neumip.validation"
META_TRIM = "neumip.trim"
"""JSON of what `neumip trim` cut from a model (absent: an untrimmed model)."""
META_SAMPLING = "neumip.sampling"
"""JSON ``{"alpha": a, "weight": w}`` of the material's sampling lobe (`SamplingLobe`); absent: sample
the cosine alone."""


class SamplingLobe(NamedTuple):
    """Where a renderer should send the directions it samples at a neural surface, besides the cosine.

    A GGX lobe of roughness ``alpha`` about the mirror direction of the macro normal, sampled with
    probability ``weight`` and the cosine otherwise (a defensive mixture: the pdf is never below
    ``(1 - weight) cos / pi``). It only moves noise; the answers and the image's mean stay the same.
    Written at training from the material's maps (`training.microgeometry.lobe`).
    """

    alpha: float
    weight: float

    def to_json(self) -> str:
        return json.dumps({"alpha": self.alpha, "weight": self.weight})


class SamplingLobeError(NeumipError, ValueError):
    """A model file's `META_SAMPLING` that is not a valid lobe."""


def sampling_lobe(metadata: dict[str, str]) -> SamplingLobe | None:
    """The `SamplingLobe` a model file's metadata declares (None: none, sample the cosine).

    Raises SamplingLobeError on a value that is not ``{"alpha": 0 < a <= 1, "weight": 0 <= w < 1}``.
    """
    text = metadata.get(META_SAMPLING)
    if not text:
        return None
    try:
        data = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise SamplingLobeError(f"bad {META_SAMPLING} metadata {text[:80]!r}: not JSON ({exc})") from exc
    return as_sampling_lobe(data, f"{META_SAMPLING} metadata {text[:80]!r}")


def as_sampling_lobe(data: object, what: str = "sampling lobe") -> SamplingLobe | None:
    """``{"alpha": 0 < a <= 1, "weight": 0 <= w < 1}`` (decoded JSON) -> its `SamplingLobe` (None where
    the weight is 0); anything else raises SamplingLobeError naming ``what``."""
    values = [data.get(key) for key in ("alpha", "weight")] if isinstance(data, dict) else []
    if len(values) != 2 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
        raise SamplingLobeError(f"bad {what}: it must be {{\"alpha\": number, \"weight\": number}}")
    try:
        alpha, weight = (float(v) for v in values)
    except OverflowError:  # an integer beyond float range
        alpha = weight = math.nan
    if not (0 < alpha <= 1 and 0 <= weight < 1):
        raise SamplingLobeError(f"bad {what}: alpha must be in (0, 1] and weight in [0, 1)")
    return SamplingLobe(alpha, weight) if weight > 0 else None


class QueryError(NeumipError, ValueError):
    """A query buffer that breaks the contract (shape, dtype or values)."""


def version_problem(metadata: dict[str, str], source: str = "OLD.onnx") -> str | None:
    """Why a model file whose ONNX metadata is `metadata` cannot be served by this build (None: it can):
    the one wording every engine gives a file of another contract version, naming the command that
    upgrades an older one (`source`: the file's path, as the command should read it)."""
    version = metadata.get(META_CONTRACT)
    if version == CONTRACT_VERSION:
        return None
    if version in UPGRADABLE_VERSIONS:
        return (f"query contract version {version} (exported before query groups were part of the contract), "
                f"this build reads version {CONTRACT_VERSION}: upgrade the file (same weights and answers) "
                f"with `neumip export {source} -o NEW.onnx`")
    if version is None:
        return f"not a neumip material (no {META_CONTRACT} in its ONNX metadata)"
    return (f"query contract version {version[:20]!r}, this build reads version {CONTRACT_VERSION} "
            f"(and upgrades version {', '.join(UPGRADABLE_VERSIONS)} with `neumip export`)")


def engine_problem(metadata: dict[str, str], source: str = "OLD.onnx") -> str | None:
    """Why an engine cannot serve a model file whose ONNX metadata is `metadata` (None: it can). A file
    that declares a contract version must declare this one (`version_problem`); a graph made by another
    tool may declare none, and is then judged by its graph alone (every engine: ONNX Runtime, the
    server, the in-kernel engine). A malformed sampling lobe (`sampling_lobe`) is a problem too."""
    problem = version_problem(metadata, source) if META_CONTRACT in metadata else None
    if problem is None:
        try:
            sampling_lobe(metadata)
        except SamplingLobeError as exc:
            return str(exc)
    return problem


def level_of_detail(sigma: np.ndarray, resolution: int, bias: int = 0) -> np.ndarray:
    """Continuous level of detail for footprint ``sigma`` on a pyramid whose finest level is ``resolution``,
    raised by ``bias`` levels (a model's `MaterialConfig.lod_bias`: its finest level answers footprints of
    ``2^-bias`` texels and less).

    (N,) float -> (N,) float in ``[0, log2(resolution)]``; 0 is the finest level.
    """
    levels = int(math.log2(resolution))
    with np.errstate(divide="ignore", invalid="ignore"):
        lod = np.log2(np.maximum(sigma, 0) * resolution) + bias
    return np.clip(np.nan_to_num(lod, nan=0.0, neginf=0.0), 0, levels)


def sigma_for_level(level: float, resolution: int, bias: int = 0) -> float:
    """Inverse of :func:`level_of_detail`: the footprint whose level is exactly ``level``."""
    return 2.0 ** (level - bias) / resolution


MIN_SAMPLE_FOOTPRINT = 1 / 8
"""Smallest share of the pixel footprint a sample reads (pbrt-v4's floor)."""


def sample_footprint(spp: int) -> float:
    """Share of a pixel's footprint (std) that one of ``spp`` samples per pixel queries: the samples
    average over the pixel themselves, so each reads ``max(1/8, 1/sqrt(spp))`` of it (pbrt-v4's rule)."""
    return max(MIN_SAMPLE_FOOTPRINT, 1 / math.sqrt(max(spp, 1)))


def group_width(lights: int) -> int:
    """Columns of a query group of ``lights`` light directions: ``5 + 2 lights`` (7 for one)."""
    if not 1 <= lights <= MAX_LIGHTS:
        raise QueryError(f"a query group holds 1 to {MAX_LIGHTS} lights, got {lights}")
    return QUERY_DIM + 2 * (lights - 1)


def group_lights(width: int) -> int:
    """Lights of a query group ``width`` columns wide (the inverse of :func:`group_width`)."""
    lights = (width - QUERY_DIM) // 2 + 1
    if width < QUERY_DIM or (width - QUERY_DIM) % 2 or lights > MAX_LIGHTS:
        raise QueryError(
            f"queries must have shape (N, {QUERY_DIM}) ({', '.join(QUERY_FIELDS)}), or (N, 5 + 2 K) for a "
            f"group of K <= {MAX_LIGHTS} lights (wi_x, wi_y of each further light after them), "
            f"got {width} columns"
        )
    return lights


def as_queries(data: object, *, copy: bool = False, groups: bool = False) -> np.ndarray:
    """Check a buffer against the contract and return it as a C-contiguous (N, 7) float32 array;
    with ``groups``, (N, 5 + 2 K) query groups of any K (:func:`group_lights` reads K).

    Raises :class:`QueryError` saying what is wrong: not 2-D, wrong column count, non-numeric,
    non-finite values, or directions outside the unit disk. N = 0 is valid and gives an empty array.
    """
    arr = np.asarray(data)
    if arr.dtype.kind not in "fiu":
        raise QueryError(f"queries must be numeric, got dtype {arr.dtype}")
    if arr.ndim != 2 or (arr.shape[1] != QUERY_DIM and not groups):
        raise QueryError(
            f"queries must have shape (N, {QUERY_DIM}) ({', '.join(QUERY_FIELDS)}), got {arr.shape}"
        )
    group_lights(arr.shape[1])
    arr = np.ascontiguousarray(arr, dtype=DTYPE)
    if copy:
        arr = arr.copy()
    check_values(arr)
    return arr


def check_values(queries: np.ndarray) -> None:
    """Raise :class:`QueryError` if float32 ``queries`` (N, 7), or query groups (N, 5 + 2 K), hold
    non-finite values or bad directions."""
    if queries.size == 0:
        return
    finite = np.isfinite(queries)
    if not finite.all():
        row, col = np.argwhere(~finite)[0]
        extra = col - QUERY_DIM
        name = QUERY_FIELDS[col] if extra < 0 else f"wi_{'xy'[extra % 2]} of light {extra // 2 + 2}"
        raise QueryError(f"queries must be finite: row {row} column {name} is {queries[row, col]}")
    extra = [(f"wi of light {j + 2}", (QUERY_DIM + 2 * j, QUERY_DIM + 2 * j + 1))
             for j in range(group_lights(queries.shape[1]) - 1)]
    for name, (cx, cy) in [("wi", (WI_X, WI_Y)), ("wo", (WO_X, WO_Y))] + extra:
        r2 = queries[:, cx] ** 2 + queries[:, cy] ** 2
        bad = r2 > 1.0 + DIRECTION_TOLERANCE
        if bad.any():
            row = int(np.argmax(bad))
            raise QueryError(
                f"{name} must be the (x, y) of a unit vector (x^2 + y^2 <= 1, up to "
                f"{1 + DIRECTION_TOLERANCE:g} for rounding): row {row} has x^2 + y^2 = {r2[row]:.9g}"
            )


def ungroup(groups: np.ndarray) -> np.ndarray:
    """Query groups (N, 5 + 2 K) -> the (N K, 7) single queries they hold (row ``n K + j``: light j
    of group n), whose (N K, 3) answers reshape to the groups' (N, 3 K)."""
    n, lights = groups.shape[0], group_lights(groups.shape[1])
    out = np.empty((n, lights, QUERY_DIM), DTYPE)
    out[:] = groups[:, None, :QUERY_DIM]
    for j in range(1, lights):
        out[:, j, WI_X:WI_Y + 1] = groups[:, QUERY_DIM + 2 * (j - 1):QUERY_DIM + 2 * j]
    return out.reshape(n * lights, QUERY_DIM)


def pack_queries(
    u: np.ndarray,
    v: np.ndarray,
    sigma: np.ndarray,
    wi: np.ndarray,
    wo: np.ndarray,
) -> np.ndarray:
    """Assemble (N, 7) float32 queries from u, v, sigma (each (N,)) and wi, wo ((N, 2) or (N, 3))."""
    wi, wo = np.asarray(wi), np.asarray(wo)
    cols = [u, v, sigma, wi[:, 0], wi[:, 1], wo[:, 0], wo[:, 1]]
    return np.ascontiguousarray(np.stack([np.asarray(c, dtype=DTYPE) for c in cols], axis=1))


def random_queries(
    n: int,
    seed: int = 0,
    *,
    max_zenith_deg: float = 85.0,
    u_range: tuple[float, float] = (-2.0, 3.0),
    log2_sigma_range: tuple[float, float] = (-11.0, 1.0),
) -> np.ndarray:
    """(n, 7) float32 valid queries, uniformly random: the worst case for a texture cache.

    ``u, v`` uniform in ``u_range`` (several tiles, so seams and wrap-around are exercised), ``sigma``
    log-uniform (base 2) in ``log2_sigma_range`` (every level of detail and beyond both ends), ``wi`` and
    ``wo`` uniform on the projected disk up to ``max_zenith_deg``. The one generator that tests,
    benchmarks and smoke checks share; training data follows ``training.microgeometry.sampling``.
    """
    rng = np.random.default_rng(seed)
    u = rng.uniform(*u_range, n)
    v = rng.uniform(*u_range, n)
    sigma = 2.0 ** rng.uniform(*log2_sigma_range, n)
    r = math.sin(math.radians(max_zenith_deg)) * np.sqrt(rng.uniform(0, 1, (n, 2)))
    phi = rng.uniform(0, 2 * np.pi, (n, 2))
    wi = np.stack([r[:, 0] * np.cos(phi[:, 0]), r[:, 0] * np.sin(phi[:, 0])], 1)
    wo = np.stack([r[:, 1] * np.cos(phi[:, 1]), r[:, 1] * np.sin(phi[:, 1])], 1)
    return pack_queries(u, v, sigma, wi, wo)


def direction_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """z of the unit vector with components x, y (0 for grazing or slightly-outside directions)."""
    return np.sqrt(np.maximum(1.0 - x * x - y * y, 0.0))


def as_rgb(data: object, rows: int, lights: int = 1) -> np.ndarray:
    """Check an answer buffer: (rows, 3 lights) float32, finite. Raises :class:`QueryError` otherwise."""
    arr = np.asarray(data)
    if arr.shape != (rows, RGB_DIM * lights):
        raise QueryError(f"answer must have shape ({rows}, {RGB_DIM * lights}), got {arr.shape}")
    arr = np.ascontiguousarray(arr, dtype=DTYPE)
    if not np.isfinite(arr).all():
        raise QueryError("answer holds non-finite values")
    return arr


class Evaluator(Protocol):
    """Anything that answers queries for named materials: in-process or over HTTP."""

    def materials(self) -> list[str]:
        """Names of the materials this evaluator can answer for."""
        ...

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        """(N, 7) float32 queries -> (N, 3) float32 RGB for ``material``; query groups (N, 5 + 2 K)
        -> (N, 3 K)."""
        ...
