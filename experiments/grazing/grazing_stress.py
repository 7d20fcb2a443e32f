"""Stability at grazing views: each model's largest answers on random queries seen from near the horizon.

A material's answer is an expectation: a model that answers far above what its data reach there renders
fireflies. The queries: u, v uniform, the finest footprint (sigma 1/512), wo 80-88 degrees from the normal,
wi 0-85 degrees, azimuths uniform (seed 0). Printed per model (ONNX Runtime): the maximum and the 99.99th
and 99.9th percentiles of the largest channel; with --data, the same of the data's targets at wo > 80
degrees beside them.

    .venv/bin/python experiments/grazing/grazing_stress.py models [--data data/turtle_n1048576_s16]
"""

from __future__ import annotations

import argparse

import numpy as np

from neumip.engines.local import LocalMaterials


def stress_queries(n: int = 200_000, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    th_o, ph_o = np.radians(rng.uniform(80, 88, n)), rng.uniform(0, 2 * np.pi, n)
    th_i, ph_i = np.radians(rng.uniform(0, 85, n)), rng.uniform(0, 2 * np.pi, n)
    return np.stack([rng.uniform(0, 1, n), rng.uniform(0, 1, n), np.full(n, 1 / 512),
                     np.sin(th_i) * np.cos(ph_i), np.sin(th_i) * np.sin(ph_i),
                     np.sin(th_o) * np.cos(ph_o), np.sin(th_o) * np.sin(ph_o)], 1).astype(np.float32)


def line(name: str, answers: np.ndarray) -> str:
    top = answers.max(axis=1)
    return (f"{name:28s} max {top.max():9.1f}   99.99th {np.quantile(top, 0.9999):8.2f}   "
            f"99.9th {np.quantile(top, 0.999):7.2f}   mean {top.mean():.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", nargs="+", help="folders of .onnx models")
    parser.add_argument("--data", action="append", default=[], help="data sets whose grazing targets to show")
    args = parser.parse_args()
    q = stress_queries()
    for folder in args.folder:
        materials = LocalMaterials(folder, threads=2)
        for name in materials.materials():
            print(line(f"{folder}/{name}", materials.evaluate(name, q)))
    for data in args.data:
        queries, rgb = np.load(f"{data}/queries.npy", mmap_mode="r"), np.load(f"{data}/rgb.npy", mmap_mode="r")
        wo = np.asarray(queries[:, 5:7])
        grazing = (wo * wo).sum(1) > np.sin(np.radians(80)) ** 2
        print(line(f"{data} (targets, wo > 80 deg)", np.asarray(rgb)[grazing]))


if __name__ == "__main__":
    main()
