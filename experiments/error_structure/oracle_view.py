"""Would a perfect model keep a report view's bias? A render of method N with an oracle for the model.

The oracle (`OracleEvaluator`) answers every query of the neural integrator (`neumip_path`) by path tracing the
material's microgeometry with the training data's own estimator (`QueryTracer`, built as `neumip generate` builds
it), ``--tracer-spp`` samples a query, fresh samples every call: a model that answers exactly what its training
targets estimate. It renders the report's own scene of method N (its camera, lights, film and footprints) with the
report's settings (``ReportConfig``: 64 spp, passes of at most ``max_lanes`` lanes), and is scored against R
(Mitsuba ``path`` on the displaced geometry) as ``error_structure.py images`` scores N: the MSE of two seeds' mean,
its bias (MSE less the mean's noise, half one render's, and R's), and the mean luminance over R's.

Two pairings of seeds. Until `render.pass_seed` (2026-11-26) `render_scene` rendered a film in passes with seeds
``seed, seed + 1, ...`` (as many as its pass plan), so the report's pairs, methods at seeds 0 and 1 and R at 1000
and 1001, shared passes: ``noise_mse`` of such a pair saw only the passes they did not share, the noise was
underestimated and the rest counted as bias (`experiments/error_structure/oracle.txt` was measured then). Now no two seeds share a pass
and both pairings read the whole noise.
"report": the report's seeds (N, Nmaps from the cache of ``error_structure.py``; the oracle at the same seeds, its
tracer samples independent). "indep.": every pair's second seed is the first one past the first render's passes
(methods 0 and 2, R 1000 and 1004 at the report's film), so the two renders share no sample. Renders missing from
``--cache`` are made and stored in ``--scratch`` (default: ``--cache``); the oracle's are not cached.

    .venv/bin/python experiments/error_structure/oracle_view.py foam level4_high,level2_high --scratch /tmp/oracle_renders
    .venv/bin/python experiments/error_structure/oracle_view.py rock level4_high --scratch /tmp/oracle_renders
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


class OracleEvaluator:
    """A `contract.Evaluator` for one material whose answers are path-traced on its microgeometry (`QueryTracer`):
    (N, 7) queries -> (N, 3), query groups (N, 5 + 2 K) -> (N, 3 K), each light traced as its own query."""

    def __init__(self, name: str, tracer, spp: int, seed: int) -> None:
        self.name, self.tracer, self.spp, self.seed = name, tracer, spp, seed
        self.calls = self.queries = 0
        self.seconds = 0.0

    def materials(self) -> list[str]:
        return [self.name]

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        from neumip.core import contract as C

        lights = C.group_lights(queries.shape[1])
        single = C.ungroup(np.asarray(queries, C.DTYPE))  # (N K, 7): row n K + j is light j of group n
        # `neumip_path` sends groups only where every light is valid and a single query where one is, so
        # every row here is a light that counts (an engine's answer to an invalid one is dropped anyway)
        seed = int(np.random.SeedSequence([self.seed, self.calls]).generate_state(1, np.uint64)[0] >> 1)
        start = time.perf_counter()
        rgb = self.tracer.estimate(single, self.spp, seed)  # (N K, 3)
        self.seconds += time.perf_counter() - start
        self.calls, self.queries = self.calls + 1, self.queries + len(single)
        return rgb.reshape(queries.shape[0], C.RGB_DIM * lights)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material", help="a shipped material or a description file (.toml)")
    parser.add_argument("views", help="comma-separated report views (level4_high, ...)")
    parser.add_argument("--methods", default="N,Nmaps", help="neural methods to score beside the oracle")
    parser.add_argument("--tracer-spp", type=int, default=4, help="path samples per oracle query")
    parser.add_argument("--models", type=Path, default=Path("models"))
    parser.add_argument("--cache", type=Path, default=Path("runs/floor/renders"))
    parser.add_argument("--scratch", type=Path, help="where renders missing from --cache go (default: --cache)")
    args = parser.parse_args()

    from neumip.engines.kernel import KernelMaterials
    from neumip.client.mitsuba import render as R
    from neumip.groundtruth.description import resolve
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.tracer import QueryTracer
    from neumip.report import metrics as Q
    from neumip.report.cache import RenderCache
    from neumip.report.config import ReportConfig
    from neumip.report.pipeline import REFERENCE_SEEDS
    from neumip.report.renderer import MaterialRenderer
    from neumip.report.run import find_materials
    from neumip.report.views import VIEWS

    name = Path(args.material).stem
    desc = find_materials([args.material], args.models)[name]
    cfg = ReportConfig()
    geo = resolve(desc)
    renderer = MaterialRenderer(name, desc, geo, args.models, KernelMaterials(args.models), cfg, RenderCache(args.cache))
    scratch = RenderCache(args.scratch) if args.scratch else renderer.cache
    settings = GenerateSettings()  # the tracer and tiling of `neumip generate` (the training data's)
    tracer = QueryTracer(geo, settings.tracer, settings.tiling)
    views = {v.name: v for v in VIEWS}

    def cached_render(view, method: str, spp: int, seed: int) -> np.ndarray:
        main_cache = renderer.cache
        renderer.cache = main_cache if renderer.cached(view, method, spp, seed) else scratch
        try:
            return renderer.render(view, method, spp, seed)[0]
        finally:
            renderer.cache = main_cache

    def p99(image: np.ndarray) -> float:  # the report's highlight figure (`metrics.score`'s p99_ratio)
        return float(np.percentile(Q.luminance(image), 99))

    def passes(view, spp: int) -> int:
        film = renderer.spec(view).film
        return len(R.pass_plan(film.width * film.height, spp, cfg.max_lanes))

    def oracle_render(view, seed: int) -> np.ndarray:
        oracle = OracleEvaluator(renderer.models["N"].stem, tracer, args.tracer_spp, seed)
        start = time.perf_counter()
        result = R.render_scene(renderer.scene(view, "N"), oracle,
                                R.RenderConfig(spp=cfg.spp, seed=seed, max_lanes=cfg.max_lanes))
        print(f"   oracle seed {seed}: {time.perf_counter() - start:.1f} s, {oracle.calls} calls, {oracle.queries} "
              f"queries x {args.tracer_spp} path samples ({oracle.seconds:.1f} s tracing)", flush=True)
        return result.image[..., :3]

    for view_name in args.views.split(","):
        view = views[view_name]
        ref_seeds = {"report": REFERENCE_SEEDS, "indep.": (REFERENCE_SEEDS[0], REFERENCE_SEEDS[0] +
                                                          passes(view, cfg.reference_spp))}
        seeds = {"report": (0, 1), "indep.": (0, passes(view, cfg.spp))}
        refs = {}
        for pairing, (s0, s1) in ref_seeds.items():
            r0, r1 = (cached_render(view, "R", cfg.reference_spp, s) for s in (s0, s1))
            refs[pairing] = ((r0 + r1) / 2, Q.noise_mse(r0, r1) / 2)
        renderer.release()  # R's instances slow every render while they live
        film = renderer.spec(view).film
        print(f"== {name} {view_name}: film {film.width} x {film.height}; passes of a render: R "
              f"{passes(view, cfg.reference_spp)} x {cfg.reference_spp // passes(view, cfg.reference_spp)} spp, "
              f"methods {passes(view, cfg.spp)} x {cfg.spp // passes(view, cfg.spp)} spp; R mean "
              f"{refs['indep.'][0].mean():.4f}, R noise x1e-3 (seeds {ref_seeds['report']}) "
              f"{refs['report'][1] * 1e3:.4f}, (seeds {ref_seeds['indep.']}) {refs['indep.'][1] * 1e3:.4f}", flush=True)
        rows = []
        for method in args.methods.split(","):
            if method in renderer.models:
                images = {s: cached_render(view, method, cfg.spp, s) for s in sorted({*seeds["report"], *seeds["indep."]})}
                rows.append((method, images))
        oracle = {s: oracle_render(view, s) for s in sorted({*seeds["report"], *seeds["indep."]})}
        rows.append((f"oracle{args.tracer_spp}", oracle))
        print(f"   {'method':<8} {'pairing':<7} {'seeds':>7} {'R seeds':>11} {'MSE x1e-3':>9} {'noise':>7} {'R noise':>7} "
              f"{'bias':>7} {'mean/R':>7} {'p99/R':>7}")
        for method, images in rows:
            for pairing, (s0, s1) in seeds.items():
                a, b = images[s0], images[s1]
                ref, ref_noise = refs[pairing]
                mean = (a + b) / 2
                mse = Q.mse(mean, ref)
                noise = Q.noise_mse(a, b) / 2  # the mean of two seeds has half one render's noise
                print(f"   {method:<8} {pairing:<7} {f'{s0},{s1}':>7} {','.join(map(str, ref_seeds[pairing])):>11} "
                      f"{mse * 1e3:9.4f} {noise * 1e3:7.4f} {ref_noise * 1e3:7.4f} {(mse - noise - ref_noise) * 1e3:7.4f} "
                      f"{mean.mean() / ref.mean():7.4f} {p99(mean) / p99(ref):7.4f}")
        renderer.release()


if __name__ == "__main__":
    main()
