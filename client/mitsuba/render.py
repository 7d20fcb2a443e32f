"""Render a scene with neural materials: load, bind an evaluator, render in passes, write atomically.

Memory of a wavefront grows with its lane count (about 680 MiB per million lanes), so an image of
``W x H`` pixels at ``spp`` samples is rendered as several `mi.render` passes of at most
``RenderConfig.max_lanes`` lanes each (each its own seed, `pass_seed`), averaged. The image file is written only
after every pass succeeded, through a temporary file and an atomic rename: a failed render leaves
no file behind (and never a partial one under the requested name).
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from neumip.core.errors import NeumipError
from neumip.core.files import atomic_write

from neumip.client.mitsuba.bsdf import dr, mi
from neumip.client.mitsuba.integrator import NeuMIPPathIntegrator
from neumip.client.mitsuba.shading import NestedNeuralBSDF, ShadingStats, neural_bsdfs

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".exr")


class RenderError(NeumipError, RuntimeError):
    """A render that could not complete; the message says why (no image was written)."""


@dataclass
class RenderConfig:
    """How an image is rendered."""

    spp: int | None = None
    """Samples per pixel; None uses the scene sensor's sampler count."""
    max_lanes: int = 2**21
    """Most lanes (pixels x samples) in one pass; bounds memory (~680 MiB per million lanes)."""
    seed: int = 0
    """Seed of the render: its first pass's; the others' follow from it (`pass_seed`)."""
    threads: int = 0
    """Mitsuba worker threads (0: leave drjit's default)."""
    footprint_spp: int | None = None
    """spp whose per-sample footprint the queries use (`contract.sample_footprint`); None: ``spp``.
    `neumip budget` traces a few samples with the footprints of the scene's full spp."""


@dataclass
class RenderResult:
    """An image and what producing it cost."""

    image: np.ndarray
    """(H, W, C) float32, linear radiance (C = 3 for RGB films, more with alpha/AOVs)."""
    seconds: float
    """Wall time of all passes."""
    passes: int
    """Number of `mi.render` passes."""
    spp: int
    """Samples per pixel rendered."""
    stats: ShadingStats = field(default_factory=ShadingStats)
    """Neural evaluation cost (queries, calls, seconds)."""


def load_scene(path: str | os.PathLike, **params: str) -> mi.Scene:
    """Load a Mitsuba XML scene (``params`` fill its ``$name`` defaults, as Mitsuba's ``-D``).

    Raises FileNotFoundError, or RenderError with Mitsuba's reason (or where a `neumip` BSDF is
    wrapped in another BSDF, e.g. `twosided`: not supported).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"scene {path} does not exist")
    try:
        scene = mi.load_file(str(path), **params)
    except Exception as exc:  # mitsuba raises plain Exception/RuntimeError with its parser message
        raise RenderError(f"cannot load scene {path}: {exc}") from exc
    try:
        neural_bsdfs(scene)  # refuses a neumip BSDF wrapped in another BSDF
    except NestedNeuralBSDF as exc:
        raise RenderError(f"cannot load scene {path}: {exc}") from exc
    return scene


def pass_plan(pixels: int, spp: int, max_lanes: int) -> list[int]:
    """Samples per pass so that ``pixels * samples <= max_lanes`` (at least 1 sample a pass)."""
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    per_pass = max(1, min(spp, max_lanes // max(pixels, 1)))
    count = math.ceil(spp / per_pass)
    base, extra = divmod(spp, count)  # balanced: passes differ by at most one sample
    return [base + (i < extra) for i in range(count)]


def render_scene(
    scene: mi.Scene,
    evaluator,
    config: RenderConfig | None = None,
    integrator: mi.Integrator | None = None,
    on_pass: Callable[[int, int], None] | None = None,
) -> RenderResult:
    """Render ``scene`` with its `neumip_path` integrator (or ``integrator``) and ``evaluator``.

    ``on_pass(done, total)`` is called after each pass. Raises RenderError (with the evaluator's or
    Mitsuba's real error as the cause) if any pass fails.
    """
    config = config or RenderConfig()
    integrator = integrator or scene.integrator()
    neural = isinstance(integrator, NeuMIPPathIntegrator)
    if not neural and neural_bsdfs(scene):
        raise RenderError(
            f"the scene has neumip materials but its integrator is {type(integrator).__name__}; "
            "use <integrator type=\"neumip_path\"/>"
        )
    sensor = scene.sensors()[0]
    spp = config.spp or sensor.sampler().sample_count()
    if neural:
        integrator.bind(scene, evaluator, footprint_spp=config.footprint_spp or spp)
    if config.threads:
        dr.set_thread_count(config.threads)
    w, h = sensor.film().crop_size()
    plan = pass_plan(w * h, spp, config.max_lanes)
    log.info("rendering %dx%d at %d spp in %d pass(es)", w, h, spp, len(plan))
    start = time.perf_counter()
    total = None
    for i, k in enumerate(plan):
        image = _render_pass(scene, integrator, k, pass_seed(config.seed, i))
        total = image * k if total is None else total + image * k
        if on_pass:
            on_pass(i + 1, len(plan))
    stats = integrator.shading.stats if neural else ShadingStats()
    return RenderResult(total / spp, time.perf_counter() - start, len(plan), spp, stats)


def pass_seed(seed: int, index: int) -> int:
    """Seed of pass `index` of a render seeded `seed`: `seed` itself for the first pass, a 32-bit mix of
    (seed, index) for the others. Renders of nearby seeds share no pass: with ``seed + index``, two-pass renders
    of seeds 0 and 1 both held the pass of seed 1, and their difference saw half their noise."""
    if index == 0:
        return seed
    return int(np.random.SeedSequence([seed, index]).generate_state(1)[0])


def _render_pass(scene, integrator, spp: int, seed: int) -> np.ndarray:
    """One `mi.render` pass -> (H, W, C) float32; unwraps errors raised inside `sample()`."""
    try:
        image = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
        return np.array(image, dtype=np.float32)
    except Exception as exc:
        cause = _root_cause(exc)
        raise RenderError(f"render pass (seed {seed}) failed: {cause}") from cause


def _root_cause(exc: BaseException) -> BaseException:
    """drjit wraps exceptions raised in Python plugins (``drjit.custom(...): error while ...``);
    the real one is the cause of those wrappers (its own causes are kept as they are)."""
    while exc.__cause__ is not None and str(exc).startswith("drjit."):
        exc = exc.__cause__
    return exc


def write_image(image: np.ndarray, path: str | os.PathLike) -> Path:
    """Write (H, W, C) linear radiance to ``.png`` (sRGB, 8 bit) or ``.exr`` (float), atomically."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ValueError(f"output must end in {' or '.join(IMAGE_SUFFIXES)}, got {path.name}")
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.ascontiguousarray(image[..., :3], dtype=np.float32)
    bitmap = mi.Bitmap(rgb, pixel_format=mi.Bitmap.PixelFormat.RGB)
    if suffix == ".png":
        bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True)
    return atomic_write(path, lambda tmp: bitmap.write(str(tmp)), keep_suffix=True)  # the format: by the suffix
