"""The in-kernel engine on an NVIDIA GPU, against the bounds of its arithmetic and memory traffic and against an
MLP-only torch graph of the model's shapes on the same card, in one run (issue 50's CUDA figures).

    python benchmarks/bench_cuda.py models/rock.onnx [--sizes 16,18,20,22,24] [--rounds 5]
    .venv/bin/python benchmarks/bench_cuda.py models/rock.onnx --backend llvm --device cpu --sizes 14   # a dry run

Per call size (2^k single queries), medians of interleaved rounds, in M queries/s:

- ``kernel numpy``: `KernelMaterial.evaluate` on ``drjit.cuda.ad``: numpy in and out (the upload, the graph's
  kernel, the read-back): how the server's ``kernel`` engine runs on a GPU;
- ``kernel resident``: the query columns already on the card, the answers evaluated there (`KernelMaterial.answers`
  then ``dr.eval``): how the renderer's cuda variants run it, inside their own kernels;
- ``kernel GPU time``: the resident call's kernels alone, by drjit's kernel history (no launch or Python cost);
- ``check``: `contract.as_queries` alone, the host's check of a numpy call's queries (part of ``kernel numpy``'s time);
- ``mlp fp32`` / ``mlp bf16``: the decoder MLP alone (`weights.mlps`: its widths, `hidden`, `layers`) as a torch
  ``Sequential`` of Linear + ReLU, its input resident, ``torch.cuda.synchronize`` after each call.

The bounds come from the graph (`graph_cost.py`): the bytes its texture ``Gather`` nodes read a query (each
table in its stored type: float16 where the model reads its textures rounded, float32 otherwise) over the card's memory bandwidth, and the FLOPs of its ``MatMul``/``Gemm``
nodes plus the other nodes' elements (each as an FMA's 2 FLOPs) over its float32 peak (``--bandwidth``,
``--flops``: the H200's 4.3 TB/s measured copy and 67 TFLOP/s float32 without tensor cores).
"""

from __future__ import annotations

import argparse
import importlib
import time

import numpy as np
import onnx

from graph_cost import graph_cost
from neumip.core import contract as C
from neumip.core import weights as W
from neumip.engines.kernel import KernelMaterial


def decoder_mlp(config, torch, device: str, dtype):
    """The decoder's shapes as torch layers (random weights: speed does not depend on them)."""
    inputs, answers = W.mlps(config)[W.DECODER]
    widths = [inputs] + [config.hidden] * (config.layers - 1) + [answers]
    layers = []
    for i in range(config.layers):
        layers.append(torch.nn.Linear(widths[i], widths[i + 1]))
        if i < config.layers - 1:
            layers.append(torch.nn.ReLU())
    return torch.nn.Sequential(*layers).to(device=device, dtype=dtype).eval(), inputs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model")
    parser.add_argument("--sizes", default="16,18,20,22,24", help="log2 of the queries a call, comma-separated")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--backend", default="cuda", help="drjit backend: cuda, or llvm for a dry run")
    parser.add_argument("--device", default="cuda", help="torch device of the MLP-only graph")
    parser.add_argument("--bandwidth", type=float, default=4.3e12, help="memory bytes/s of the card")
    parser.add_argument("--flops", type=float, default=67e12, help="float32 FLOP/s of the card (no tensor cores)")
    args = parser.parse_args()
    import drjit as dr
    import torch

    jit = importlib.import_module(f"drjit.{args.backend}.ad")
    material = KernelMaterial(args.model, jit)
    cost = graph_cost(onnx.load(args.model))
    mlp32, width = decoder_mlp(material.config, torch, args.device, torch.float32)
    mlp16, _ = decoder_mlp(material.config, torch, args.device, torch.bfloat16)
    config = material.config
    print(f"# {args.model}: {cost['nodes']} nodes; a query reads {cost['bytes']} B of tables (each in its stored type) and does "
          f"{cost['flops']} FLOPs of matrix products and {cost['elements']} other operations; decoder {width} -> "
          f"{config.hidden} x {config.layers - 1} -> {W.mlps(config)[W.DECODER][1]}")
    print(f"# bounds: memory {args.bandwidth / cost['bytes'] / 1e6:.0f} M q/s at {args.bandwidth / 1e12:.1f} TB/s; "
          f"arithmetic {args.flops / (cost['flops'] + 2 * cost['elements']) / 1e6:.0f} M q/s at "
          f"{args.flops / 1e12:.0f} "
          "TFLOP/s (an operation that is no FMA counted as 2 FLOPs)")
    if args.device == "cuda":
        print(f"# {torch.cuda.get_device_name()}; torch {torch.__version__}; drjit {dr.__version__}")

    def sync():
        dr.sync_thread()
        if args.device == "cuda":
            torch.cuda.synchronize()

    print(f"{'queries':>9s} {'kernel numpy':>13s} {'kernel resident':>16s} {'kernel GPU time':>16s} "
          f"{'mlp fp32':>9s} {'mlp bf16':>9s} {'check':>9s}   (M q/s, median of {args.rounds})")
    for k in (int(s) for s in args.sizes.split(",")):
        n = 1 << k
        q = C.random_queries(n, seed=k)
        columns = [jit.Float(np.ascontiguousarray(q[:, i])) for i in range(C.QUERY_DIM)]
        dr.eval(columns)
        x32 = torch.rand(n, width, device=args.device)
        x16 = x32.to(torch.bfloat16)
        gpu_seconds = []

        def resident():
            rgb = [c for answer in material.answers(columns) for c in answer]
            dr.eval(rgb)
            sync()

        def resident_history():
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            dr.kernel_history()  # cleared
            resident()
            kernels = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
            dr.set_flag(dr.JitFlag.KernelHistory, False)
            gpu_seconds.append(sum(h["execution_time"] for h in kernels) / 1e3)

        def torch_call(mlp, x):
            def call():
                with torch.no_grad():
                    mlp(x)
                sync()
            return call

        calls = {"numpy": lambda: (material.evaluate(q), sync()), "resident": resident,
                 "mlp32": torch_call(mlp32, x32), "mlp16": torch_call(mlp16, x16),
                 "check": lambda: C.as_queries(q, groups=True)}
        for call in calls.values():  # warm up: kernels traced, compiled, cached
            call()
            call()
        seconds = {name: [] for name in calls}
        for _ in range(args.rounds):
            for name, call in calls.items():
                start = time.perf_counter()
                call()
                seconds[name].append(time.perf_counter() - start)
            resident_history()
        rate = {name: n / np.median(s) / 1e6 for name, s in seconds.items()}
        gpu = n / np.median(gpu_seconds) / 1e6 if gpu_seconds and np.median(gpu_seconds) > 0 else float("nan")
        print(f"{'2^' + str(k):>9s} {rate['numpy']:13.1f} {rate['resident']:16.1f} {gpu:16.1f} "
              f"{rate['mlp32']:9.1f} {rate['mlp16']:9.1f} {rate['check']:9.1f}", flush=True)


if __name__ == "__main__":
    main()
