"""Models on the data's close-up queries under a grazing light, against the targets, binned by the base's answer.

Under a light 5 degrees above the horizon the shipped models compress the contrast of rock's close-ups: the
decoder's correction lives on the 64^2 latents (4 map texels a texel), so it lifts the base's shadows and dims its
lit ridges together (`experiments/grazing/grazing.txt`). For each checkpoint (a model with a base) this prints the
reference set's log MSE (`fit.reference_error`, what `--base auto` judges) and, over the data's queries with a
light 78-88 degrees from the normal and a footprint under 2 map texels (the report's low-light close-up), the mean
target and the model's mean answer per bin of the base's own answer (the model with its decoder's last layer
zeroed). The targets are unbiased, so a bin's mean target is the answer the model should give there.

    .venv/bin/python experiments/grazing/grazing_queries.py data/rock_n1048576_s16 runs/rock/reference runs/loss/VIS/rock.pt ...
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from neumip.core import contract as C  # noqa: E402

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def judge(data: str, reference: str, checkpoint_path: str) -> None:
    from neumip.training.loop import checkpoint
    from neumip.groundtruth.dataset import open_dataset
    from neumip.training.loop.fit import reference_error

    torch.set_num_threads(1)
    model, _ = checkpoint.load(checkpoint_path)
    model.eval()
    print(f"{checkpoint_path}: reference log MSE {reference_error(model, open_dataset(reference)) * 1e3:.3f}e-3")
    ds = open_dataset(data)
    q, t = np.asarray(ds.queries), np.asarray(ds.rgb) @ LUMINANCE
    zenith = np.degrees(np.arccos(np.sqrt(np.clip(1 - q[:, C.WI_X] ** 2 - q[:, C.WI_Y] ** 2, 0, 1))))
    rows = (zenith > 78) & (zenith < 88) & (q[:, C.SIGMA] < 2 / model.config.base)
    queries, t = torch.as_tensor(q[rows]), t[rows]
    with torch.no_grad():
        y = model(queries).numpy() @ LUMINANCE
        last = model.decoder[-1]
        saved = last.weight.clone(), last.bias.clone()
        last.weight.zero_(), last.bias.zero_()
        b = model(queries).numpy() @ LUMINANCE
        last.weight.copy_(saved[0]), last.bias.copy_(saved[1])
    print(f"  {rows.sum()} queries (light 78-88 degrees, footprint < 2 map texels): target {t.mean():.4f}, "
          f"model {y.mean():.4f}, base {b.mean():.4f}; per bin of the base's answer (its quantiles):")
    print("    base in            queries  target   model    base   model MSE x1e-3")
    for lo, hi in ((0, 0.5), (0.5, 0.8), (0.8, 0.9), (0.9, 0.95), (0.95, 0.98), (0.98, 0.99), (0.99, 1.0)):
        a, z = np.quantile(b, [lo, hi])
        sel = (b >= a) & (b <= z) if hi == 1.0 else (b >= a) & (b < z)
        if lo == 0:
            sel = b < z
        if sel.any():
            print(f"    [{a:6.3f}, {z:6.3f}]  {sel.sum():7d}  {t[sel].mean():.4f}  {y[sel].mean():.4f}  {b[sel].mean():.4f}"
                  f"   {((y[sel] - t[sel]) ** 2).mean() * 1e3:.3f}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", help="the models' data set folder")
    p.add_argument("reference", help="a low-noise data set of the same material (make_models.sh's runs/NAME/reference)")
    p.add_argument("checkpoints", nargs="+", help="checkpoints (.pt) of models with a base")
    args = p.parse_args()
    for path in args.checkpoints:
        judge(args.data, args.reference, path)


if __name__ == "__main__":
    main()
