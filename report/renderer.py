"""Renders of one method in one view, built once, cached on disk by everything that determines them."""

from __future__ import annotations

import gc
import hashlib
import logging
import os
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from neumip.groundtruth.description import MaterialDescription, Microgeometry

from neumip.report import methods as M
from neumip.report.cache import RenderCache
from neumip.report.config import ReportConfig
from neumip.report.views import View, film_for_tiles

log = logging.getLogger(__name__)

CACHE_VERSION = 6
"""Bump when a change in this package (or in `render_scene`) changes what a cached render would hold (5: a
render's passes after its first have seeds of their own, `render.pass_seed`, not the next renders'; 6: light
samples choose the sun or the environment in proportion to their irradiance, `views.emitter_dicts`)."""
NEURAL_VERSION = 8
"""Bump when `neumip_path` renders a neural material differently, or at another cost: the cached
renders hold their times (2: per-sample footprints; 3: query groups, whose graph rounds the decoder's
first sum in another order; 4: answers computed in the render's kernels, `client.kernel`, which round
in their own order; 5: their parallax in the graph's order; 6: a material on nearly every lane
computed without compaction, the same images sooner; 7: directions sampled from the model's sampling
lobe as well as the cosine, `client.mitsuba.bsdf`; 8: next-event estimation towards every emitter,
`PathConfig.all_emitters`)."""


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
        self.models = M.neural_models(name, models)
        self.digests = {m: file_digest(path) for m, path in self.models.items()}
        self.resolution = desc.resolution
        """Texels per tile in which the views' footprints are counted: the description's maps', so
        every model of the material (64^2, 256^2, ...) is judged on the same views."""
        self._scenes: dict = {}

    @property
    def methods(self) -> tuple[str, ...]:
        return tuple(m for m in M.METHODS if m not in M.NEURAL or m in self.digests)

    def spec(self, view: View) -> M.SceneSpec:
        film = self.config.film
        if self.geo.height.shape[0] > 1:  # real geometry: keep the tiles R must build within bounds
            film = film_for_tiles(view, film, self.resolution, self.config.max_reference_tiles)
        return M.SceneSpec(view, film, self.resolution)

    def mip_level(self, view: View) -> int:
        return M.mip_level_for(self.spec(view), self.geo.base_color.shape[0])

    def key(self, view: View, method: str, spp: int, seed: int) -> dict:
        key = {"version": CACHE_VERSION, "material": self.desc.to_dict(), "view": asdict(view),
               "film": asdict(self.spec(view).film), "resolution": self.resolution, "method": method,
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
                d = M.neural_scene(mi, spec, self.models[method].stem)
            else:
                d = M.classical_scene(mi, spec, self.geo, self.mip_level(view) if method == "Cmip" else None)
            self._scenes[(view.name, method)] = mi.load_dict(d)
        return self._scenes[(view.name, method)]

    def release(self) -> None:
        """Drop every scene (and what drjit holds for it)."""
        self._scenes.clear()
        gc.collect()

    def render(self, view: View, method: str, spp: int, seed: int,
               fresh: bool = False) -> tuple[np.ndarray, float, float]:
        """``(image, seconds, load)`` from the cache, or rendered and stored: the render's wall time
        and the 1-minute load average of the machine when it finished (nan where not measured). `fresh`:
        rendered (and timed) anew even where cached."""
        key = self.key(view, method, spp, seed)
        cached = None if fresh else self.cache.get(key)
        if cached is not None:
            return cached.image, cached.seconds, cached.load
        scene = self.scene(view, method)
        start = time.perf_counter()
        image = self._render(scene, spp, seed)
        seconds = time.perf_counter() - start
        load = os.getloadavg()[0]
        self.cache.put(key, image, seconds, load)
        return image, seconds, load

    def cached(self, view: View, method: str, spp: int, seed: int) -> bool:
        return self.cache.path(self.key(view, method, spp, seed)).exists()

    def forget(self, view: View, method: str, spp: int, seed: int) -> None:
        self.cache.forget(self.key(view, method, spp, seed))

    def warm_up(self, view: View, method: str) -> None:
        """One untimed 1-spp render of a freshly built scene (not stored): its first launch pays
        allocations and kernel look-ups that a timed render should not count."""
        self._render(self.scene(view, method), 1, 999_999)

    def _render(self, scene, spp: int, seed: int) -> np.ndarray:
        cfg = self._R.RenderConfig(spp=spp, seed=seed, max_lanes=self.config.max_lanes)
        result = self._R.render_scene(scene, self.evaluator, cfg)
        image = result.image[..., :3]
        if not np.all(np.isfinite(image)):
            raise self._R.RenderError(f"{self.name}: non-finite pixels in a render")
        return image
