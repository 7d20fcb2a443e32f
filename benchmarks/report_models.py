"""Report on the shipped materials: sizes, validation tables, offset ablation, flat-plane known answer.

Reads models/NAME.onnx and models/NAME.json (written by `neumip train`) and prints:
- per model: file size, training steps and time, the per-level validation table;
- for every material shipped with and without the neural offset: validation MSE per level side by
  side and the ratio without / with;
- the known answer: models/flat.onnx evaluated on random queries against the flat Lambertian's
  exact MBTF 0.5 / pi (relative error), through the in-process ONNX Runtime evaluator.

- with --reference MATERIAL=DATA (a data set path-traced with many more samples per query, e.g.
  `neumip generate rock -o data/rock_ref --queries 40000 --spp 256 --seed 1 --resolution 64`):
  the ablation pair's MSE per level against that low-noise reference (the held-out split of the
  16-spp training data carries Monte Carlo noise that both models share, which hides ratios).

Run: .venv/bin/python benchmarks/report_models.py [--models models] [--reference rock=data/rock_ref ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.core.contract import random_queries
from neumip.engines.local import LocalMaterials
from neumip.training.loop.validation import format_table

FLAT_ALBEDO = 0.5
"""Albedo of the shipped `flat` material (groundtruth/library/flat.toml)."""


def report_reference(folder: Path, material: str, data_path: str) -> None:
    """MSE per level of MATERIAL and MATERIAL_nooffset against a low-noise reference data set."""
    from neumip.groundtruth.dataset import open_dataset
    from neumip.training.loop.validation import validation_table

    data = open_dataset(data_path)
    queries, target = np.asarray(data.queries), np.asarray(data.rgb)
    spp = data.meta.get("generator", {}).get("spp", "?")
    local = LocalMaterials(folder)
    tables = {}
    for name in (material, f"{material}_nooffset"):
        resolution = json.loads((folder / f"{name}.json").read_text())["material_config"]["resolution"]
        tables[name] = validation_table(local.evaluate(name, queries), target, queries[:, C.SIGMA], resolution)
    with_off, without = tables[material], tables[f"{material}_nooffset"]
    print(f"\n== {material} against {data_path} ({len(queries)} queries, {spp} spp): MSE x1e-3, without / with")
    for a, b in zip(without["levels"] + [without["overall"]], with_off["levels"] + [with_off["overall"]]):
        label = a.get("level", "all")
        print(f"  level {label!s:>3} (n {a['n']:>6}): without {a['mse'] * 1e3:8.4f}  with {b['mse'] * 1e3:8.4f}  "
              f"ratio {a['mse'] / b['mse']:5.2f}x   rel L1 without {a['rel_l1']:.3f} with {b['rel_l1']:.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--models", default="models")
    parser.add_argument("--reference", nargs="*", default=[], metavar="MATERIAL=DATA")
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

    for spec in args.reference:
        material, data_path = spec.split("=", 1)
        report_reference(folder, material, data_path)

    if (folder / "flat.onnx").exists():
        q = random_queries(200_000)
        rgb = LocalMaterials(folder).evaluate("flat", q)
        exact = FLAT_ALBEDO / np.pi
        rel = np.abs(rgb - exact) / exact
        print(f"\n== known answer: flat Lambertian, albedo {FLAT_ALBEDO}: exact MBTF {exact:.5f}")
        print(f"model mean {rgb.mean():.5f} (relative error of the mean {abs(rgb.mean() - exact) / exact:.2e}); "
              f"per query relative error: mean {rel.mean():.2e}, 99th percentile {np.quantile(rel, 0.99):.2e}, "
              f"max {rel.max():.2e} over {len(q)} random queries")


if __name__ == "__main__":
    main()
