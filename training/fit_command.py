"""`neumip fit`: the command line of `training/loop/fit.py`: a material description to a model in one command,
with one progress bar for the whole run. Its model and training flags are `neumip train`'s (`commands`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from neumip.training import commands
from neumip.training.loop.config import PRESETS, RECIPES  # torch-free

SHIPPED_MODELS = Path(__file__).resolve().parents[1] / "models"
"""The shipped models of a checkout (an editable install); a wheel has none, and the verdict then stands alone."""


def register(sub: argparse._SubParsersAction) -> None:
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.sampling import QuerySampling

    p = sub.add_parser(
        "fit", help="material description -> model in one command: ground truth, training, validation, export",
        description="Path-trace the ground truth of MATERIAL (a .toml description with its maps beside it, or "
        "a shipped name), train a neural material on it, validate it on held-out queries and export "
        "OUTPUT (.onnx) with NAME.json, NAME.loss.png and NAME.progress.png beside it. The data set, "
        "checkpoint and progress views go into the work folder (default NAME.run/ beside the output); "
        "an interrupted fit resumes where it stopped when the same command is run again.",
    )
    p.add_argument("material", help="a .toml material description (groundtruth/MATERIALS.md) "
                   "or a shipped material name (neumip generate --list)")
    p.add_argument("-o", "--output", required=True, help="output .onnx path (e.g. models/NAME.onnx)")
    p.add_argument("--force", action="store_true", help="replace a finished model at the output")
    p.add_argument("--preset", choices=tuple(PRESETS), default="ship",
                   help="training schedule preset, as neumip train takes it (training/TRAINING.md)")
    p.add_argument("--resolution", type=int, help="finest pyramid level, texels per side (default: the "
                   "description's); the ground truth has --queries-per-texel per texel of it, with footprints "
                   "sampled for the description's resolution where that is finer")
    p.add_argument("--work", type=Path, help="folder of the data set, checkpoint and views (default NAME.run/ "
                   "beside the output)")
    p.add_argument("--data", type=Path, help="data set folder of the ground truth, written or resumed (default "
                   "WORK/data); models of one material, e.g. with and without --no-offset, can share it")
    p.add_argument("--queries-per-texel", type=float, default=QuerySampling.queries_per_texel,
                   help="ground-truth queries per texel of the model's finest level (their footprints are "
                        "sampled for the material's own resolution)")
    p.add_argument("--queries", type=int, help="ground-truth queries (default: --queries-per-texel per texel of "
                   "the finest level); models of other resolutions can so share one data set")
    p.add_argument("--spp", type=int, default=GenerateSettings.spp, help="path samples per ground-truth query")
    p.add_argument("--coarse-spp", type=int, default=GenerateSettings.coarse_spp,
                   help="path samples per ground-truth query of the footprints where --coarse-loss applies (0: --spp)")
    p.add_argument("--recipe", choices=("auto",) + tuple(RECIPES), default="auto",
                   help="what the model is made of where no flag says otherwise (training/loop/config.py RECIPES): auto "
                        "makes the shipped map-informed model (maps) of a material with principled maps, the paper's "
                        "(paper) of one without; a flag given wins over the recipe's value")
    p.add_argument("--maps", action="store_true", help="map-informed model: its textures are encoded from the "
                   "material's prefiltered maps (training/TRAINING.md); the export is the paper's graph")
    p.add_argument("--base", nargs="?", const="on", choices=("on", "auto", "off"),
                   help=commands.BASE_HELP + "; --base auto trains the model without and with it and keeps the base only "
                   "where it lowers the (log-space) error on a low-noise reference set by 10 %% (fit.BASE_MARGIN; "
                   "twice the training time)")
    p.add_argument("--seeds", type=int, default=1, help="train the model from this many initial weights and keep the "
                   "one with the lowest error on a low-noise reference set (FitSettings.seeds; this many times the "
                   "training time; default 1)")
    p.add_argument("--description", default="", help="short description stored in the model metadata "
                   "(default: the material's summary, resolution and preset)")
    p.add_argument("--views-material", metavar="NAME_OR_TOML",
                   help="material whose ground truth the progress grid shows (default: the fitted one)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: one per core)")
    p.add_argument("--compare", type=Path, default=SHIPPED_MODELS, metavar="MODELS",
                   help="folder of model records (NAME.json) the verdict line places the model among (default: "
                   "the shipped models' folder of this checkout, when there is one)")
    commands.add_material_flags(p)
    commands.add_map_flags(p)
    p.set_defaults(func=_fit)


class StageBar:
    """The progress of a whole fit: a bar for each stage that counts something (queries traced, steps trained),
    left at its end when the stage is done, and one line for each stage that does not. A bar never goes back."""

    UNITS = {"ground truth": ("query", True), "training": ("step", False)}
    """Unit and unit scaling of the stages that count something."""

    def __init__(self, name: str, batch: int) -> None:
        self.name, self.batch = name, batch
        self.bar = None  # the current stage's bar, if it counts
        self.stage = None

    def report(self, stage: str, done: int, total: int | None) -> None:
        from tqdm import tqdm

        from neumip.training.loop.fit import STAGES

        if stage != self.stage:
            self.stage = stage
            self.close()
            desc = f"{self.name} [{STAGES.index(stage) + 1}/{len(STAGES)}] {stage}"
            if stage not in self.UNITS:
                tqdm.write(desc)
                return
            unit, scale = self.UNITS[stage]
            self.bar = tqdm(total=total, unit=unit, unit_scale=scale, desc=desc, dynamic_ncols=True)
        bar = self.bar
        if bar is None:
            return
        if total is not None and bar.total != total:  # a stage that grows (the reference set after the data)
            bar.total = total
        bar.update(done - bar.n)
        if stage == "training" and done % 10 == 0 and bar.format_dict["rate"]:
            bar.set_postfix(queries_per_s=f"{bar.format_dict['rate'] * self.batch / 1e6:.2f}M")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _fit(args: argparse.Namespace) -> int:
    from neumip.training.loop.paths import occupied

    output = commands.output_path(args, occupied(args.output))
    commands.import_torch(args.threads)  # first: its OpenMP threads read OMP_WAIT_POLICY once, at import
    from neumip.core.errors import CommandError
    from neumip.client.mitsuba.runtime import MitsubaUnavailable

    from neumip.training.loop.checkpoint import CheckpointError
    from neumip.groundtruth.dataset import DatasetError
    from neumip.training.loop.fit import FitSettings, fit
    from neumip.groundtruth.description import DescriptionError, find_description, resolve
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.sampling import QuerySampling
    from neumip.training.loop.paths import progress_path, work_folder
    from neumip.training.loop.train import TrainingDiverged, TrainingError
    from tqdm import tqdm

    work = work_folder(output, args.work)
    try:
        desc = find_description(args.material)
        config = commands.train_settings(args)
        recipe = args.recipe if args.recipe != "auto" else "maps" if resolve(desc).bsdf is None else "paper"
        commands.apply_recipe(args, RECIPES[recipe], maps_on=True, base_on="on")
        resolution = args.resolution or desc.resolution
        material = commands.material_config(args, resolution, resolve(desc) if args.base or args.relief else None)
        generate = GenerateSettings(spp=args.spp, sampling=QuerySampling(queries_per_texel=args.queries_per_texel,
                                                                         sub_texel_levels=material.lod_bias),
                                    queries=args.queries, coarse_spp=args.coarse_spp)
        maps = commands.map_config(args, args.maps)
    except (DescriptionError, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    kind = ("neural offset" if material.offset else "no neural offset") + (", map-informed" if args.maps else "") \
        + (", half vector" if material.half_vector else "") + (", classical base" if args.base == "on" else "") \
        + ((", local frame with the base" if args.base == "auto" else ", local frame") if material.local_frame else "") \
        + (f", terminator softening {material.terminator}" if args.base and material.terminator != "all" else "") \
        + (", visibility input" if material.visibility_input else "") \
        + (f", relief ({material.relief_steps} steps)" if material.relief else "") \
        + (", classical base if it lowers the held-out error" if args.base == "auto" else "") \
        + (f", best of {args.seeds} initial weights" if args.seeds > 1 else "")
    description = args.description or f"{desc.name}: {desc.summary or 'fitted'}, {resolution}^2, {kind}, " \
                                      f"{args.preset} preset"
    settings = FitSettings(material, config, generate, work, args.data, description, args.views_material,
                           maps, choose_base=args.base == "auto", seeds=args.seeds)
    bar = StageBar(desc.name, config.batch)
    try:
        table, paths = fit(desc, output, settings, bar.report,
                           lambda trainer: tqdm.write(commands.progress_line(trainer, progress_path(output))))
    except (DescriptionError, DatasetError, CheckpointError, TrainingDiverged, TrainingError,
            MitsubaUnavailable, ValueError) as exc:
        raise CommandError(str(exc)) from exc
    except KeyboardInterrupt:
        bar.close()
        print(f"interrupted: re-run the same command to resume (work folder {work})")
        raise
    finally:
        bar.close()
    commands.print_finished(table, paths, f"work folder {work}")
    from neumip.training.loop.verdict import shipped_ratios, verdict_line

    print(verdict_line(table["noise"], shipped_ratios(args.compare)))
    return 0
