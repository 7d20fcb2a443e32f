"""Training-side subcommands: `train` and `export`. Torch is imported lazily."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from . import fit_command, trim_command
from neumip.core.config import TERMINATORS, MaterialConfig  # torch-free
from .train_config import LOSSES, PRESETS  # torch-free

HALF_VECTOR_HELP = ("the decoder also reads each light's half vector and cos(theta_d) (MaterialConfig.half_vector; "
                    "glossy materials: benchmarks/results/maps.txt)")
LOCAL_FRAME_HELP = ("with the classical base: the decoder also reads wi and wo in the frame of the base's normal "
                    "(MaterialConfig.local_frame; benchmarks/results/frame.txt)")
VISIBILITY_INPUT_HELP = ("with the classical base: the decoder also reads the base's visibility of each light, its "
                         "horizon test at the maps' resolution (MaterialConfig.visibility_input; "
                         "benchmarks/results/grazing.txt)")
TERMINATOR_HELP = ("with the classical base: the base's terms that the shadow terminator's softening S(g) multiplies "
                   "(MaterialConfig.terminator; none: a facet facing a grazing light answers as the real geometry's "
                   "lit faces do; benchmarks/results/terminator.txt)")
BASE_HELP = ("the classical material as the base: the answer is the principled BSDF on the material's maps (a "
             "pyramid at the maps' resolution) times exp(the decoder's correction), plus its additive term "
             "(MaterialConfig.base, training/TRAINING.md)")
RELIEF_HELP = ("parallax and occlusion from the material's height map: every lookup reads where the view ray "
               "first meets the height field, marched in STEPS steps on a height pyramid at the map's resolution, "
               "before the neural offset (MaterialConfig.relief, training/TRAINING.md)")


def add_terminator_argument(p: argparse.ArgumentParser) -> None:
    """`--terminator {all,specular,none}` (default `MaterialConfig.terminator`)."""
    p.add_argument("--terminator", choices=TERMINATORS, default=MaterialConfig.terminator, help=TERMINATOR_HELP)


def add_relief_argument(p: argparse.ArgumentParser, help_tail: str = "") -> None:
    """`--relief [STEPS]` (0, the default: none; alone: `MaterialConfig.relief_steps`)."""
    p.add_argument("--relief", type=int, nargs="?", const=MaterialConfig.relief_steps, default=0, metavar="STEPS",
                   help=RELIEF_HELP + help_tail + f"; STEPS defaults to {MaterialConfig.relief_steps}")


LOD_BIAS_HELP = ("raise every footprint's level of detail by K levels (MaterialConfig.lod_bias): the finest level then "
                 "answers footprints of 2^-K texels and less, the sharp samples of a close-up render, instead of "
                 "the appearance filtered by a texel; the data need footprints that fine (generate --sub-texel-levels K)")


def add_lod_bias_argument(p: argparse.ArgumentParser) -> None:
    """`--lod-bias K` (`MaterialConfig.lod_bias`, default 0: the paper's level of detail)."""
    p.add_argument("--lod-bias", type=int, default=0, metavar="K", help=LOD_BIAS_HELP + " (default 0)")


RESIDUAL_HELP = ("with --maps: also train a free texture, added to the encoded one, on every level of at most SIZE "
                 "texels per side (MapConfig.residual; default 0: none), where the data hold many queries per texel")
HIDDEN_HELP = (f"width of the hidden layers of both MLPs (default {MaterialConfig.hidden}, the paper's; "
               "the shipped materials too; 48 was measured, not shipped: benchmarks/results/quality_levers_log.md)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="fit a neural material to an MBTF data set and export it to ONNX")
    p.add_argument("data", help="data set folder (written by `neumip generate` or `write_dataset`)")
    p.add_argument("-o", "--output", required=True, help="output .onnx path (e.g. out/NAME.onnx)")
    p.add_argument("--force", action="store_true", help="replace the output model if it exists")
    p.add_argument("--preset", choices=tuple(PRESETS), default="ship",
                   help="training schedule preset (training/TRAINING.md)")
    p.add_argument("--config", help="JSON file of TrainConfig fields (applied over the preset)")
    p.add_argument("--checkpoint", help="checkpoint path (default NAME.run/checkpoint.pt beside the output); "
                   "resumes if it exists")
    level = p.add_mutually_exclusive_group()
    level.add_argument("--resolution", "--finest-resolution", type=int,
                       help="finest pyramid level, texels per side (default: the data's generator resolution, else 128)")
    level.add_argument("--budget", type=Path,
                       help="`neumip budget --json` output: train at its recommended finest resolution for the material")
    p.add_argument("--material", help="material name to look up in --budget (default: the output's file stem)")
    p.add_argument("--no-offset", action="store_true", help="train without the neural offset")
    p.add_argument("--maps", nargs="?", const="", metavar="NAME_OR_TOML",
                   help="map-informed model: its textures are encoded from the material's prefiltered maps "
                        "(the data's own material, or this library name / .toml); the export is the paper's graph")
    p.add_argument("--horizons", type=int, default=0, metavar="K",
                   help="with --maps: the horizon's elevation towards K azimuths among the map features "
                        "(shadows cast from afar; MapConfig.horizons)")
    p.add_argument("--residual", type=int, default=0, metavar="SIZE", help=RESIDUAL_HELP)
    p.add_argument("--description", default="", help="short description stored in the model metadata")
    p.add_argument("--head", choices=("relu", "yuv"), default="relu",
                   help="decoder output head: relu (paper) or yuv (authors' exp(YUV) - 1 with a shadow mask)")
    p.add_argument("--hidden", type=int, default=MaterialConfig.hidden, help=HIDDEN_HELP)
    p.add_argument("--half-vector", action="store_true", help=HALF_VECTOR_HELP)
    p.add_argument("--local-frame", action="store_true", help=LOCAL_FRAME_HELP)
    p.add_argument("--visibility-input", action="store_true", help=VISIBILITY_INPUT_HELP)
    add_terminator_argument(p)
    add_lod_bias_argument(p)
    p.add_argument("--base", action="store_true", help=BASE_HELP + "; the maps are the data's material's, or --maps'")
    add_relief_argument(p)
    p.add_argument("--views-material", metavar="NAME_OR_TOML",
                   help="material whose ground truth the progress grid NAME.progress.png shows (default: the "
                        "data's own, when its description can be rebuilt from meta.json)")
    for name, kind in (("steps", int), ("batch", int), ("lr", float), ("seed", int), ("blur-half-life", float),
                       ("candidates", int)):
        p.add_argument(f"--{name}", type=kind, help=f"override TrainConfig.{name.replace('-', '_')}")
    p.add_argument("--loss", choices=LOSSES, help="override TrainConfig.loss")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), help="override TrainConfig.device")
    p.add_argument("--compile", action="store_true", help="torch.compile the step (~1.5x faster on CPU after ~15 s)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: one per core; idle threads sleep "
                   "instead of spinning, so this holds up on a busy machine: training/TRAINING.md)")
    p.set_defaults(func=_train)
    fit_command.register(sub)

    p = sub.add_parser("export", help="export a training checkpoint to an ONNX material, or rewrite an "
                       "exported .onnx material with this version's graph (same weights and metadata; "
                       "upgrades a file of an older query contract version)")
    p.add_argument("checkpoint", help="checkpoint file written by `neumip train`, or an exported .onnx model")
    p.add_argument("-o", "--output", required=True, help="output .onnx path (e.g. models/NAME.onnx)")
    p.add_argument("--force", action="store_true", help="replace the output model if it exists")
    p.add_argument("--description", default="", help="short description stored in the metadata")
    p.add_argument("--material", metavar="NAME_OR_TOML",
                   help="declare the sampling lobe of this material's maps (library name or .toml; a renderer "
                        "samples the model's directions from it: client/mitsuba/bsdf.py), in place of the "
                        "file's or checkpoint's own")
    p.set_defaults(func=_export)
    _register_train_many(sub)
    trim_command.register(sub)


