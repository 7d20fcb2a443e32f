"""Two model files of one material judged on a reference data set: which one would a judge keep?

Prints each file's log-space MSE (what `fit.reference_error` computes), a relative MSE, (p - t)^2 / (t^2 + 0.01),
and the mean target over the mean answer per channel (its brightness), on the queries of REFERENCE (a `neumip
generate` data set), and the ratio second / first. Used in experiments/seeds/seeds.txt to test a judge of seeds
against the report's images, e.g. a reference set uniform over the whole domain rather than sampled like the
training data:

    neumip generate rock -o runs/uref/rock --queries 16384 --spp 256 --seed 1 --resolution 256 \
        --directions solid_angle --max-zenith 85 --level-fraction 1.0 --heavy-fraction 0
    .venv/bin/python experiments/seeds/judge_models.py runs/uref/rock models/rock.onnx runs/models-seeds3/rock.onnx
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    import onnxruntime as ort

    from neumip.groundtruth.dataset import open_dataset
    from neumip.training.loop.validation import errors as error_figures

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("reference")
    p.add_argument("models", nargs=2)
    args = p.parse_args()
    data = open_dataset(args.reference)
    queries, target = np.asarray(data.queries), np.asarray(data.rgb, np.float64)
    errors = []
    for path in args.models:
        session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
        answer = session.run(None, {"queries": queries})[0].astype(np.float64)
        log_mse = error_figures(answer, target)["log_mse"]  # what fit.reference_error computes
        relative = float(np.mean((answer - target) ** 2 / (target ** 2 + 0.01)))
        errors.append((log_mse, relative))
        brightness = target.mean(0) / np.maximum(answer.mean(0), 1e-30)  # > 1: the model answers too dark
        print(f"{path}: log MSE {log_mse * 1e3:.4f}e-3, relative MSE {relative:.5f}, "
              f"mean target / answer per channel {np.round(brightness, 3)}")
    print(f"second / first: log MSE {errors[1][0] / errors[0][0]:.3f}, relative MSE {errors[1][1] / errors[0][1]:.3f}")


if __name__ == "__main__":
    main()
