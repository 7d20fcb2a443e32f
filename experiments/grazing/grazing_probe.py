"""Models against the microgeometry's own answer on a grid of positions, per light and footprint: do they keep the
contrast of a grazing light?

For each light (zenith:azimuth in degrees, the azimuth from the view's) and level of detail (log2 of the footprint
in map texels), the queries are a GRID x GRID lattice of positions over the tile at that footprint, viewed from
``--view-zenith`` degrees: a report view's queries without the camera. The truth is `QueryTracer` (the training
data's estimator) at ``--spp`` samples a query, so it holds directions the data never sampled (the data stop at
84.26 degrees; the report's low light is at 85). Printed per model: the mean luminance, its median, 90th and
99th percentile over the truth's, the correlation, and the MSE of the luminance; no render, so a model is judged
in seconds where `experiments/maps/maps.py score` takes minutes.

    .venv/bin/python experiments/grazing/grazing_probe.py rock models/rock_maps.onnx models/rock.onnx
    .venv/bin/python experiments/grazing/grazing_probe.py docs/materials/planks.toml A.onnx B.onnx --lights 85:90,60:90
"""

from __future__ import annotations

import argparse

import numpy as np

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def lattice(grid: int, lod: float, resolution: int, light: tuple[float, float], view_zenith: float) -> np.ndarray:
    """(grid^2, 7) queries: positions over the tile, footprint 2^lod texels of `resolution`, one light, one view."""
    g = (np.arange(grid) + 0.5) / grid
    u, v = np.meshgrid(g, g, indexing="xy")
    zi, ai, zo = np.radians(light[0]), np.radians(light[1]), np.radians(view_zenith)
    q = np.zeros((grid * grid, 7), np.float32)
    q[:, 0], q[:, 1], q[:, 2] = u.ravel(), v.ravel(), 2.0 ** lod / resolution
    q[:, 3], q[:, 4] = np.sin(zi) * np.cos(ai), np.sin(zi) * np.sin(ai)
    q[:, 5], q[:, 6] = np.sin(zo), 0.0
    return q


def figures(answer: np.ndarray, truth: np.ndarray) -> str:
    """One model's luminance figures over the truth's."""
    ratio = [f"{np.percentile(answer, p) / np.percentile(truth, p):.3f}" if np.percentile(truth, p) > 0 else "-"
             for p in (50, 90, 99)]  # (a truth's percentile of 0: no ratio)
    return (f"mean {answer.mean() / truth.mean():.3f}  p50 {ratio[0]}  p90 {ratio[1]}  p99 {ratio[2]}  "
            f"corr {np.corrcoef(answer, truth)[0, 1]:.3f}  MSE {np.mean((answer - truth) ** 2) * 1e3:.3f}e-3")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material", help="a shipped material or a description file (.toml)")
    parser.add_argument("models", nargs="+", help="model files (.onnx)")
    parser.add_argument("--lights", default="85:90,80:90,85:180,60:90,20:45",
                        help="zenith:azimuth pairs in degrees, the azimuth from the view's")
    parser.add_argument("--lods", default="0,2,4", help="footprints, log2 of map texels")
    parser.add_argument("--view-zenith", type=float, default=55.0, help="the report's distance views' 55 degrees")
    parser.add_argument("--grid", type=int, default=64)
    parser.add_argument("--spp", type=int, default=128, help="path samples a query for the truth")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()

    import onnxruntime as ort

    from neumip.groundtruth.description import find_description, resolve
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.tracer import QueryTracer

    desc = find_description(args.material)
    geo = resolve(desc)
    settings = GenerateSettings()
    tracer = QueryTracer(geo, settings.tracer, settings.tiling)
    sessions = {path: ort.InferenceSession(path, providers=["CPUExecutionProvider"]) for path in args.models}
    width = max(len(path) for path in args.models)
    for light in args.lights.split(","):
        zenith, azimuth = (float(x) for x in light.split(":"))
        for lod in (float(x) for x in args.lods.split(",")):
            q = lattice(args.grid, lod, desc.resolution, (zenith, azimuth), args.view_zenith)
            truth = tracer.estimate(q, args.spp, args.seed).astype(np.float64) @ LUMINANCE
            print(f"light {zenith:g}:{azimuth:g}, {2 ** lod:g} texels: truth mean {truth.mean():.4f}, "
                  f"p50 {np.percentile(truth, 50):.4f}, p90 {np.percentile(truth, 90):.4f}, "
                  f"p99 {np.percentile(truth, 99):.4f}", flush=True)
            for path, session in sessions.items():
                answer = session.run(None, {"queries": q})[0].astype(np.float64) @ LUMINANCE
                print(f"   {path:<{width}}  {figures(answer, truth)}", flush=True)


if __name__ == "__main__":
    main()
