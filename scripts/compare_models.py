"""Compare the model files of two folders, file by file: do they answer the same?

`neumip export OLD.onnx -o NEW.onnx` prints its own check; this one is independent of neumip's loaders
(raw ONNX Runtime, files of any contract version), so it also checks an upgrade against the files
from before it (e.g. ``git show main:models/rock.onnx > /tmp/old/rock.onnx``).

    python scripts/compare_models.py OLD_FOLDER NEW_FOLDER

Per file of NEW_FOLDER: whether the graph is unchanged, the largest |old - new| answer on 2^20 random
queries and on 2^18 query groups of three lights, and which metadata keys changed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort

from neumip.core import contract as C


def session(path: Path) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def metadata(model: onnx.ModelProto) -> dict[str, str]:
    return {p.key: p.value for p in model.metadata_props}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    args = parser.parse_args()
    queries = C.random_queries(1 << 20, seed=11)  # (2^20, 7)
    lights = [C.random_queries(1 << 18, seed=12 + j)[:, C.WI_X:C.WI_Y + 1] for j in range(2)]
    groups = np.ascontiguousarray(np.hstack([queries[: 1 << 18], *lights]))  # (2^18, 11)
    for new_path in sorted(args.new.glob("*.onnx")):
        old_path = args.old / new_path.name
        old, new = onnx.load(str(old_path)), onnx.load(str(new_path))
        a, b = session(old_path), session(new_path)
        diff = [float(np.abs(a.run(None, {C.ONNX_INPUT: x})[0] - b.run(None, {C.ONNX_INPUT: x})[0]).max())
                for x in (queries, groups)]
        changed = sorted(k for k in metadata(old).keys() | metadata(new).keys()
                         if metadata(old).get(k) != metadata(new).get(k))
        print(f"{new_path.name}: graph unchanged {old.graph == new.graph}; largest |old - new|: 2^20 queries "
              f"{diff[0]:.3g}, 2^18 groups of 3 lights {diff[1]:.3g}; metadata changed: {', '.join(changed) or 'none'}")


if __name__ == "__main__":
    main()
