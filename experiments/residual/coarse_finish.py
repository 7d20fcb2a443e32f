"""Refit only the coarse levels of an exported model, everything else frozen: do the far views mend?

Issue 25's far views (16-256 map texels a pixel) read a map-informed model's coarse levels, textures its encoder
computed from the prefiltered maps. There the data hold hundreds to thousands of queries per texel, enough to fit
a texel freely. A free residual trained with the whole model (`MapConfig.residual`, experiments/residual/residual.txt) paid on
foam and moved the decoder on rock, whose close-ups got darker. Here the decoder, the fine levels, the offset, the
base and the relief are frozen: the levels of at most ``--size`` texels a side are the only parameters, so a lookup
that reads only finer levels answers bit for bit as before.

The model is read back from its ONNX file (`export_read.read_model`), trained for ``--steps`` Adam steps of
``--batch`` queries of DATA's training split (the split `neumip fit` holds out is left out) with the model's own
loss (comb2), and written with the same graph and metadata. No blur: the exported textures are what it answers.

    .venv/bin/python experiments/residual/coarse_finish.py models/rock_maps.onnx data/rock_n1048576_s16 -o runs/finish/rock_maps.onnx
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np


def material_from_file(path: Path):
    """An exported model -> (`NeuMIPMaterial` with its weights, its config, metadata, finest level)."""
    import onnx
    import torch

    from neumip.core import weights as W
    from neumip.training.export.read import read_model
    from neumip.training.model.material import NeuMIPMaterial

    config, weights, meta, finest = read_model(onnx.load(str(path)), str(path))
    if finest:
        raise SystemExit(f"{path}: a trimmed model (finest level {finest}); refit the untrimmed one")
    material = NeuMIPMaterial(config)
    state = {f"pyramid.{i}": torch.from_numpy(level.copy())
             for i, level in enumerate(split_atlas(weights[W.PYRAMID], config.level_sizes()))}
    for prefix in W.mlps(config):
        for i in range(config.layers):
            state[f"{prefix}.{2 * i}.weight"] = torch.from_numpy(weights[W.weight(prefix, i)].copy())
            state[f"{prefix}.{2 * i}.bias"] = torch.from_numpy(weights[W.bias(prefix, i)].copy())
    if config.offset:
        r = config.resolution
        state["offset_texture"] = torch.from_numpy(weights[W.OFFSET_TEXTURE].reshape(r, r, -1).copy())
    for name in (W.BASE, W.RELIEF):
        if name in weights:
            state[name] = torch.from_numpy(weights[name].copy())
    material.load_state_dict(state)
    return material, config, meta, finest


def split_atlas(atlas: np.ndarray, sizes: list[int]) -> list[np.ndarray]:
    """(sum S^2, C) texels of a pyramid, finest first -> one (S, S, C) array per level."""
    out, start = [], 0
    for size in sizes:
        out.append(atlas[start:start + size * size].reshape(size, size, -1))
        start += size * size
    return out


def arguments(description: str, steps: int, lr: float) -> argparse.ArgumentParser:
    """The options every refit of an exported model takes (this script's and `prune.py`'s)."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path)
    parser.add_argument("data", help="the model's training data (a `neumip generate` folder)")
    parser.add_argument("-o", "--out", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=steps)
    parser.add_argument("--batch", type=int, default=16384)
    parser.add_argument("--lr", type=float, default=lr)
    parser.add_argument("--threads", type=int, default=1)
    return parser


def batches(material, config, data_dir: str, batch: int, seed: int):
    """(`BatchSampler` over DATA's training split, with the relief's landed positions where the model has a relief;
    the ship preset at this batch: the loss's settings)."""
    from neumip.core import weights as W
    from neumip.groundtruth.dataset import open_dataset
    from neumip.training.model.relief import landed_positions
    from neumip.training.loop.train import BatchSampler, split_indices
    from neumip.training.loop.config import PRESETS

    train_config = replace(PRESETS["ship"], batch=batch)
    data = open_dataset(data_dir)
    train_idx, _ = split_indices(len(data), train_config)
    landed = None
    if config.relief:
        heights = split_atlas(getattr(material, W.RELIEF).numpy(), config.relief_pyramid().level_sizes())
        landed = landed_positions(heights, config, data.queries)
    return BatchSampler(data, train_idx, batch, seed=seed, preload_mb=2048, landed=landed), train_config


def save_like(material, config, meta: dict, finest: int, out: Path) -> None:
    """Write `material` with the graph and the metadata of the file it was read from."""
    from neumip.core import contract as C
    from neumip.training.export.graph import build_onnx, save_onnx, weights_from_state

    weights = weights_from_state(material.state_dict(), config)
    owned = {C.META_CONTRACT, C.META_CONFIG, C.META_DESCRIPTION}
    extra = {key: value for key, value in meta.items() if key not in owned}
    out.parent.mkdir(parents=True, exist_ok=True)
    save_onnx(build_onnx(config, weights, meta.get(C.META_DESCRIPTION, ""), extra, finest), out)


def main() -> None:
    parser = arguments(__doc__, steps=400, lr=1e-3)
    parser.add_argument("--size", type=int, default=16, help="refit the levels of at most this many texels a side")
    args = parser.parse_args()

    import torch

    from neumip.training.loop.losses import training_loss

    torch.set_num_threads(args.threads)
    material, config, meta, finest = material_from_file(args.model)
    sizes = config.level_sizes()
    coarse = [i for i, s in enumerate(sizes) if s <= args.size]
    for p in material.parameters():
        p.requires_grad_(False)
    params = [material.pyramid[i] for i in coarse]
    for p in params:
        p.requires_grad_(True)
    sampler, train_config = batches(material, config, args.data, args.batch, seed=1)
    optimizer = torch.optim.Adam(params, lr=args.lr)
    start, window = time.perf_counter(), []
    for step in range(args.steps):
        q, rgb = sampler.draw(torch.device("cpu"))
        loss = training_loss(material(q, landed=config.relief > 0, ceiling=False), rgb, train_config)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        window.append(float(loss.detach()))
        if (step + 1) % 100 == 0:
            print(f"step {step + 1}: loss {np.mean(window):.6f} ({time.perf_counter() - start:.0f} s)", flush=True)
            window = []
    save_like(material, config, meta, finest, args.out)
    print(f"levels {[sizes[i] for i in coarse]} refit in {time.perf_counter() - start:.0f} s -> {args.out}")


if __name__ == "__main__":
    main()