def train_settings(args: argparse.Namespace):
    import json
    from dataclasses import replace

    from .train_config import PRESETS, TrainConfig

    config = PRESETS[args.preset]
    if args.config:
        config = TrainConfig.from_dict({**config.to_dict(), **json.loads(Path(args.config).read_text())})
    overrides = {
        k: getattr(args, k)
        for k in ("steps", "batch", "lr", "seed", "blur_half_life", "loss", "device", "candidates")
        if getattr(args, k) is not None
    }
    if args.compile:
        overrides["compile"] = True
    return replace(config, **overrides)


def _map_source(args: argparse.Namespace):
    """(MapConfig or None, Microgeometry) of `--maps`, `--base` and `--relief`: the material's maps (the data's own
    material's, or the one `--maps` names), with the map encoder's config under `--maps`; None without either."""
    maps = map_config(args, args.maps is not None)
    if maps is None and not args.base and not args.relief:
        return None
    return maps, data_geometry(args.data, args.maps)


def map_config(args: argparse.Namespace, maps: bool):
    """The map encoder's `MapConfig` of `--maps`, `--horizons` and `--residual` (None without `--maps`)."""
    for flag in ("horizons", "residual"):
        if getattr(args, flag) and not maps:
            raise ValueError(f"--{flag} is a feature of the map-informed model: pass --maps too")
    if not maps:
        return None
    from .maps import MapConfig

    return MapConfig(horizons=args.horizons, residual=args.residual)


