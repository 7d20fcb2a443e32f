"""Renders of one method in one view, built once, cached on disk by everything that determines them."""

from __future__ import annotations

import gc
import hashlib
import logging
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from neumip.training.microgeometry.description import MaterialDescription, Microgeometry

from . import methods as M
from .cache import RenderCache
from .config import ReportConfig
from .views import View

log = logging.getLogger(__name__)

CACHE_VERSION = 3
"""Bump when a change in this package changes what a cached render would hold."""
NEURAL_VERSION = 6
"""Bump when `neumip_path` renders a neural material differently, or at another cost: the cached
renders hold their times (2: per-sample footprints; 3: query groups, whose graph rounds the decoder's
first sum in another order; 4: answers computed in the render's kernels, `client.kernel`, which round
in their own order; 5: their parallax in the graph's order; 6: a material on nearly every lane
computed without compaction, the same images sooner)."""


def file_digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


class MaterialRenderer:
    """Every method's scenes of one material; renders through the cache."""

    def __init__(self, name: str, desc: MaterialDescription, geo: Microgeometry, models: Path, evaluator,
                 config: ReportConfig, cache: RenderCache) -> None:
        from neumip.client.mitsuba import render as R

        self._R = R
        self.name, self.desc, self.geo, self.config, self.cache = name, desc, geo, config, cache
        self.evaluator = evaluator
        self.models = {"N": name, "N0": f"{name}_nooffset"}
        self.digests = {m: file_digest(models / f"{model}.onnx") for m, model in self.models.items()
                        if (models / f"{model}.onnx").exists()}
        if "N" not in self.digests:
            raise FileNotFoundError(f"no model {models / (name + '.onnx')}")
        self.resolution = evaluator.kernel(name).config.resolution
        self._scenes: dict = {}
        self._warm: set = set()

    @property
    def methods(self) -> tuple[str, ...]:
        return tuple(m for m in M.METHODS if m not in M.NEURAL or m in self.digests)

    def spec(self, view: View) -> M.SceneSpec:
        return M.SceneSpec(view, self.config.film, self.resolution)

    def mip_level(self, view: View) -> int:
        return M.mip_level_for(self.spec(view), self.geo.base_color.shape[0])

    def key(self, view: View, method: str, spp: int, seed: int) -> dict:
        key = {"version": CACHE_VERSION, "material": self.desc.to_dict(), "view": asdict(view),
               "film": asdict(self.config.film), "resolution": self.resolution, "method": method,
               "spp": spp, "seed": seed}
        if method in M.NEURAL:
            key["model"], key["neural_version"] = self.digests[method], NEURAL_VERSION
        return key

    def scene(self, view: View, method: str):
        """The Mitsuba scene (built on first use; one view's scenes are kept until :meth:`release`)."""
        mi = self._R.mi
        if (view.name, method) not in self._scenes:
            spec = self.spec(view)
            if method == "R":
                d = M.reference_scene(mi, spec, self.geo)
            elif method in M.NEURAL:
                d = M.neural_scene(mi, spec, self.models[method])
            else:
                d = M.classical_scene(mi, spec, self.geo, self.mip_level(view) if method == "Cmip" else None)
            self._scenes[(view.name, method)] = mi.load_dict(d)
        return self._scenes[(view.name, method)]

    def release(self) -> None:
        """Drop every scene (and what drjit holds for it)."""
        self._scenes.clear()
        self._warm.clear()
        gc.collect()

    def render(self, view: View, method: str, spp: int, seed: int, timed: bool = True) -> tuple[np.ndarray, float, bool]:
        """``(image, seconds, fresh)``: from the cache, or rendered and stored.

        A timed render first renders the same scene at the same spp once, untimed (another seed):
        drjit compiles a kernel per scene and sample count, and that compilation is not counted.
        """
        key = self.key(view, method, spp, seed)
        cached = self.cache.get(key)
        if cached is not None:
            return cached.image, cached.seconds, False
        scene = self.scene(view, method)
        if timed and (view.name, method, spp) not in self._warm:
            self._render(scene, spp, 999_999)
            self._warm.add((view.name, method, spp))
        start = time.perf_counter()
        image = self._render(scene, spp, seed)
        seconds = time.perf_counter() - start
        self.cache.put(key, image, seconds)
        return image, seconds, True

    def _render(self, scene, spp: int, seed: int) -> np.ndarray:
        cfg = self._R.RenderConfig(spp=spp, seed=seed, max_lanes=self.config.max_lanes)
        result = self._R.render_scene(scene, self.evaluator, cfg)
        image = result.image[..., :3]
        if not np.all(np.isfinite(image)):
            raise self._R.RenderError(f"{self.name}: non-finite pixels in a render")
        return image
