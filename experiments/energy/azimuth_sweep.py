"""A far view's configuration turned about the normal: the model's answers' mean against the training data's own
estimator (`QueryTracer`, 16 samples a query, 20 000 random positions a point), both directions rotated together by
phi, at one level. The report's views look along the tile's y axis (phi = 0); a material whose microgeometry is
laid out along its axes (plates, boards, grooves) reflects differently there than at phi = 20 degrees, and a
model that blurs that anisotropy answers those views wrong while its data, pooled over every azimuth, say it is
right.

    .venv/bin/python experiments/energy/azimuth_sweep.py MATERIAL MODEL... [--level 6] [--light side]

``--estimates PRINTOUT``: the estimator's means from an earlier run's printout of the same material, level, lights
and step (the positions are the same: the random generator is replayed), instead of tracing them again.
"""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path

import numpy as np

LIGHTS = {"high": (20, 45), "side": (60, 90), "front": (50, 135)}
"""The report's lights: zenith and azimuth from the direction towards the camera, degrees."""
POSITIONS = 20000
"""Random positions a configuration."""


def read_estimates(path: Path) -> dict[tuple[str, float], tuple[float, float]]:
    """A printout of this script -> {(light, phi): (the estimator's mean, the first model's ratio)}, in its order."""
    out = {}
    for line in path.read_text().splitlines():
        m = re.match(r"\s+(\w+)\s+phi\s+([\d.]+): estimator ([\d.]+)\s+([\d.]+)", line)
        if m:
            out[m.group(1), float(m.group(2))] = float(m.group(3)), float(m.group(4))
    return out


def configurations(configs, level: int, resolution: int):
    """(light, phi) pairs in the sweep's order -> yields (light, phi, (POSITIONS, 7) queries): the light and the
    55-degree view turned by phi, at random positions (the same for every run: the generator seeded 0)."""
    from neumip.core import contract as C

    rng = np.random.default_rng(0)
    for light, phi in configs:
        zen, az = LIGHTS[light]

        def direction(zenith, azimuth):
            z, a = math.radians(zenith), math.radians(azimuth + phi)
            return math.sin(z) * math.sin(a), -math.sin(z) * math.cos(a)
        q = np.zeros((POSITIONS, 7), np.float32)
        q[:, C.U], q[:, C.V] = rng.random(POSITIONS), rng.random(POSITIONS)
        q[:, C.SIGMA] = 2.0**level / resolution
        q[:, C.WI_X:C.WI_Y + 1], q[:, C.WO_X:C.WO_Y + 1] = direction(zen, az), direction(55, 0)
        yield light, phi, q


def shape_score(logs: np.ndarray, lights: int) -> float:
    """log ratios in the sweep's order -> the mean |log| about each light's own mean (the error by azimuth, each
    light's brightness taken out)."""
    per_light = np.asarray(logs).reshape(lights, -1)
    return float(np.abs(per_light - per_light.mean(1, keepdims=True)).mean())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("material")
    parser.add_argument("models", nargs="+")
    parser.add_argument("--level", type=int, default=6, help="footprint 2^LEVEL map texels")
    parser.add_argument("--lights", default="high,side,front")
    parser.add_argument("--step", type=float, default=7.5, help="degrees between rotations")
    parser.add_argument("--estimates", type=Path, help="an earlier printout whose estimator means to reuse")
    args = parser.parse_args()
    known = {key: est for key, (est, _) in read_estimates(args.estimates).items()} if args.estimates else {}

    from neumip.engines.local import load_material
    from neumip.groundtruth.description import find_description, resolve
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.tracer import QueryTracer

    geo = resolve(find_description(args.material))
    settings = GenerateSettings()
    tracer = None if known else QueryTracer(geo, settings.tracer, settings.tiling)
    models = [load_material(m) for m in args.models]
    resolution = find_description(args.material).resolution
    lum = np.array([0.2126, 0.7152, 0.0722])
    logs = [[] for _ in models]
    print(f"{args.material}, footprint 2^{args.level} texels, view 55 degrees; the answers' mean / the estimator's "
          f"for {', '.join(args.models)}; phi: the view's azimuth from the tile's -y axis")
    lights = args.lights.split(",")
    turns = np.arange(0.0, 90.0 + 1e-6, args.step)
    for light, phi, q in configurations([(light, phi) for light in lights for phi in turns], args.level, resolution):
        truth = known[light, float(phi)] if known else (tracer.estimate(q, 16, int(phi * 10)) @ lum).mean()
        ratios = [(m.run(q) @ lum).mean() / truth for m in models]
        for log, r in zip(logs, ratios):
            log.append(math.log(r))
        print(f"  {light:5s} phi {phi:5.1f}: estimator {truth:.4f}  " + "  ".join(f"{r:.3f}" for r in ratios),
              flush=True)
    for path, log in zip(args.models, logs):
        print(f"  {path}: mean |log(answer / estimator)| {np.mean(np.abs(log)):.4f}, largest {np.max(np.abs(log)):.4f}; "
              f"shape (each light's turns about their mean log) {shape_score(log, len(lights)):.4f}")

if __name__ == "__main__":
    main()
