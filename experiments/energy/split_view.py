"""Where a far view's excess or missing energy comes from: the sun's queries or the environment's.

Renders method N's scene of a report view (`experiments/error_structure/oracle_view.py`'s set-up: the report's
camera, lights, film, footprints, 64 spp) with evaluators that answer each query either with the model (ONNX
Runtime) or with the oracle (the training data's own estimator, `QueryTracer`, 4 path samples a query):

- ``oracle``: every query path-traced;
- ``sun N``: the sun's queries (the light direction the view's directional light gives every shading point)
  answered by the model, the environment's (every other direction) path-traced;
- ``sky N``: the other way round.

Each render's mean over R's mean (R: the report's reference, from the cache) says how much of N's own
mean / R each light's queries carry. Beside it, per light and for the environment's queries by the light's
elevation (the sine of the angle above the plane), the model's answers summed over the oracle's, over every query
the render sent (unweighted by the integrator's sampling weights: what the model says where it is asked).

    .venv/bin/python experiments/energy/split_view.py turtle level8_side,level6_side --cache runs/rep/cache/renders
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "error_structure"))
from oracle_view import OracleEvaluator  # noqa: E402

ELEVATION_EDGES = (0.0, 0.1, 0.25, 0.5, 0.75, 1.0001)
"""Bins of wi_z (the sine of the light's elevation) for the environment's queries."""


class SplitEvaluator(OracleEvaluator):
    """Answers the sun's queries with ``sun`` and the rest with ``sky`` ("model" or "oracle"); sums both
    answers' luminance by light and elevation bin."""

    def __init__(self, name, tracer, spp, seed, model, sun_wi, sun: str, sky: str) -> None:
        super().__init__(name, tracer, spp, seed)
        self.model, self.sun_wi, self.sun, self.sky = model, sun_wi, sun, sky
        self.sums: dict = {}

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        from neumip.core import contract as C

        lights = C.group_lights(queries.shape[1])
        single = C.ungroup(np.asarray(queries, C.DTYPE))
        traced = super().evaluate(material, queries).reshape(-1, C.RGB_DIM)
        modelled = np.asarray(self.model.evaluate(material, single), np.float64).reshape(-1, C.RGB_DIM)
        wi = single[:, C.WI_X:C.WI_Y + 1]
        if self.sun_wi is None:  # the sun's direction: the one every shading point's light sample shares
            values, counts = np.unique(np.round(wi, 4), axis=0, return_counts=True)
            self.sun_wi = values[counts.argmax()].astype(np.float32)
        is_sun = np.abs(wi - self.sun_wi).max(axis=1) < 2e-4
        wi_z = np.sqrt(np.maximum(0.0, 1.0 - (wi.astype(np.float64) ** 2).sum(axis=1)))
        lum = np.array([0.2126, 0.7152, 0.0722])
        keys = np.where(is_sun, -1, np.digitize(wi_z, ELEVATION_EDGES) - 1)
        for key in np.unique(keys):
            rows = keys == key
            s = self.sums.setdefault(int(key), [0, 0.0, 0.0])
            s[0] += int(rows.sum())
            s[1] += float((modelled[rows] @ lum).sum())
            s[2] += float((traced[rows] @ lum).sum())
        out = np.where(is_sun[:, None], modelled if self.sun == "model" else traced,
                       modelled if self.sky == "model" else traced)
        return out.astype(np.float32).reshape(queries.shape[0], C.RGB_DIM * lights)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material")
    parser.add_argument("views", help="comma-separated report views")
    parser.add_argument("--models", type=Path, default=Path("models"))
    parser.add_argument("--cache", type=Path, default=Path("runs/rep/cache/renders"))
    parser.add_argument("--tracer-spp", type=int, default=4)
    args = parser.parse_args()

    from neumip.client.mitsuba import render as R
    from neumip.engines.kernel import KernelMaterials
    from neumip.engines.local import LocalMaterials
    from neumip.groundtruth.description import resolve
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.tracer import QueryTracer
    from neumip.report.cache import RenderCache
    from neumip.report.config import ReportConfig
    from neumip.report.pipeline import REFERENCE_SEEDS
    from neumip.report.renderer import MaterialRenderer
    from neumip.report.run import find_materials
    from neumip.report.views import VIEWS

    name = Path(args.material).stem
    desc = find_materials([args.material], args.models)[name]
    cfg, geo = ReportConfig(), resolve(desc)
    renderer = MaterialRenderer(name, desc, geo, args.models, KernelMaterials(args.models), cfg, RenderCache(args.cache))
    settings = GenerateSettings()
    tracer = QueryTracer(geo, settings.tracer, settings.tiling)
    model = LocalMaterials(args.models)
    views = {v.name: v for v in VIEWS}
    labels = {-1: "sun"} | {i: f"sky wi_z {ELEVATION_EDGES[i]:.2f}-{min(ELEVATION_EDGES[i + 1], 1):.2f}"
                            for i in range(len(ELEVATION_EDGES) - 1)}
    for view_name in args.views.split(","):
        view = views[view_name]
        ref = sum(renderer.render(view, "R", cfg.reference_spp, s)[0] for s in REFERENCE_SEEDS) / 2
        n = sum(renderer.render(view, "N", cfg.spp, s)[0] for s in (0, 1)) / 2
        renderer.release()
        print(f"== {name} {view_name}: R mean {ref.mean():.5f}; N mean / R {n.mean() / ref.mean():.4f}", flush=True)
        for sun, sky in (("oracle", "oracle"), ("model", "oracle"), ("oracle", "model")):
            ev = SplitEvaluator(renderer.models["N"].stem, tracer, args.tracer_spp, 0, model, None, sun, sky)
            images = [R.render_scene(renderer.scene(view, "N"), ev,
                                     R.RenderConfig(spp=cfg.spp, seed=s, max_lanes=cfg.max_lanes)).image[..., :3]
                      for s in (0, 1)]
            mean = (images[0] + images[1]) / 2
            print(f"   sun {sun:6s} sky {sky:6s}: mean / R {mean.mean() / ref.mean():.4f}   (sun's wi {ev.sun_wi})", flush=True)
            if sun == sky:
                for key in sorted(ev.sums):
                    count, m, t = ev.sums[key]
                    print(f"      {labels[key]:<20} {count:9d} queries  model / oracle {m / t:.4f}  "
                          f"(oracle mean {t / count:.4f})")
        renderer.release()


if __name__ == "__main__":
    main()
