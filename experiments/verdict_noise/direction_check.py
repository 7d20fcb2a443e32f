"""Is a far view's brightness error in the model's answers at that view's own directions, or somewhere else?

    .venv/bin/python experiments/verdict_noise/direction_check.py turtle level8_side level6_front ...

For each named report view (`report.views.VIEWS`), at the image centre: the light's direction wi, the direction
towards the camera wo, and the footprint a 64-spp sample of `neumip_path` queries (`contract.sample_footprint`, an
eighth of the pixel's). Queries at random positions over the tile with those directions are answered by the model
(`MODELS/NAME.onnx`, the kernel engine) and by the ground-truth tracer (`QueryTracer`, the generator's, `--spp`
samples each). Printed per view: the model's mean over the tile against the tracer's, per channel and in luminance,
for

- the light's own direction ("direct", what the directional light contributes to the view's pixels), and
- directions near it ("cell": wi and wo each tilted by up to `--cell` degrees, 8 by default; the energy table's
  cells are 16-18 degrees of half-vector angle wide), to see whether the error holds around the direction, and
- the dim environment's light (wi cosine-distributed over the hemisphere), its share of the centre pixel.

A model whose direct ratio is 1 while the rendered view is a few percent off puts the error outside the answers; one
whose direct ratio is off while the cell's is 1 shows a cell pooling directions whose errors differ.
"""

from __future__ import annotations

import argparse
import atexit
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import onnx

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.training.export.graph import build_onnx, save_onnx
from neumip.training.export.read import read_model
from neumip.training.model.energy import ones_table
from neumip.engines.kernel import KernelMaterials
from neumip.groundtruth.description import find_description, resolve
from neumip.groundtruth.tracer import QueryTracer
from neumip.report.views import ENV_RADIANCE, VIEWS, camera_origin, light_direction

LUM = np.array(C.LUMINANCE)


def unit_directions(xy: np.ndarray) -> np.ndarray:
    """(n, 2) query directions' x, y -> (n, 3) unit vectors (`contract.direction_z`)."""
    return np.concatenate([xy, C.direction_z(xy[:, 0], xy[:, 1])[:, None]], 1)