def data_geometry(data: str | Path, material: str | None = None):
    """The `Microgeometry` (maps) of a data set's material, rebuilt from its meta.json (or of `material`, a
    name or description file, when given)."""
    from .dataset import open_dataset
    from .microgeometry.description import resolve
    from .views import data_material

    meta = open_dataset(data).meta
    return resolve(data_material(meta.get("material") or {}, material or None, meta.get("description_dir")))


def _data_resolution(data: str, default: int = 128) -> int:
    """The finest resolution the data set was sampled for (its generator's), else `default`."""
    import json

    meta = Path(data) / "meta.json"
    if not meta.exists():
        return default  # open_dataset reports the real problem
    generator = json.loads(meta.read_text()).get("generator")
    return int(generator.get("resolution", default)) if isinstance(generator, dict) else default


def _budget_resolution(args: argparse.Namespace, output: Path) -> int | None:
    """The finest resolution `--budget` recommends for the material (None without --budget); says so
    when that is finer than the data was sampled for (regenerate it with --resolution)."""
    import json

    from .trim import finest_level_from_budget

    if args.budget is None:
        return None
    name = args.material or output.stem
    finest_level_from_budget(budget := json.loads(args.budget.read_text()), name)  # TrimError if absent
    resolution = next(int(m["recommended_resolution"]) for m in budget["materials"] if m["material"] == name)
    if resolution > _data_resolution(args.data, resolution):
        print(f"note: the budget asks for {resolution}^2, finer than the data was sampled for; "
              f"regenerate it with `neumip generate --resolution {resolution}` for a model that resolves it")
    print(f"training {name} at {resolution}^2 (recommended by {args.budget})")
    return resolution


def output_path(args: argparse.Namespace, done: bool) -> Path:
    """--output as a .onnx path that may be written (`done`: a model is already there)."""
    from neumip.client.cli import CommandError

    output = Path(args.output)
    if output.suffix != ".onnx":
        raise CommandError(f"--output must end in .onnx, got {output}")
    if done and not args.force:
        raise CommandError(f"{output} exists: pass --force to replace it, or choose another --output")
    return output


def import_torch(threads: int | None) -> None:
    """Import torch with `threads` CPU threads (None: one per core) that sleep while they wait."""
    # torch's OpenMP threads spin while they wait by default: on a machine whose cores other jobs
    # use, 2 spinning threads made a quick run ~7x slower than 1; sleeping threads do not (TRAINING.md)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import torch

    if threads:
        torch.set_num_threads(threads)


def _step_bar(bar, batch: int):
    """(step, loss) callback that advances `bar` to `step`, with the loss and the query rate."""
    def progress(step: int, loss: float) -> None:
        bar.update(step - bar.n)
        if step % 10 == 0:
            rate = bar.format_dict["rate"] or 0.0
            bar.set_postfix(loss=f"{loss:.4g}", queries_per_s=f"{rate * batch / 1e6:.2f}M")
    return progress


def progress_line(trainer, progress_png: Path) -> str:
    step, _levels, mse = trainer.state.progress[-1]
    return f"step {step}: held-out MSE {mse * 1e3:.4f}e-3, {progress_png} updated"


def print_finished(table: dict, paths: dict, kept: str) -> None:
    """Print the validation table, the files written and the run's length (`kept`: where its state is)."""
    from .validation import format_table

    print(format_table(table))
    size = paths["onnx"].stat().st_size / 1e6
    print(f"wrote {paths['onnx']} ({size:.2f} MB), {paths['json']}, {paths['png']}, {paths['progress']}")
    dropped = table.get("dropped_steps", 0)
    extra = f" (and {dropped} of the candidate starts dropped)" if dropped else ""
    print(f"trained {table['steps']} steps{extra} in {table['train_seconds'] / 60:.1f} min; {kept}")
    if "base_choice" in table:
        choice = table["base_choice"]
        print(f"classical base: reference log MSE x1e-3 {choice['reference_log_mse_without'] * 1e3:.4f} without, "
              f"{choice['reference_log_mse_with'] * 1e3:.4f} with (kept only {choice['margin'] * 100:.0f} % lower): the "
              f"model {choice['kept']} it was kept")
    if "seed_choice" in table:
        choice = table["seed_choice"]
        errors = ", ".join(f"{seed}: {e * 1e3:.4f}" for seed, e in zip(choice["seeds"], choice["reference_log_mse"]))
        print(f"initial weights: reference log MSE x1e-3 of seeds {errors}: seed {choice['kept']} kept")


