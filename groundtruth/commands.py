"""Ground-truth subcommands: `generate` (path-traced MBTF queries) and `import-queries` (external data).

Mitsuba, the tracer and tqdm are imported inside the command functions.
"""

from __future__ import annotations

import argparse
import sys

from neumip.core.cluster import add_ray_arguments, ray_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "generate",
        help="path-trace an MBTF training set for a material (shipped name or .toml description)",
        description="Path-trace MBTF queries through tiled microgeometry (Mitsuba 3) into a data set "
        "folder. Interrupted runs resume when the same command is run again; on a complete data set "
        "made with the same settings it does nothing.",
    )
    from neumip.groundtruth.generate import GenerateSettings  # the defaults shown are the settings' own
    from neumip.groundtruth.sampling import DIRECTIONS, QuerySampling
    from neumip.groundtruth.tracer import TracerConfig

    p.add_argument("material", nargs="?", help="shipped material name (see --list) or a .toml description")
    p.add_argument("-o", "--output", help="data set folder to write (or resume)")
    p.add_argument("--queries", type=int, help="number of queries (default: --queries-per-texel per finest texel)")
    p.add_argument("--queries-per-texel", type=float, default=QuerySampling.queries_per_texel,
                   help="queries per finest texel (the paper used 200-400)")
    p.add_argument("--spp", type=int, default=GenerateSettings.spp, help="path samples per query")
    p.add_argument("--coarse-spp", type=int, default=GenerateSettings.coarse_spp,
                   help="path samples per query of footprints from --coarse-texels finest texels (0: --spp)")
    p.add_argument("--coarse-texels", type=float, default=GenerateSettings.coarse_texels,
                   help="footprint (finest texels) from which --coarse-spp applies")
    p.add_argument("--seed", type=int, default=GenerateSettings.seed,
                   help="data set seed (same seed, same data)")
    p.add_argument("--max-depth", type=int, default=TracerConfig.max_depth,
                   help="surface interactions per path")
    p.add_argument("--max-zenith", type=float, help="largest zenith angle of wi, wo in degrees "
                   f"(default: {QuerySampling.max_zenith_deg:.2f}, the authors' r = sqrt(0.99 U))")
    p.add_argument("--directions", choices=DIRECTIONS, default=QuerySampling.directions,
                   help="distribution of wi, wo: uniform on the projected disk (the authors') or in solid angle "
                   "(4x the grazing queries)")
    p.add_argument("--level-fraction", type=float, default=QuerySampling.level_fraction,
                   help="share of sigma log-uniform over levels")
    p.add_argument("--heavy-fraction", type=float, default=QuerySampling.heavy_fraction,
                   help="share of sigma = texel / sqrt(U); the rest is sigma = 0")
    p.add_argument("--resolution", type=int, help="finest texels per tile side for sigma (default: the material's)")
    p.add_argument("--levels-resolution", type=int, help="the log-uniform share of sigma spans the levels of a "
                   "pyramid this fine (a model coarser than --resolution; default: --resolution's)")
    p.add_argument("--sub-texel-levels", type=int, default=QuerySampling.sub_texel_levels, metavar="K",
                   help="footprints down to 2^-K texel (for a model trained with --lod-bias K; QuerySampling.sub_texel_levels)")
    p.add_argument("--chunk", type=int, default=GenerateSettings.chunk,
                   help="queries per chunk, the unit of resumption")
    p.add_argument("--lanes", type=int, default=TracerConfig.lanes,
                   help="samples per wavefront pass (memory ~0.3 GB/M)")
    p.add_argument("--variant", default=TracerConfig.variant, help="Mitsuba variant (cuda_ad_rgb on a GPU)")
    p.add_argument("--list", action="store_true", help="list the shipped materials and exit")
    add_ray_arguments(p, "chunk")
    p.set_defaults(func=_generate)

    p = sub.add_parser(
        "import-queries",
        help="turn external MBTF queries (e.g. converted measured BTFs) into a data set",
        description="Write a data set from (N, 7) float queries in the contract's layout "
        "(u, v, sigma, wi_x, wi_y, wo_x, wo_y) and their (N, 3) RGB values, given as two .npy files "
        "or one .npz with arrays 'queries' and 'rgb'.",
    )
    p.add_argument("inputs", nargs="+", help="QUERIES.npy RGB.npy, or DATA.npz")
    p.add_argument("-o", "--output", required=True, help="data set folder to write")
    p.add_argument("--name", required=True, help="material name stored in the metadata")
    p.add_argument("--source", default="", help="where the data come from (stored in the metadata)")
    p.set_defaults(func=_import_queries)


