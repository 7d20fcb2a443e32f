"""Prune an exported model's MLPs to a sparsity, then fine-tune them: a wide MLP at a narrow one's render cost?

Issue 25's wider MLPs (48 wide, experiments/grazing/grazing.txt section 10) lowered the reference error on four of five
materials, but the render's kernels unroll every MLP into one fma per weight, so the neural plane cost 1.05x the
geometry's time (the goal: at most 0.8x). The kernel skips zero coefficients (`engines/onnx_ops.py`, `Ops._rows`),
so a sparse weight matrix costs only its nonzeros there, with the graph, the file format and every engine as
they are (ONNX Runtime multiplies the zeros as it did).

Gradual magnitude pruning (Zhu and Gupta 2017): every weight matrix of every MLP (the decoder, the offset
network) loses its smallest-magnitude weights, the sparsity rising as s (1 - (1 - t / T)^3) over the first
``--prune-fraction`` of the ``--steps``, the mask redrawn every ``--every`` steps at the ramp's value at the end of
its interval (so the first mask, before any step, already cuts s (1 - (1 - every / T)^3)); the rest of the steps
fine-tune the survivors. The MLPs' weights and biases are the only parameters: the pyramid, the offset texture, the base and
the relief are frozen, as they were exported. Loss, batches and the training split are `neumip fit`'s (comb2, 16 384
queries, the held-out split left out). No blur: the exported textures are what it answers.

    # the best of experiments/grazing/grazing.txt section 11 (Ld50o85): the decoder, which the render asks once per light,
    # at half its weights, the offset network at 0.15, pruned slowly
    .venv/bin/python experiments/prune/prune.py runs/seeds/Mship256_h48/rock.onnx data/rock_n1048576_s16 \\
        --sparsity 0.5 --offset-sparsity 0.85 --steps 4000 --prune-fraction 0.75 -o runs/prune/rock_Ld50o85.onnx

``--teacher`` distils: the targets are the dense source model's answers to the data's queries, not the data's
16-spp estimates. ``--offset-sparsity`` sets the offset network's apart. ``--sparsity 0`` fine-tunes with the
same steps and nothing pruned: the control.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "residual"))  # experiments/residual/coarse_finish.py
from coarse_finish import arguments, batches, material_from_file, save_like  # noqa: E402


def weight_matrices(material, config) -> dict[str, list]:
    """Every MLP's weight matrices (not the biases), by MLP."""
    from neumip.core import weights as W

    return {prefix: [getattr(material, prefix)[2 * i].weight for i in range(config.layers)] for prefix in W.mlps(config)}


def magnitude_masks(matrices: list, sparsity: float) -> list:
    """Per matrix: keep the largest-magnitude (1 - sparsity) of its weights (at least as many as it has rows)."""
    import torch

    masks = []
    for w in matrices:
        keep = max(int(round(w.numel() * (1.0 - sparsity))), w.shape[0])
        threshold = torch.topk(w.detach().abs().flatten(), keep).values[-1]
        masks.append((w.detach().abs() >= threshold).to(w.dtype))
    return masks


def ramp(done: int, every: int, span: int) -> float:
    """The share of the final sparsity for the mask drawn `done` steps into a ramp of `span` steps: the cubic
    1 - (1 - t)^3 at the end of the mask's `every`-step interval."""
    return 1.0 - (1.0 - min(done + every, span) / span) ** 3


def apply_masks(matrices: list, masks: list) -> None:
    """Zero the pruned weights (after every optimiser step: Adam's momentum moves them off zero)."""
    import torch

    with torch.no_grad():
        for w, m in zip(matrices, masks):
            w.mul_(m)


def fmas(matrices: list) -> tuple[int, int]:
    """(nonzero weights, all weights): the kernel's fmas a query against a dense evaluation's."""
    return sum(int((w != 0).sum()) for w in matrices), sum(w.numel() for w in matrices)


def main() -> None:
    parser = arguments(__doc__, steps=800, lr=3e-4)
    parser.add_argument("--sparsity", type=float, default=0.6, help="fraction of each weight matrix set to zero")
    parser.add_argument("--offset-sparsity", type=float, help="the offset network's (default: --sparsity)")
    parser.add_argument("--prune-fraction", type=float, default=0.5, help="of the steps, those the sparsity rises over")
    parser.add_argument("--every", type=int, default=25, help="steps between mask updates while pruning")
    parser.add_argument("--teacher", action="store_true",
                        help="fit the source model's own answers (noise-free) instead of the data's targets")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    if args.offset_sparsity is None:
        args.offset_sparsity = args.sparsity
    if not (0.0 <= args.sparsity < 1.0 and 0.0 <= args.offset_sparsity < 1.0):
        parser.error("a sparsity must be in [0, 1)")

    import torch

    from neumip.core import weights as W
    from neumip.training.loop.losses import training_loss

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    material, config, meta, finest = material_from_file(args.model)
    teacher = material_from_file(args.model)[0].eval() if args.teacher else None
    for p in material.parameters():
        p.requires_grad_(False)
    params = [p for prefix in W.mlps(config) for p in getattr(material, prefix).parameters()]
    for p in params:
        p.requires_grad_(True)
    by_mlp = weight_matrices(material, config)
    matrices = [w for ws in by_mlp.values() for w in ws]
    sparsity = {prefix: args.offset_sparsity if prefix == W.OFFSET_MLP else args.sparsity for prefix in by_mlp}
    sampler, train_config = batches(material, config, args.data, args.batch, args.seed)
    optimizer = torch.optim.Adam(params, lr=args.lr)
    prune_steps = max(1, int(args.steps * args.prune_fraction))
    masks = None
    start, window = time.perf_counter(), []
    for step in range(args.steps):
        if max(sparsity.values()) > 0 and step <= prune_steps and step % args.every == 0:
            share = ramp(step, args.every, prune_steps)
            masks = [m for prefix, ws in by_mlp.items() for m in magnitude_masks(ws, sparsity[prefix] * share)]
        q, rgb = sampler.draw(torch.device("cpu"))
        if teacher is not None:
            with torch.no_grad():
                rgb = teacher(q, landed=config.relief > 0, ceiling=False)
        loss = training_loss(material(q, landed=config.relief > 0, ceiling=False), rgb, train_config)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if masks is not None:
            apply_masks(matrices, masks)
        window.append(float(loss.detach()))
        if (step + 1) % 100 == 0:
            nonzero, total = fmas(matrices)
            print(f"step {step + 1}: loss {np.mean(window):.6f}, weights {nonzero}/{total} "
                  f"({time.perf_counter() - start:.0f} s)", flush=True)
            window = []
    save_like(material, config, meta, finest, args.out)
    nonzero, total = fmas(matrices)
    print(f"{nonzero} of {total} weights nonzero ({nonzero / total:.3f}) in {time.perf_counter() - start:.0f} s "
          f"-> {args.out}")


if __name__ == "__main__":
    main()