def _train(args: argparse.Namespace) -> int:
    from neumip.client.cli import CommandError

    from .fit import work_folder

    output = output_path(args, Path(args.output).exists())
    import_torch(args.threads)
    from tqdm import tqdm

    from .checkpoint import CheckpointError
    from .dataset import DatasetError
    from .outputs import install_outputs, progress_path, write_progress
    from .base import base_resolution
    from .relief import relief_resolution
    from .train import Trainer, TrainingDiverged, TrainingError
    from .views import ViewGrid, trace_views

    checkpoint = Path(args.checkpoint or work_folder(output) / "checkpoint.pt")
    try:
        config = train_settings(args)
        resolution = args.resolution or _budget_resolution(args, output) or _data_resolution(args.data)
        maps = _map_source(args)
        material = MaterialConfig(resolution=resolution, offset=not args.no_offset, head=args.head,
                                  half_vector=args.half_vector, hidden=args.hidden, local_frame=args.local_frame,
                                  terminator=args.terminator, visibility_input=args.visibility_input,
                                  base=base_resolution(maps[1]) if args.base else 0,
                                  relief=relief_resolution(maps[1]) if args.relief else 0,
                                  relief_steps=args.relief or MaterialConfig.relief_steps, lod_bias=args.lod_bias)
        trainer = Trainer(args.data, checkpoint, material, config, args.description, maps)
    except (ValueError, DatasetError, CheckpointError) as exc:
        raise CommandError(str(exc)) from exc
    meta = trainer.data.meta
    views = trace_views(meta.get("material") or {}, ViewGrid(), resolution, checkpoint.parent / "views",
                        args.views_material, meta.get("description_dir"))
    progress_png = progress_path(output)

    def on_progress(trainer: Trainer) -> None:
        write_progress(trainer, progress_png, views)
        bar.write(progress_line(trainer, progress_png))

    bar = tqdm(total=trainer.config.total_steps, initial=trainer.steps_done, unit="step", dynamic_ncols=True)
    try:
        table = trainer.run(_step_bar(bar, config.batch), on_progress)
    except (TrainingDiverged, TrainingError) as exc:
        raise CommandError(str(exc)) from exc
    except KeyboardInterrupt:
        bar.close()
        if checkpoint.exists():
            print(f"interrupted: re-run the same command to resume from {checkpoint}")
        raise
    finally:
        bar.close()
    print_finished(table, install_outputs(trainer, table, output, views), f"checkpoint {checkpoint}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from neumip.client.cli import CommandError

    from .export import export_checkpoint

    if Path(args.output).exists() and not args.force:
        raise CommandError(f"{args.output} exists: pass --force to replace it, or choose another --output")
    sampling = "keep"
    if args.material:
        from .microgeometry.description import DescriptionError
        from .microgeometry.lobe import material_lobe

        try:
            sampling = material_lobe(args.material)
        except (DescriptionError, OSError, ValueError) as exc:
            raise CommandError(f"--material {args.material}: {exc}") from exc
        print(f"sampling lobe of {args.material}: {sampling or 'none (the cosine alone)'}")

    if args.checkpoint.endswith(".onnx"):
        from google.protobuf.message import DecodeError

        from .export_read import CHECK_QUERIES, reexport_file

        try:
            path, difference = reexport_file(args.checkpoint, args.output, args.description, sampling)
        except (OSError, ValueError, DecodeError) as exc:  # ModelLayoutError, unreadable or corrupt file
            raise CommandError(f"{args.checkpoint}: cannot re-export: {exc}") from exc
        print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB); largest answer difference from "
              f"{args.checkpoint} on {CHECK_QUERIES:,} random queries: {difference:.3g}")
        return 0
    path = export_checkpoint(args.checkpoint, args.output, args.description, sampling)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


# --- train-many: a material library, in this process or one Ray task per material ----------------