def _generate(args: argparse.Namespace) -> int:
    from neumip.core.errors import CommandError
    from neumip.client.mitsuba.runtime import MitsubaUnavailable
    from neumip.core.cluster import ClusterError
    from neumip.groundtruth.dataset import DatasetError

    from neumip.groundtruth.description import DescriptionError, find_description, library_names

    if args.list:
        for name in library_names():
            print(f"{name:10s} {find_description(name).summary}")
        return 0
    if not args.material or not args.output:
        hint = f" (--ray took {args.ray!r} as its address: write --ray=ADDRESS or put --ray last)" if args.ray else ""
        raise CommandError(f"give a MATERIAL and -o DATA (or --list){hint}")
    try:
        desc = find_description(args.material)
        settings = _settings(args)
        return _run_generate(desc, args.output, settings, ray_config(args))
    except (DescriptionError, DatasetError, MitsubaUnavailable, ClusterError, ValueError) as exc:
        raise CommandError(str(exc)) from None


def _settings(args: argparse.Namespace):
    from neumip.groundtruth.generate import GenerateSettings
    from neumip.groundtruth.sampling import QuerySampling
    from neumip.groundtruth.tracer import TracerConfig

    sampling = QuerySampling(
        queries_per_texel=args.queries_per_texel,
        level_fraction=args.level_fraction,
        heavy_fraction=args.heavy_fraction,
        directions=args.directions,
        levels_resolution=args.levels_resolution,
        sub_texel_levels=args.sub_texel_levels,
        **({} if args.max_zenith is None else {"max_zenith_deg": args.max_zenith}),
    )
    return GenerateSettings(
        queries=args.queries, spp=args.spp, coarse_spp=args.coarse_spp, coarse_texels=args.coarse_texels,
        seed=args.seed, chunk=args.chunk, resolution=args.resolution,
        sampling=sampling, tracer=TracerConfig(max_depth=args.max_depth, lanes=args.lanes, variant=args.variant),
    )


def _run_generate(desc, output: str, settings, ray=None) -> int:
    from tqdm import tqdm

    from neumip.groundtruth.generate import generate

    bars = []

    def on_chunk(done: int, total: int) -> None:
        if not bars:  # created at the first report so a resumed run starts part-way
            bars.append(tqdm(total=total, initial=done, unit="query", unit_scale=True,
                             dynamic_ncols=True, desc=desc.name, file=sys.stderr))
        else:
            bars[0].update(done - bars[0].n)

    try:
        data = generate(desc, output, settings, on_chunk, ray)
    finally:
        for bar in bars:
            bar.close()
    print(f"{data.path}: {len(data)} queries of {desc.name} ({settings.spp} spp), complete")
    return 0


def _import_queries(args: argparse.Namespace) -> int:
    import numpy as np

    from neumip.core.errors import CommandError
    from neumip.groundtruth.dataset import DatasetError, write_dataset

    try:
        if len(args.inputs) == 1:
            with np.load(args.inputs[0], allow_pickle=False) as npz:
                queries, rgb = npz["queries"], npz["rgb"]
        elif len(args.inputs) == 2:
            queries, rgb = (np.load(path, allow_pickle=False) for path in args.inputs)
        else:
            raise CommandError("give QUERIES.npy RGB.npy, or one DATA.npz")
        meta = {
            "material": {"name": args.name, "summary": args.source},
            "generator": {"name": "external", "source": args.source, "inputs": list(args.inputs)},
        }
        data = write_dataset(args.output, queries, rgb, meta)
    except (KeyError, ValueError, DatasetError) as exc:
        raise CommandError(f"cannot import: {exc}") from None
    print(f"wrote {len(data)} external queries of {args.name} to {data.path}")
    return 0
