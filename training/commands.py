"""Training-side subcommands: `train` and `export`. Torch is imported lazily."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from .train_config import PRESETS  # torch-free


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="fit a neural material to an MBTF data set and export it to ONNX")
    p.add_argument("data", help="data set folder (written by `neumip generate` or `write_dataset`)")
    p.add_argument("-o", "--output", required=True, help="output .onnx path (e.g. out/NAME.onnx)")
    p.add_argument("--force", action="store_true", help="replace the output model if it exists")
    p.add_argument("--preset", choices=tuple(PRESETS), default="ship",
                   help="training schedule preset (training/TRAINING.md)")
    p.add_argument("--config", help="JSON file of TrainConfig fields (applied over the preset)")
    p.add_argument("--checkpoint", help="checkpoint path (default runs/NAME/checkpoint.pt); resumes if it exists")
    p.add_argument("--resolution", type=int,
                   help="finest pyramid level, texels per side (default: the data's generator resolution, else 128)")
    p.add_argument("--no-offset", action="store_true", help="train without the neural offset")
    p.add_argument("--description", default="", help="short description stored in the model metadata")
    p.add_argument("--head", choices=("relu", "yuv"), default="relu",
                   help="decoder output head: relu (paper) or yuv (authors' exp(YUV) - 1 with a shadow mask)")
    p.add_argument("--views-material", metavar="NAME_OR_TOML",
                   help="material whose ground truth the progress grid NAME.progress.png shows (default: the "
                        "data's own, when its description can be rebuilt from meta.json)")
    for name, kind in (("steps", int), ("batch", int), ("lr", float), ("seed", int), ("blur-half-life", float)):
        p.add_argument(f"--{name}", type=kind, help=f"override TrainConfig.{name.replace('-', '_')}")
    p.add_argument("--loss", choices=("comb2", "mse"), help="override TrainConfig.loss")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), help="override TrainConfig.device")
    p.add_argument("--compile", action="store_true", help="torch.compile the step (~1.5x faster on CPU after ~15 s)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: one per core; idle threads sleep "
                   "instead of spinning, so this holds up on a busy machine: training/TRAINING.md)")
    p.set_defaults(func=_train)

    p = sub.add_parser("export", help="export a training checkpoint to an ONNX material")
    p.add_argument("checkpoint", help="checkpoint file written by `neumip train`")
    p.add_argument("-o", "--output", required=True, help="output .onnx path (e.g. models/NAME.onnx)")
    p.add_argument("--force", action="store_true", help="replace the output model if it exists")
    p.add_argument("--description", default="", help="short description stored in the metadata")
    p.set_defaults(func=_export)


def _train_config(args: argparse.Namespace):
    import json
    from dataclasses import replace

    from .train_config import PRESETS, TrainConfig

    config = PRESETS[args.preset]
    if args.config:
        config = TrainConfig.from_dict({**config.to_dict(), **json.loads(Path(args.config).read_text())})
    overrides = {
        k: getattr(args, k)
        for k in ("steps", "batch", "lr", "seed", "blur_half_life", "loss", "device")
        if getattr(args, k) is not None
    }
    if args.compile:
        overrides["compile"] = True
    return replace(config, **overrides)


def _data_resolution(data: str, default: int = 128) -> int:
    """The finest resolution the data set was sampled for (its generator's), else `default`."""
    import json

    meta = Path(data) / "meta.json"
    if not meta.exists():
        return default  # open_dataset reports the real problem
    generator = json.loads(meta.read_text()).get("generator")
    return int(generator.get("resolution", default)) if isinstance(generator, dict) else default


def _train(args: argparse.Namespace) -> int:
    from neumip.client.cli import CommandError

    output = Path(args.output)
    if output.suffix != ".onnx":
        raise CommandError(f"--output must end in .onnx, got {output}")
    if output.exists() and not args.force:
        raise CommandError(f"{output} exists: pass --force to replace it, or choose another --output")
    # torch's OpenMP threads spin while they wait by default: on a machine whose cores other jobs
    # use, 2 spinning threads made a quick run ~7x slower than 1; sleeping threads do not (TRAINING.md)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch
    from tqdm import tqdm

    from .checkpoint import CheckpointError
    from .config import MaterialConfig
    from .dataset import DatasetError
    from .outputs import progress_path, write_outputs, write_progress
    from .train import Trainer, TrainingDiverged, TrainingError
    from .validation import format_table
    from .views import ViewGrid, trace_views

    if args.threads:
        torch.set_num_threads(args.threads)
    checkpoint = Path(args.checkpoint or Path("runs") / output.stem / "checkpoint.pt")
    try:
        config = _train_config(args)
        resolution = args.resolution or _data_resolution(args.data)
        material = MaterialConfig(resolution=resolution, offset=not args.no_offset, head=args.head)
        trainer = Trainer(args.data, checkpoint, material, config, args.description)
    except (ValueError, DatasetError, CheckpointError) as exc:
        raise CommandError(str(exc)) from exc
    views = trace_views(trainer.data.meta.get("material") or {}, ViewGrid(), resolution,
                        checkpoint.parent / "views", args.views_material)
    progress_png = progress_path(output)

    def on_progress(trainer: Trainer) -> None:
        write_progress(trainer, progress_png, views)
        step, _levels, mse = trainer.state.progress[-1]
        bar.write(f"step {step}: held-out MSE {mse * 1e3:.4f}e-3, {progress_png} updated")

    bar = tqdm(total=config.steps, initial=trainer.state.step, unit="step", dynamic_ncols=True)

    def progress(step: int, loss: float) -> None:
        bar.update(1)
        if step % 10 == 0:
            rate = bar.format_dict["rate"] or 0.0
            bar.set_postfix(loss=f"{loss:.4g}", queries_per_s=f"{rate * config.batch / 1e6:.2f}M")

    try:
        table = trainer.run(progress, on_progress)
    except (TrainingDiverged, TrainingError) as exc:
        raise CommandError(str(exc)) from exc
    except KeyboardInterrupt:
        bar.close()
        if checkpoint.exists():
            print(f"interrupted: re-run the same command to resume from {checkpoint}")
        raise
    finally:
        bar.close()
    paths = write_outputs(trainer, table, output, views)
    print(format_table(table))
    size = paths["onnx"].stat().st_size / 1e6
    print(f"wrote {paths['onnx']} ({size:.2f} MB), {paths['json']}, {paths['png']}, {paths['progress']}")
    print(f"trained {trainer.state.step} steps in {trainer.state.seconds / 60:.1f} min; checkpoint {checkpoint}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from neumip.client.cli import CommandError

    from .export import export_checkpoint

    if Path(args.output).exists() and not args.force:
        raise CommandError(f"{args.output} exists: pass --force to replace it, or choose another --output")

    path = export_checkpoint(args.checkpoint, args.output, args.description)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0
