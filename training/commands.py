"""Training-side subcommands: `train`, `export` and `train-many`, and what `fit` shares with them: the flags of
`MaterialConfig`, `TrainConfig` and `MapConfig`, generated from their fields (`core.flags`). Torch is imported
lazily."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from neumip.core import flags
from neumip.core.config import DERIVED_FIELDS, FIELD_CHOICES, MaterialConfig  # torch-free
from neumip.training.loop.config import LOSSES, PRESETS, RECIPES, Recipe, TrainConfig  # torch-free

BASE_HELP = ("the classical material as the base: the answer is the principled BSDF on the material's maps (a "
             "pyramid at the maps' resolution) times exp(the decoder's correction), plus its additive term "
             "(MaterialConfig.base, training/TRAINING.md)")
RELIEF_HELP = ("parallax and occlusion from the material's height map: every lookup reads where the view ray "
               "first meets the height field, marched in STEPS steps on a height pyramid at the map's resolution, "
               "before the neural offset (MaterialConfig.relief, training/TRAINING.md)")
TRAIN_CHOICES = {"loss": LOSSES, "finish_loss": LOSSES + ("",), "coarse_loss": LOSSES + ("",), "device": ("auto", "cpu", "cuda"),
                 "lr_schedule": ("constant", "cosine")}
"""The values a string field of `TrainConfig` takes."""
MAP_FLAGS = {"hidden": "map_hidden", "layers": "map_layers"}
"""`MapConfig` fields whose flags are renamed (`MaterialConfig` has fields of the same names)."""


def add_material_flags(p: argparse.ArgumentParser, skip: tuple[str, ...] = ()) -> None:
    """A flag for each `MaterialConfig` field a user sets (not `DERIVED_FIELDS`), `--relief [STEPS]`, and the
    `TrainConfig` fields as overrides of the preset."""
    model = p.add_argument_group("model (MaterialConfig, over the --recipe's values)")
    flags.add_flags(model, MaterialConfig, skip=DERIVED_FIELDS + skip, choices=FIELD_CHOICES,
                    metavars={"lod_bias": "K"}, overrides=True, show_default=True)
    model.add_argument("--relief", type=int, nargs="?", const=MaterialConfig.relief_steps, metavar="STEPS",
                       help=RELIEF_HELP + f"; STEPS defaults to {MaterialConfig.relief_steps}; 0: none")
    schedule = p.add_argument_group("training (TrainConfig, over the --preset's values)")
    schedule.add_argument("--config", help="JSON file of TrainConfig fields (applied over the preset)")
    flags.add_flags(schedule, TrainConfig, choices=TRAIN_CHOICES, overrides=True)


def apply_recipe(args: argparse.Namespace, recipe: Recipe, maps_on=True, base_on=True) -> None:
    """Fill what the command line left unset with `recipe`'s values: its `MaterialConfig` fields, its map encoder
    (`args.maps` set to `maps_on`), its base (`args.base` to `base_on`) and its relief. A flag given wins."""
    for name, value in recipe.material.items():
        if getattr(args, name, None) is None:
            setattr(args, name, value)
    if recipe.maps is not None and not args.maps:
        args.maps = maps_on
        for name, value in recipe.maps.items():
            if getattr(args, MAP_FLAGS.get(name, name), None) is None:
                setattr(args, MAP_FLAGS.get(name, name), value)
    if recipe.base and not args.base:
        args.base = base_on
    if args.relief is None:
        args.relief = recipe.relief


def add_map_flags(p: argparse.ArgumentParser) -> None:
    """The `MapConfig` fields, for a map-informed model (`--maps`)."""
    from neumip.training.model.maps import MapConfig  # (torch-free at import)

    group = p.add_argument_group("map encoder (MapConfig, with --maps)")
    flags.add_flags(group, MapConfig, overrides=True, rename=MAP_FLAGS,
                    metavars={"horizons": "K", "residual": "SIZE"})


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="fit a neural material to an MBTF data set and export it to ONNX")
    p.add_argument("data", help="data set folder (written by `neumip generate` or `write_dataset`)")
    p.add_argument("-o", "--output", required=True, help="output .onnx path (e.g. out/NAME.onnx)")
    p.add_argument("--force", action="store_true", help="replace the output model if it exists")
    p.add_argument("--preset", choices=tuple(PRESETS), default="ship",
                   help="training schedule preset (training/TRAINING.md)")
    p.add_argument("--checkpoint", help="checkpoint path (default NAME.run/checkpoint.pt beside the output); "
                   "resumes if it exists")
    level = p.add_mutually_exclusive_group()
    level.add_argument("--resolution", "--finest-resolution", type=int,
                       help="finest pyramid level, texels per side (default: the data's generator resolution, else 128)")
    level.add_argument("--budget", type=Path,
                       help="`neumip budget --json` output: train at its recommended finest resolution for the material")
    p.add_argument("--material", help="material name to look up in --budget (default: the output's file stem)")
    p.add_argument("--recipe", choices=tuple(RECIPES), default="paper",
                   help="what the model is made of where no flag says otherwise (training/loop/config.py RECIPES; "
                        "maps: the shipped map-informed model, on the data's material's maps)")
    p.add_argument("--maps", nargs="?", const="", metavar="NAME_OR_TOML",
                   help="map-informed model: its textures are encoded from the material's prefiltered maps "
                        "(the data's own material, or this library name / .toml); the export is the paper's graph")
    p.add_argument("--description", default="", help="short description stored in the model metadata")
    p.add_argument("--base", action="store_true", help=BASE_HELP + "; the maps are the data's material's, or --maps'")
    p.add_argument("--views-material", metavar="NAME_OR_TOML",
                   help="material whose ground truth the progress grid NAME.progress.png shows (default: the "
                        "data's own, when its description can be rebuilt from meta.json)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: one per core; idle threads sleep "
                   "instead of spinning, so this holds up on a busy machine: training/TRAINING.md)")
    add_material_flags(p)
    add_map_flags(p)
    p.set_defaults(func=_train)

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
    p.add_argument("--half-textures", action="store_true",
                   help="store the textures in float16 (MaterialConfig.half_textures: about half a map-informed "
                        "file); a float32 model's answers move by the rounding (the largest difference is printed)")
    p.set_defaults(func=_export)
    _register_train_many(sub)


def train_settings(args: argparse.Namespace) -> TrainConfig:
    """The `TrainConfig` of a command line: the preset, then --config's JSON, then each flag given."""
    import json
    from dataclasses import replace

    config = PRESETS[args.preset]
    if getattr(args, "config", None):
        config = TrainConfig.from_dict({**config.to_dict(), **json.loads(Path(args.config).read_text())})
    return replace(config, **flags.values(args, TrainConfig))


