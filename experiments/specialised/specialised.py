"""An upper bound for a close-up: data for one report view's directions only, so the whole model serves them.

The map-informed model answers every light and view direction from one decoder. Trained on data whose directions
are only those one report view asks for, its whole capacity serves that view: if even such a model keeps the
view's close-up error, the error is in what the architecture can hold at the maps' resolution, not in how the
shared decoder spreads itself over directions or how long it trains.

``make MATERIAL VIEW SOURCE OUT``: the positions and footprints of the data set SOURCE (`neumip generate`'s, so
the footprints are those the model is trained on), with directions replaced: a share ``--sun`` of the queries
lit from the view's directional light, the rest from SOURCE's own light directions (the view's dim environment
lights from everywhere), and every view direction drawn uniformly within the camera's field of view around the
direction towards the camera at the image centre; path-traced at SOURCE's spp by the data's own estimator
(`QueryTracer`). OUT is a data set `neumip train` reads, with SOURCE's metadata. Train it with the shipped
recipe and score it with `footprint.py views`:

    .venv/bin/python experiments/specialised/specialised.py make rock level0_side data/rock_n1048576_s16_st1 data/rock_side_only
    neumip train data/rock_side_only -o runs/spec/rock_maps.onnx --maps --horizons 8 --relief 8 --base \\
        --local-frame --terminator none --resolution 256 --lod-bias 1 --threads 1
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np


def view_directions(view, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 2) x, y of unit directions towards the camera, uniform in a cone of half the field of view's diagonal
    (the report's film) around the image centre's."""
    from neumip.report.config import ReportConfig

    film = ReportConfig().film
    t = math.radians(view.theta)
    half = math.radians(view.fov) / 2 * math.hypot(1.0, film.width / film.height)
    cos_max = math.cos(half)
    z = rng.uniform(cos_max, 1.0, n)
    phi = rng.uniform(0.0, 2 * math.pi, n)
    r = np.sqrt(1 - z * z)
    local = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    c, s = math.cos(t), math.sin(t)  # a rotation about x taking (0, 0, 1) to the centre's (0, -sin t, cos t)
    return np.stack([local[:, 0], c * local[:, 1] - s * local[:, 2]], 1)


def make(args) -> None:
    from neumip.core import contract as C
    from neumip.groundtruth.dataset import open_dataset, write_dataset
    from neumip.groundtruth.description import find_description, resolve
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.tracer import QueryTracer
    from neumip.report.views import VIEWS, light_direction

    view = {v.name: v for v in VIEWS}[args.view]
    source = open_dataset(args.source)
    meta = json.loads((Path(args.source) / "meta.json").read_text())
    spp = meta["generator"]["spp"]
    rng = np.random.default_rng(args.seed)
    q = np.array(source.queries, dtype=np.float32)
    sun = rng.uniform(size=len(q)) < args.sun
    q[sun, C.WI_X:C.WI_Y + 1] = light_direction(view)[:2]
    q[:, C.WO_X:C.WO_Y + 1] = view_directions(view, len(q), rng)
    settings = GenerateSettings()
    tracer = QueryTracer(resolve(find_description(args.material)), settings.tracer, settings.tiling)
    start = time.perf_counter()
    rgb = np.concatenate([tracer.estimate(q[i:i + 65536], spp, args.seed + i) for i in range(0, len(q), 65536)])
    meta["specialised"] = {"view": view.name, "sun_share": args.sun, "source": str(args.source), "seed": args.seed}
    for key in ("complete", "n"):
        meta.pop(key, None)
    write_dataset(args.out, q, rgb, meta)
    print(f"{args.out}: {len(q)} queries for {view.name} ({sun.mean():.2f} lit by its sun), {spp} spp, traced in "
          f"{time.perf_counter() - start:.0f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("make", help="a data set of one view's directions")
    m.add_argument("material")
    m.add_argument("view")
    m.add_argument("source", type=Path, help="a `neumip generate` data set: its positions, footprints and spp")
    m.add_argument("out", type=Path)
    m.add_argument("--sun", type=float, default=0.7, help="share of the queries lit by the view's directional light")
    m.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    make(args)


if __name__ == "__main__":
    main()
