"""The image comparison of one material: every view, every method, scores, bias/noise, spp ladders.

Per view: the reference R is the mean of two seeds at ``reference_spp`` (its own noise is measured
from their difference). Each method (R included, as a check) is rendered with seeds 0 and 1 at
``spp``: seed 0 gives its scores, the pair its noise, and error - noise - reference noise its bias.
Views with a ladder then render every method at each spp of its ladder in rounds (round r uses
seed r, so rounds 0 and 1 at ``spp`` are the two renders above), timed in this process: R alone,
then the other methods interleaved (N N0 C Cmip, N N0 C Cmip, ...); the reported seconds are the
median over rounds, and a linear fit gives the per-spp slope and the fixed cost per render.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from . import metrics as Q
from .config import ReportConfig
from .renderer import MaterialRenderer
from .views import VIEWS, View

log = logging.getLogger(__name__)

REFERENCE_SEEDS = (1000, 1001)
"""Seeds of the reference's two renders (apart from the methods' seeds 0, 1, ...)."""


def view_steps(renderer: MaterialRenderer, view: View) -> int:
    """Renders one view takes (for progress bars)."""
    cfg, methods = renderer.config, renderer.methods
    n = 2 + 2 * len(methods)  # the reference, then two seeds of each method
    if view.ladder:
        n += cfg.rounds * sum(len(ladder_of(cfg, m)) for m in methods)
    return n


def ladder_of(config: ReportConfig, method: str) -> tuple[int, ...]:
    return config.reference_ladder if method == "R" else config.ladder


def run_view(renderer: MaterialRenderer, view: View, tick: Callable[[], None] = lambda: None) -> dict:
    """Scores of every method in ``view``: ``{"reference": {...}, "methods": {method: {spp: {...}}},
    "fits": {method: {...}}}`` plus the images the report shows (``"images"``, not JSON).

    R's scene is rendered and released before the other methods' scenes are built: drjit's virtual
    calls dispatch over every live shape, so the reference's many instances would slow down every
    other render in the process while it exists.
    """
    cfg = renderer.config
    images: dict = {}
    seconds: dict = {}

    def render(method: str, spp: int, seed: int, timed: bool = True) -> None:
        image, secs, _ = renderer.render(view, method, spp, seed, timed)
        images[(method, spp, seed)] = image
        seconds.setdefault((method, spp), {})[seed] = secs
        tick()

    groups = [("R",), tuple(m for m in renderer.methods if m != "R")]
    for group in groups:
        if group == ("R",):
            for seed in REFERENCE_SEEDS:
                render("R", cfg.reference_spp, seed, timed=False)
        for method in group:
            for seed in (0, 1):
                render(method, cfg.spp, seed)
        if view.ladder:
            for spp in sorted({s for m in group for s in ladder_of(cfg, m)}):
                for rnd in range(cfg.rounds):
                    for method in group:
                        if spp in ladder_of(cfg, method):
                            render(method, spp, rnd)
        renderer.release()
    return score_view(renderer, view, images, seconds)


def score_view(renderer: MaterialRenderer, view: View, images: dict, seconds: dict) -> dict:
    cfg = renderer.config
    r0, r1 = (images[("R", cfg.reference_spp, s)] for s in REFERENCE_SEEDS)
    reference = (r0 + r1) / 2
    ref_noise = Q.noise_mse(r0, r1) / 2  # noise of one render / 2: the mean of two
    exposure = Q.exposure_for(reference)
    out = {
        "reference": {"spp": 2 * cfg.reference_spp, "noise_mse": ref_noise,
                      "seconds": seconds[("R", cfg.reference_spp)][REFERENCE_SEEDS[0]],
                      "mean_luminance": float(Q.luminance(reference).mean()), "exposure": exposure},
        "methods": {}, "fits": {}, "images": {"R": reference}, "flip_maps": {},
        "mip_level": renderer.mip_level(view),
    }
    for method in renderer.methods:
        a, b = images[(method, cfg.spp, 0)], images[(method, cfg.spp, 1)]
        scores, fmap = Q.score(reference, a, exposure)
        noise = Q.noise_mse(a, b)
        entry = {**scores.to_dict(), "seconds": seconds[(method, cfg.spp)][0],
                 **Q.bias_noise(scores.mse, noise, ref_noise)}
        out["methods"].setdefault(method, {})[cfg.spp] = entry
        if method != "R":
            out["images"][method], out["flip_maps"][method] = a, fmap
        if not view.ladder:
            continue
        ladder = ladder_of(cfg, method)
        for spp in ladder:
            e = out["methods"][method].setdefault(spp, {})
            if "mse" not in e:
                e.update(Q.score(reference, images[(method, spp, 0)], exposure)[0].to_dict())
            rounds = [seconds[(method, spp)][r] for r in range(cfg.rounds)]
            e["seconds"] = float(np.median(rounds))
        secs = [out["methods"][method][s]["seconds"] for s in ladder]
        slope, fixed = np.polyfit(np.array(ladder, float), np.array(secs), 1) if len(ladder) > 1 else (secs[0], 0.0)
        out["fits"][method] = {"seconds_per_spp": float(slope), "fixed_seconds": float(fixed)}
    return out


def run_material(renderer: MaterialRenderer, views: tuple[View, ...] = VIEWS, tick=lambda: None) -> dict:
    """Every view of one material (scenes are released after each view: the reference is large)."""
    results = {}
    for view in views:
        log.info("%s / %s", renderer.name, view.name)
        results[view.name] = run_view(renderer, view, tick)
        renderer.release()
    return results