def material_config(args: argparse.Namespace, resolution: int, geometry=None, **fields) -> MaterialConfig:
    """The `MaterialConfig` of a command line: its generated flags, the finest `resolution`, and the pyramids
    the material's maps (`geometry`, a `Microgeometry`) give with --base and --relief; `fields` override."""
    from neumip.training.model.base import base_resolution
    from neumip.training.model.relief import relief_resolution

    chosen = flags.values(args, MaterialConfig, skip=DERIVED_FIELDS)
    if "base" not in fields:
        fields["base"] = base_resolution(geometry) if getattr(args, "base", False) not in (False, None, "off") else 0
    if "relief" not in fields:
        fields["relief"] = relief_resolution(geometry) if args.relief else 0
    return MaterialConfig(resolution=resolution, relief_steps=args.relief or MaterialConfig.relief_steps,
                          **{**chosen, **fields})


def _map_source(args: argparse.Namespace):
    """(MapConfig or None, Microgeometry) of `--maps`, `--base` and `--relief`: the material's maps (the data's own
    material's, or the one `--maps` names), with the map encoder's config under `--maps`; None without either."""
    from neumip.training.loop.views import data_geometry

    maps = map_config(args, args.maps is not None)
    if maps is None and not args.base and not args.relief:
        return None
    return maps, data_geometry(args.data, args.maps)


def map_config(args: argparse.Namespace, maps: bool):
    """The map encoder's `MapConfig` of `--maps` and the map flags (None without `--maps`)."""
    from neumip.training.model.maps import MapConfig

    chosen = flags.values(args, MapConfig, rename=MAP_FLAGS)
    if chosen and not maps:
        given = ", ".join(flags.flag(MAP_FLAGS.get(name, name)) for name in chosen)
        raise ValueError(f"{given} is a feature of the map-informed model: pass --maps too")
    return MapConfig(**chosen) if maps else None


def _data_resolution(data: str, default: int = 128) -> int:
    """The finest resolution the data set was sampled for (its generator's), else `default`."""
    from neumip.groundtruth.dataset import read_meta

    meta = Path(data) / "meta.json"
    if not meta.exists():
        return default  # open_dataset reports the real problem
    generator = read_meta(meta).get("generator")
    return int(generator.get("resolution", default)) if isinstance(generator, dict) else default


