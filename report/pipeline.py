"""The image comparison of one material: every view, every method, scores, bias/noise, spp ladders.

Per view: the reference R is the mean of two seeds at ``reference_spp`` (its own noise is measured
from their difference). Each compared method is rendered with seeds 0 and 1 at ``spp``: seed 0 gives
its scores, the pair its noise, and error - noise - reference noise its bias.

Views with a ladder (the ladder light's) render every method, R included, at each spp of the
ladder in interleaved rounds (R N N0 C Cmip, R N N0 C Cmip, ...; round r uses seed r, so rounds 0
and 1 at ``spp`` are the two scored renders). Only the method being rendered has a scene alive in
the process: it is built, warmed up by an untimed 1-spp render, rendered at every rung, and
released (drjit's virtual calls dispatch over every live shape, so the reference's many instances
slowed every other render in the process by up to 9x while they existed). Round 0 is untimed (it
compiles the kernels); the reported seconds are the fastest of the ``rounds`` timed rounds (a shared machine
only adds time), with the machine's load average beside them, and a linear
fit gives the per-spp slope and the fixed cost.
The timed rounds of a view come from one run: where any of them is not in the cache, all are rendered
anew (a cached R timed on a quiet machine against an N timed now on a busy one halved the ratios once).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from neumip.report import metrics as Q
from neumip.report.renderer import MaterialRenderer
from neumip.report.views import VIEWS, View

log = logging.getLogger(__name__)

REFERENCE_SEEDS = (1000, 1001)
"""Seeds of the reference's two renders (apart from the methods' seeds 0, 1, ...)."""


def scored_methods(renderer: MaterialRenderer, view: View) -> tuple[str, ...]:
    """Methods rendered in ``view``: R as a method only where it is timed (the ladder views)."""
    return tuple(m for m in renderer.methods if m != "R" or view.ladder)


def view_steps(renderer: MaterialRenderer, view: View) -> int:
    """Renders one view takes (for progress bars)."""
    cfg, methods = renderer.config, scored_methods(renderer, view)
    if view.ladder:
        return 2 + (cfg.rounds + 1) * len(methods) * len(cfg.ladder)
    return 2 + 2 * len(methods)


def run_view(renderer: MaterialRenderer, view: View, tick: Callable[[], None] = lambda: None) -> dict:
    """Scores of every method in ``view``: ``{"reference": {...}, "methods": {method: {spp: {...}}},
    "fits": {method: {...}}}`` plus the images the report shows (``"images"``, not JSON)."""
    cfg = renderer.config
    images: dict = {}
    timings: dict = {}

    def render(method: str, spp: int, seed: int, fresh: bool = False) -> None:
        image, secs, load = renderer.render(view, method, spp, seed, fresh)
        images[(method, spp, seed)] = image
        timings[(method, spp, seed)] = (secs, load)
        tick()

    for seed in REFERENCE_SEEDS:
        render("R", cfg.reference_spp, seed)
    renderer.release()
    methods = scored_methods(renderer, view)
    if view.ladder:
        # Timings are compared as ratios, so they must come from one run: where any timed rung is not
        # cached (a new model, say), every method's timed rungs are rendered anew beside it. `retime` forgets
        # them first, so that a run stopped half-way leaves them missing, not half of them from another run.
        timed = [(m, s, rnd) for m in methods for s in cfg.ladder for rnd in range(1, cfg.rounds + 1)]
        if cfg.retime:
            for rung in timed:
                renderer.forget(view, *rung)
        fresh = not all(renderer.cached(view, *rung) for rung in timed)
        for rnd in range(cfg.rounds + 1):
            for method in methods:
                if rnd > 0 and (fresh or not all(renderer.cached(view, method, s, rnd) for s in cfg.ladder)):
                    renderer.warm_up(view, method)
                for spp in cfg.ladder:
                    render(method, spp, rnd, fresh and rnd > 0)
                renderer.release()
    else:
        for method in methods:
            for seed in (0, 1):
                render(method, cfg.spp, seed)
            renderer.release()
    return score_view(renderer, view, images, timings)


def score_view(renderer: MaterialRenderer, view: View, images: dict, timings: dict) -> dict:
    cfg = renderer.config
    r0, r1 = (images[("R", cfg.reference_spp, s)] for s in REFERENCE_SEEDS)
    reference = (r0 + r1) / 2
    ref_noise = Q.noise_mse(r0, r1) / 2  # noise of one render / 2: the mean of two
    exposure = Q.exposure_for(reference)
    out = {
        "reference": {"spp": 2 * cfg.reference_spp, "noise_mse": ref_noise,
                      "seconds": timings[("R", cfg.reference_spp, REFERENCE_SEEDS[0])][0],
                      "mean_luminance": float(Q.luminance(reference).mean()), "exposure": exposure},
        "film": list(reference.shape[1::-1]),
        "methods": {}, "fits": {}, "images": {"R": reference}, "flip_maps": {},
        "mip_level": renderer.mip_level(view),
    }
    for method in scored_methods(renderer, view):
        a, b = images[(method, cfg.spp, 0)], images[(method, cfg.spp, 1)]
        scores, fmap = Q.score(reference, a, exposure)
        noise = Q.noise_mse(a, b)
        entry = {**scores.to_dict(), **Q.bias_noise(scores.mse, noise, ref_noise)}
        out["methods"].setdefault(method, {})[cfg.spp] = entry
        if method != "R":
            out["images"][method], out["flip_maps"][method] = a, fmap
        if view.ladder:
            out["fits"][method] = _ladder(out["methods"][method], method, reference, exposure, images, timings, cfg)
    return out


def _ladder(entries: dict, method: str, reference, exposure: float, images: dict, timings: dict, cfg) -> dict:
    """Scores and the fastest timed seconds (and the median load) of every rung; returns the linear fit of
    seconds on spp."""
    timed = range(1, cfg.rounds + 1)
    for spp in cfg.ladder:
        e = entries.setdefault(spp, {})
        if "mse" not in e:
            e.update(Q.score(reference, images[(method, spp, 0)], exposure)[0].to_dict())
        e["seconds"] = float(min(timings[(method, spp, r)][0] for r in timed))
        e["load"] = float(np.median([timings[(method, spp, r)][1] for r in timed]))
    secs = [entries[s]["seconds"] for s in cfg.ladder]
    slope, fixed = np.polyfit(np.array(cfg.ladder, float), np.array(secs), 1) if len(cfg.ladder) > 1 else (secs[0], 0.0)
    return {"seconds_per_spp": float(slope), "fixed_seconds": float(fixed)}


def run_material(renderer: MaterialRenderer, views: tuple[View, ...] = VIEWS, tick=lambda: None) -> dict:
    """Every view of one material (scenes are released after each view: the reference is large)."""
    results = {}
    for view in views:
        log.info("%s / %s", renderer.name, view.name)
        results[view.name] = run_view(renderer, view, tick)
        renderer.release()
    return results