def hemisphere_cosine(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) unit directions, cosine-distributed about +z."""
    r, phi = np.sqrt(rng.random(n)), 2 * math.pi * rng.random(n)
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - r * r))], 1)


def jitter(d: np.ndarray, degrees: float, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) copies of unit vector d tilted by up to `degrees` in a random direction, kept above the horizon."""
    n = len(d)
    a = np.radians(degrees) * np.sqrt(rng.random(n))
    t = rng.normal(size=(n, 3))
    t -= (t @ d[0])[:, None] * d
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    out = np.cos(a)[:, None] * d + np.sin(a)[:, None] * t
    out[:, 2] = np.maximum(out[:, 2], 0.02)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def queries(n: int, sigma: float, wi: np.ndarray, wo: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    q = np.empty((n, C.QUERY_DIM), np.float32)
    q[:, C.U], q[:, C.V], q[:, C.SIGMA] = rng.random(n), rng.random(n), sigma
    q[:, C.WI_X:C.WI_Y + 1] = np.broadcast_to(wi, (n, 3))[:, :2]
    q[:, C.WO_X:C.WO_Y + 1] = np.broadcast_to(wo, (n, 3))[:, :2]
    return q


def view_queries(view, resolution: int, spp: int) -> tuple[float, np.ndarray, np.ndarray]:
    """A report view's centre: the footprint (tile units) one of `spp` samples a pixel queries, (1, 3) wi and wo."""
    sigma = view.footprint_texels / resolution * C.sample_footprint(spp)
    origin = camera_origin(view, 1.0)
    return sigma, light_direction(view)[None], (origin / np.linalg.norm(origin))[None]


def view_rows(view, resolution: int, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A report view's centre pixel as queries a 64-spp sample makes: (n, 7) lit by the light's direction, and (n, 7) by
    the dim environment (wi cosine-distributed), both at `n` random positions."""
    sigma, wi, wo = view_queries(view, resolution, 64)
    direct = queries(n, sigma, wi, wo, rng)
    return direct, queries(n, sigma, hemisphere_cosine(n, rng), wo, rng)


def pixel_luminance(answer, direct: np.ndarray, env: np.ndarray) -> float:
    """The luminance of a view's centre pixel from `answer`'s (queries -> RGB) means over `view_rows`' two sets: the
    light's part plus the environment's (radiance E over the hemisphere gives E * pi * the mean answer)."""
    return float((answer(direct).astype(np.float64).mean(0)
                  + ENV_RADIANCE * math.pi * answer(env).astype(np.float64).mean(0)) @ LUM)


def without_table(models: Path, name: str) -> Path:
    """A temporary folder holding `models`/NAME.onnx with its energy table's gains set to 1 (removed when the
    process exits)."""
    out = Path(tempfile.mkdtemp())
    atexit.register(shutil.rmtree, out, True)
    path = models / f"{name}.onnx"
    config, weights, meta, _ = read_model(onnx.load(path), path)
    owned = {C.META_CONTRACT, C.META_CONFIG, C.META_DESCRIPTION}
    rest = {k: v for k, v in meta.items() if k not in owned}
    save_onnx(build_onnx(config, {**weights, W.ENERGY: ones_table(config)}, meta.get(C.META_DESCRIPTION, ""), rest),
              out / f"{name}.onnx")
    return out


def compare(name: str, model, tracer, q: np.ndarray, spp: int, weight: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    m = model(q).astype(np.float64).mean(axis=0) * weight
    t = tracer.estimate(q, spp, 11).astype(np.float64).mean(axis=0) * weight
    ratio = m / t
    print(f"  {name:<9} model {m.round(5)}  tracer {t.round(5)}  ratio r,g,b {ratio.round(3)}  "
          f"luminance {float(m @ LUM / (t @ LUM)):.3f}")
    return m, t


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("material")
    parser.add_argument("views", nargs="+")
    parser.add_argument("--models", type=Path, default=Path("models"))
    parser.add_argument("--queries", type=int, default=16384)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--cell", type=float, default=8.0, help="degrees the cell's directions are jittered by")
    parser.add_argument("--spp-rule", type=int, default=64, help="the render's spp, for the sample's footprint")
    parser.add_argument("--levels", action="store_true", help="also the direct ratio at other footprints")
    parser.add_argument("--grid", action="store_true",
                        help="also the direct ratio over a grid of light directions (zenith x azimuth) at each view's wo")
    parser.add_argument("--no-table", action="store_true", help="the model without its energy table (gains of 1)")
    args = parser.parse_args()
    desc = find_description(args.material)
    tracer = QueryTracer(resolve(desc))
    name = desc.name
    materials = KernelMaterials(without_table(args.models, name) if args.no_table else args.models)

    def model(q: np.ndarray) -> np.ndarray:
        return np.asarray(materials.evaluate(name, q))

    rng = np.random.default_rng(0)
    by_name = {v.name: v for v in VIEWS}
    for view_name in args.views:
        view = by_name[view_name]
        sigma, wi, wo = view_queries(view, desc.resolution, args.spp_rule)
        print(f"{name} {view.name}: sigma {sigma * desc.resolution:.1f} texels, wi {wi[0].round(3)}, wo {wo[0].round(3)}")
        n = args.queries
        md, td = compare("direct", model, tracer, queries(n, sigma, wi, wo, rng), args.spp)
        cell = queries(n, sigma, jitter(np.repeat(wi, n, 0), args.cell, rng), jitter(np.repeat(wo, n, 0), args.cell, rng), rng)
        compare("cell", model, tracer, cell, args.spp)
        # the environment: radiance E over the hemisphere gives E * pi * mean(M) under cosine-distributed wi
        env = queries(n, sigma, hemisphere_cosine(n, rng), wo, rng)
        me, te = compare("env", model, tracer, env, args.spp, ENV_RADIANCE * math.pi)
        if args.levels:  # a tile's mean answer is the same at every footprint: compare each level's with the tracer's
            q = queries(n, sigma, wi, wo, rng)
            t = tracer.estimate(q, args.spp, 17).astype(np.float64).mean(0) @ LUM
            ratios = []
            for texels in (0.25, 1, 4, 16, 64):
                q[:, C.SIGMA] = texels / desc.resolution
                ratios.append(f"{texels:g}: {float(model(q).astype(np.float64).mean(0) @ LUM / t):.3f}")
            print("  direct, the tile's mean at footprints (texels) / the tracer's: " + ", ".join(ratios))
        if args.grid:
            print("  direct luminance ratio, rows: light zenith 0-80, columns: azimuth from the camera 0-180 (45 apart)")
            for zenith in (0, 20, 40, 60, 80):
                row = []
                for azimuth in (0, 45, 90, 135, 180):
                    z, a = math.radians(zenith), math.radians(azimuth)
                    d = np.array([[math.sin(z) * math.sin(a), -math.sin(z) * math.cos(a), math.cos(z)]])
                    q = queries(args.queries // 2, sigma, d, wo, rng)
                    m, t = model(q).astype(np.float64).mean(0), tracer.estimate(q, args.spp, 13).astype(np.float64).mean(0)
                    row.append(float(m @ LUM / (t @ LUM)))
                print(f"    {zenith:>2}: " + " ".join(f"{r:.3f}" for r in row))
        total_m, total_t = md + me, td + te
        print(f"  {'pixel':<9} luminance model / tracer {float(total_m @ LUM / (total_t @ LUM)):.3f} "
              f"(env's share {float(te @ LUM / (total_t @ LUM)):.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