def _register_train_many(sub: argparse._SubParsersAction) -> None:
    from .cluster import add_ray_arguments

    p = sub.add_parser(
        "train-many", help="train a library of materials (one `neumip train` each), optionally as Ray tasks",
        description="Train every [NAME=]DATA (NAME defaults to the folder's name) into MODELS/NAME.onnx. "
        "Finished materials (NAME.onnx and NAME.json present) are skipped, interrupted ones resume from "
        "RUNS/NAME/checkpoint.pt; outputs are moved into place only when whole.",
    )
    p.add_argument("jobs", nargs="+", metavar="[NAME=]DATA", help="data set folder, optionally named")
    p.add_argument("-o", "--models", required=True, help="folder of the exported materials")
    p.add_argument("--runs", default="runs", help="folder of the checkpoints (default runs)")
    p.add_argument("--preset", choices=tuple(PRESETS), default="ship", help="training schedule preset")
    p.add_argument("--config", help="JSON file of TrainConfig fields (applied over the preset)")
    p.add_argument("--resolution", type=int, help="finest pyramid level (default: each data set's resolution)")
    p.add_argument("--hidden", type=int, default=MaterialConfig.hidden, help=HIDDEN_HELP)
    p.add_argument("--half-vector", action="store_true", help=HALF_VECTOR_HELP)
    p.add_argument("--no-offset", action="append", default=[], metavar="NAME",
                   help="train NAME without the neural offset (repeatable)")
    add_relief_argument(p, " (every material with a height map but those trained with --no-offset)")
    p.add_argument("--steps", type=int, help="override TrainConfig.steps")
    p.add_argument("--candidates", type=int, help="override TrainConfig.candidates")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), help="override TrainConfig.device")
    p.add_argument("--threads", type=int, default=1, help="torch threads of each material (default 1; "
                   "with --ray the CPUs each task reserves)")
    add_ray_arguments(p, "material", per_task=False)
    p.set_defaults(func=_train_many, batch=None, lr=None, seed=None, blur_half_life=None, loss=None, compile=False)


def _library_jobs(args: argparse.Namespace) -> list:
    """The MaterialJob of every [NAME=]DATA, described as models/make_models.sh describes them."""
    from neumip.client.cli import CommandError

    from .library import MaterialJob
    from .relief import relief_resolution

    jobs = []
    for spec in args.jobs:
        name, _, data = spec.rpartition("=")
        name = name or Path(data).name
        resolution = args.resolution or _data_resolution(data)
        offset = name not in args.no_offset
        relief = relief_resolution(data_geometry(data)) if args.relief and offset else 0
        kind = ("relief, " if relief else "") + ("neural offset" if offset else "no neural offset")
        material = MaterialConfig(resolution=resolution, offset=offset, hidden=args.hidden,
                                  half_vector=args.half_vector, relief=relief,
                                  relief_steps=args.relief or MaterialConfig.relief_steps)
        width = f"MLP width {args.hidden}, " if args.hidden != MaterialConfig.hidden else ""
        description = f"{Path(data).name}, {resolution}^2, {kind}, {width}{args.preset} preset"
        jobs.append(MaterialJob(name, data, material, description))
    unknown = set(args.no_offset) - {job.name for job in jobs}
    if unknown:
        raise CommandError(f"--no-offset names no material: {', '.join(sorted(unknown))}")
    return jobs


def _train_many(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from neumip.client.cli import CommandError

    from .cluster import ray_config
    from .library import LibrarySettings, finished, train_library
    from .validation import format_table

    ray = ray_config(args)
    try:
        settings = LibrarySettings(Path(args.models), Path(args.runs), train_settings(args), args.threads)
        jobs = _library_jobs(args)
    except ValueError as exc:
        raise CommandError(str(exc)) from exc
    done = [job.name for job in jobs if finished(job, settings)]
    if done:
        print(f"finished already (remove NAME.onnx and NAME.json to retrain): {', '.join(done)}")
    bar = tqdm(total=len(jobs), initial=len(done), unit="material", dynamic_ncols=True, position=0)
    steps: dict[str, tqdm] = {}  # a bar per material trained in this process

    def on_done(job, result) -> None:
        if job.name in steps:
            steps.pop(job.name).close()
        bar.update(1)
        outcome = f"failed: {result}" if isinstance(result, Exception) else "\n" + format_table(result)
        tqdm.write(f"{job.name}: {outcome}")

    def progress(job):
        steps[job.name] = tqdm(total=settings.config.total_steps, unit="step", desc=job.name, leave=False, position=1)
        return lambda step, loss: steps[job.name].update(step - steps[job.name].n)

    try:
        results = train_library(jobs, settings, ray, on_done, progress)
    finally:
        bar.close()
    failed = [name for name, result in results.items() if isinstance(result, Exception)]
    print(f"{len(results) - len(failed)} trained, {len(done)} skipped, {len(failed)} failed"
          + (f": {', '.join(failed)} (re-run to retry; finished materials are skipped)" if failed else ""))
    return 1 if failed else 0
