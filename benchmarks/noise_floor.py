"""The fit's noise check (`training/loop/verdict.py`) for models trained before it existed: each model's query MSE
on fresh queries of its data's distribution against the ground truth's own noise, written into its record
(NAME.json, ``validation.noise``), where `neumip fit`'s verdict line finds the shipped models' ratios.

    python benchmarks/noise_floor.py models   # every model with a record; prints a table (results/noise_floor.txt)
    python benchmarks/noise_floor.py models --dry-run  # the table only

"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", type=Path, help="folder of NAME.onnx models with NAME.json records")
    parser.add_argument("--dry-run", action="store_true", help="print the table, write nothing")
    args = parser.parse_args()

    from neumip.engines.local import LocalMaterials
    from neumip.groundtruth.description import MaterialDescription
    from neumip.training.loop.verdict import noise_check

    materials = LocalMaterials(args.models)
    print(f"{'model':<24} {'spp':>4} {'query MSE x1e-3':>16} {'noise x1e-3':>12} {'ratio':>6}")
    for record_path in sorted(args.models.glob("*.json")):
        record = json.loads(record_path.read_text())
        meta = record.get("data_meta") or {}
        if not (record_path.with_suffix(".onnx").is_file() and "generator" in meta and meta.get("material")):
            continue
        description = MaterialDescription.from_dict({k: v for k, v in meta["material"].items() if k != "map_sha256"},
                                                    base_dir=meta.get("description_dir"))
        name = record_path.stem
        noise = noise_check(lambda q: materials.evaluate(name, np.ascontiguousarray(q, np.float32)), description,
                            meta["generator"])
        print(f"{name:<24} {noise['spp']:>4} {noise['mse'] * 1e3:>16.4f} {noise['noise_floor'] * 1e3:>12.4f} "
              f"{noise['ratio'] or float('nan'):>6.2f}", flush=True)
        if not args.dry_run:
            record.setdefault("validation", {})["noise"] = noise
            record_path.write_text(json.dumps(record, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
