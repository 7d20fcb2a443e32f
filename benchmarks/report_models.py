"""Report on the shipped materials: sizes, validation tables, offset ablation, flat-plane known answer.

Reads models/NAME.onnx and models/NAME.json (written by `neumip train`) and prints:
- per model: file size, training steps and time, the per-level validation table;
- for every material shipped with and without the neural offset: validation MSE per level side by
  side and the ratio without / with;
- the known answer: models/flat.onnx evaluated on random queries against the flat Lambertian's
  exact MBTF 0.5 / pi (relative error), through the in-process ONNX Runtime evaluator.

Run: .venv/bin/python benchmarks/report_models.py [--models models]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from neumip.client import contract as C
from neumip.client.local import LocalMaterials
from neumip.training.validation import format_table

FLAT_ALBEDO = 0.5
"""Albedo of the shipped `flat` material (training/microgeometry/library/flat.toml)."""


def known_answer_queries(n: int, seed: int = 0) -> np.ndarray:
    """(n, 7) queries: u, v anywhere, sigma over all levels, wi, wo up to 84 degrees."""
    rng = np.random.default_rng(seed)
    r = np.sin(np.radians(84.0)) * np.sqrt(rng.uniform(0, 1, (n, 2)))
    phi = rng.uniform(0, 2 * np.pi, (n, 2))
    wi = np.stack([r[:, 0] * np.cos(phi[:, 0]), r[:, 0] * np.sin(phi[:, 0])], 1)
    wo = np.stack([r[:, 1] * np.cos(phi[:, 1]), r[:, 1] * np.sin(phi[:, 1])], 1)
    return C.pack_queries(rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), 2.0 ** rng.uniform(-10, 0, n), wi, wo)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--models", default="models")
    args = parser.parse_args()
    folder = Path(args.models)
    records = {p.stem: json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))}
    for name, rec in records.items():
        size = (folder / f"{name}.onnx").stat().st_size
        val = rec["validation"]
        print(f"\n== {name}: {size / 1e6:.2f} MB, {val['steps']} steps x {val['batch']}, "
              f"{val['train_seconds'] / 60:.1f} min training, offset={rec['material_config']['offset']}")
        print(format_table(val))

    print("\n== neural offset ablation: validation MSE x1e-3 per level, without / with")
    for name in records:
        if not name.endswith("_nooffset") or name.removesuffix("_nooffset") not in records:
            continue
        with_off = records[name.removesuffix("_nooffset")]["validation"]
        without = records[name]["validation"]
        print(f"{name.removesuffix('_nooffset')}:")
        for a, b in zip(without["levels"] + [without["overall"]], with_off["levels"] + [with_off["overall"]]):
            label = a.get("level", "all")
            print(f"  level {label!s:>3}: without {a['mse'] * 1e3:8.4f}  with {b['mse'] * 1e3:8.4f}  "
                  f"ratio {a['mse'] / b['mse']:5.2f}x")

    if (folder / "flat.onnx").exists():
        q = known_answer_queries(200_000)
        rgb = LocalMaterials(folder).evaluate("flat", q)
        exact = FLAT_ALBEDO / np.pi
        rel = np.abs(rgb - exact) / exact
        print(f"\n== known answer: flat Lambertian, albedo {FLAT_ALBEDO}: exact MBTF {exact:.5f}")
        print(f"model mean {rgb.mean():.5f} (relative error of the mean {abs(rgb.mean() - exact) / exact:.2e}); "
              f"per query relative error: mean {rel.mean():.2e}, 99th percentile {np.quantile(rel, 0.99):.2e}, "
              f"max {rel.max():.2e} over {len(q)} random queries")


if __name__ == "__main__":
    main()