def _budget_resolution(args: argparse.Namespace, output: Path) -> int | None:
    """The finest resolution `--budget` recommends for the material (None without --budget); says so
    when that is finer than the data was sampled for (regenerate it with --resolution)."""
    import json

    from neumip.training.export.trim import finest_level_from_budget

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
    from neumip.core.errors import CommandError

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
    from neumip.training.loop.validation import format_table

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
    from neumip.core.errors import CommandError

    from neumip.training.loop.paths import occupied, work_folder

    output = output_path(args, occupied(args.output))
    import_torch(args.threads)
    from tqdm import tqdm

    from neumip.training.loop.checkpoint import CheckpointError
    from neumip.groundtruth.dataset import DatasetError
    from neumip.training.loop.outputs import install_outputs, write_progress
    from neumip.training.loop.paths import progress_path
    from neumip.training.loop.train import Trainer, TrainingDiverged, TrainingError
    from neumip.training.loop.views import ViewGrid, trace_views

    checkpoint = Path(args.checkpoint or work_folder(output) / "checkpoint.pt")
    try:
        apply_recipe(args, RECIPES[args.recipe], maps_on="", base_on=True)
        config = train_settings(args)
        resolution = args.resolution or _budget_resolution(args, output) or _data_resolution(args.data)
        maps = _map_source(args)
        material = material_config(args, resolution, maps[1] if maps else None)
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
    from neumip.core.errors import CommandError

    from neumip.training.loop.outputs import export_checkpoint

    if Path(args.output).exists() and not args.force:
        raise CommandError(f"{args.output} exists: pass --force to replace it, or choose another --output")
    sampling = "keep"
    if args.material:
        from neumip.groundtruth.description import DescriptionError
        from neumip.groundtruth.lobe import material_lobe

        try:
            sampling = material_lobe(args.material)
        except (DescriptionError, OSError, ValueError) as exc:
            raise CommandError(f"--material {args.material}: {exc}") from exc
        print(f"sampling lobe of {args.material}: {sampling or 'none (the cosine alone)'}")

    if args.checkpoint.endswith(".onnx"):
        from google.protobuf.message import DecodeError

        from neumip.training.export.upgrade import CHECK_QUERIES, reexport_file

        try:
            path, difference = reexport_file(args.checkpoint, args.output, args.description, sampling,
                                             args.half_textures)
        except (OSError, ValueError, DecodeError) as exc:  # ModelLayoutError, unreadable or corrupt file
            raise CommandError(f"{args.checkpoint}: cannot re-export: {exc}") from exc
        print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB); largest answer difference from "
              f"{args.checkpoint} on {CHECK_QUERIES:,} random queries: {difference:.3g}")
        return 0
    path = export_checkpoint(args.checkpoint, args.output, args.description, sampling, args.half_textures)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    return 0


# --- train-many: a material library, in this process or one Ray task per material ----------------

def _register_train_many(sub: argparse._SubParsersAction) -> None:
    from neumip.core.cluster import add_ray_arguments

    p = sub.add_parser(
        "train-many", help="train a library of materials (one `neumip train` each), optionally as Ray tasks",
        description="Train every [NAME=]DATA (NAME defaults to the folder's name) into MODELS/NAME.onnx. "
        "Finished materials (NAME.onnx and NAME.json present) are skipped, interrupted ones resume from "
        "RUNS/NAME/checkpoint.pt; outputs are moved into place only when whole. The model and training flags "
        "are those of `neumip train`, for every material.",
    )
    p.add_argument("jobs", nargs="+", metavar="[NAME=]DATA", help="data set folder, optionally named")
    p.add_argument("-o", "--models", required=True, help="folder of the exported materials")
    p.add_argument("--runs", default="runs", help="folder of the checkpoints (default runs)")
    p.add_argument("--preset", choices=tuple(PRESETS), default="ship", help="training schedule preset")
    p.add_argument("--resolution", type=int, help="finest pyramid level (default: each data set's resolution)")
    p.add_argument("--no-offset", action="append", default=[], metavar="NAME",
                   help="train NAME without the neural offset (repeatable); with --relief, NAME has no relief either")
    p.add_argument("--maps", action="store_true", help="map-informed models: each encoded from its data's material's "
                   "prefiltered maps")
    p.add_argument("--base", action="store_true", help=BASE_HELP + "; each data set's material's maps")
    p.add_argument("--threads", type=int, default=1, help="torch threads of each material (default 1; "
                   "with --ray the CPUs each task reserves)")
    add_material_flags(p, skip=("offset",))
    add_map_flags(p)
    add_ray_arguments(p, "material", per_task=False)
    p.set_defaults(func=_train_many)


def _library_jobs(args: argparse.Namespace) -> list:
    """The MaterialJob of every [NAME=]DATA, described as models/make_models.sh describes them."""
    from neumip.core.errors import CommandError
    from neumip.training.loop.library import MaterialJob
    from neumip.training.loop.views import data_geometry

    maps = map_config(args, args.maps)
    jobs = []
    for spec in args.jobs:
        name, _, data = spec.rpartition("=")
        name = name or Path(data).name
        resolution = args.resolution or _data_resolution(data)
        offset = name not in args.no_offset
        geometry = data_geometry(data) if args.maps or args.base or (args.relief and offset) else None
        material = material_config(args, resolution, geometry, offset=offset,
                                   **({} if offset else {"relief": 0}))
        kind = ("relief, " if material.relief else "") + ("neural offset" if offset else "no neural offset")
        width = f"MLP width {material.hidden}, " if material.hidden != MaterialConfig.hidden else ""
        description = f"{Path(data).name}, {resolution}^2, {kind}, {width}{args.preset} preset"
        jobs.append(MaterialJob(name, data, material, description, maps))
    unknown = set(args.no_offset) - {job.name for job in jobs}
    if unknown:
        raise CommandError(f"--no-offset names no material: {', '.join(sorted(unknown))}")
    return jobs


def _train_many(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from neumip.core.errors import CommandError

    from neumip.core.cluster import ray_config
    from neumip.training.loop.library import LibrarySettings, finished, train_library
    from neumip.training.loop.validation import format_table

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
