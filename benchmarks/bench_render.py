"""Benchmark: what a neural material costs to render, against the geometry it replaces.

Section ``ratios`` (default) renders one view - a plane seen at 55 degrees from its normal, lit by a
directional light and a dim constant environment - seven ways in one process, in interleaved rounds,
and prints the median seconds of each and two ratios for each in-process engine (the material in the
render's own kernels, `KernelMaterials`, the default; and its ONNX graph in ONNX Runtime,
`LocalMaterials`, buffered per bounce):

- **neural / reference**: `neumip_path` with the material on a flat rectangle, against Mitsuba's stock
  `path` on the material's real displaced microgeometry (`training.microgeometry.mesh.reference_surface`,
  at its description's resolution: the geometry `neumip generate` traced the model's data on and the
  report renders as R, whatever the model's own resolution) filling the same rectangle. Target: <= 1.0.
  ``--geometry-resolution R`` traces the height field resampled to R^2 instead (a coarser, cheaper mesh:
  64 gives the 64^2 mesh of `results/render.txt`'s figures before 2026-11-26).
- **one emitter chosen**: the same neural render with `all_emitters` off (next-event estimation towards
  one emitter chosen per shading point, as the stock `path`): what sampling every emitter costs.
- **overhead / diffuse**: `neumip_path` with a material that answers a constant at no cost (so
  everything but evaluation: the wavefront loop, the lanes' compaction, the query buffers or gathers,
  the scatter of the answers), against stock `path` with a `diffuse` BSDF on the same plane. Target:
  <= 1.5. Also with one emitter chosen: the stock `path`'s one shadow ray per shading point, so the ratio is the
  integrator's own cost without the shadow ray per emitter that `all_emitters` adds.

``--floor`` also prints the in-kernel render as it would be if its evaluation ran at this machine's peak rate of
vector instructions (`kernel_ops.py`'s kernel of fmas): an estimate of what the engine's code could give.

``--server`` adds the neural plane rendered through a real `neumip serve` process on loopback (the integrator's
buffered path, as a renderer talking to the service does: msgpack bodies, and shared memory, `SERVER_PROTOCOLS`)
of the server's default engine (``auto``: the kernel engine where it runs) or the one named, and its ratio to the
geometry; its CPU seconds count the server process's too. ``--server-url URL`` renders through a server already
running instead (a container), msgpack, its CPU not counted.

Both integrators run at the same spp, ``max_depth`` and ``rr_depth``. Section ``stages`` renders the same
neural plane with the model as is and without each of its stages (the relief, half its steps, the neural
offset, the local frame, the classical base, the energy table's azimuth axis (its cells averaged over the azimuths), the
energy table: the same weights, the graph of the config without the stage), and with the same
material from the ``--compare`` folders (another export of it), interleaved with the reference geometry, each
round in another order: what each stage costs, as a share of the geometry's time. Section ``demo`` renders the
demo scene in-process (both engines; in the kernels also with one emitter chosen) and through a real `neumip serve` process and prints the HTTP /
in-process ratio; the renders use the same seed, so their largest image difference is printed too. CPU
seconds (this process, plus the server process for HTTP) are printed beside wall time: on a shared
machine they are the steadier figure. A warm-up render first compiles the kernels (for the demo, one
whole in-process render: a smaller one left kernels to compile inside the timed in-process render).

    .venv/bin/python benchmarks/bench_render.py                         # ratios, rock from models/
    .venv/bin/python benchmarks/bench_render.py --sections ratios,demo  # and the demo in-process vs HTTP
    .venv/bin/python benchmarks/bench_render.py --server                # and through a server's default engine
    .venv/bin/python benchmarks/bench_render.py --sections demo --stand-in   # untrained stand-ins
    .venv/bin/python benchmarks/bench_render.py --sections stages --compare /tmp/before   # stage costs
    .venv/bin/python benchmarks/bench_render.py --sections kernels   # the overhead renders' kernels
    .venv/bin/python benchmarks/bench_render.py --kernel-before /tmp/kernel_before.py  # and another checkout's kernel

``--stand-in`` builds constant-colour materials of the default architecture (256^2 pyramid,
neural offset) into a temporary folder for the demo: evaluation costs what a trained material costs,
the picture does not look like one.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from neumip.core import contract as C

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "demo.xml"
DEMO_MATERIALS = {"yarn": (0.55, 0.2, 0.12), "rock": (0.4, 0.37, 0.33), "turtle": (0.2, 0.45, 0.2),
                  "foam": (0.8, 0.8, 0.72)}
"""Stand-ins under the names of the demo scene's defaults (the map-informed models)."""
ZENITH_DEG = 55.0
"""Angle between the plane's normal and the view direction of the ratios section."""


def load_avg() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {os.cpu_count()} cores"


# --- ratios: neural plane vs displaced reference geometry, overhead vs diffuse ------------------------


class ConstantKernel:
    """The in-kernel counterpart of `ConstantEvaluator`: a `KernelMaterials` whose material answers one
    colour with no arithmetic (what is left is the in-kernel path's own cost: the lanes' compaction,
    gathers and scatters)."""

    def __init__(self, material: str, rgb: float = 0.1) -> None:
        self.material, self.rgb = material, rgb

    def materials(self) -> list[str]:
        return [self.material]

    def kernel(self, material: str) -> "ConstantKernel":
        return self

    def answers(self, columns: list) -> list:
        from neumip.client.mitsuba.render import dr, mi

        return [[dr.full(mi.Float, self.rgb, dr.width(columns[0]))] * C.RGB_DIM
                for _ in range(C.group_lights(len(columns)))]


class ConstantEvaluator:
    """An evaluator that answers every query with one colour, at no cost (a view of a buffer filled
    once per query width): what is left of a `neumip_path` render with it is the integrator's own
    overhead."""

    def __init__(self, material: str, rgb: float = 0.1) -> None:
        self.material, self.rgb = material, rgb
        self.answers: dict[int, np.ndarray] = {}
        """Answer columns (3 K for groups of K lights) -> a buffer of that width."""

    def materials(self) -> list[str]:
        return [self.material]

    def evaluate(self, material: str, queries: np.ndarray) -> np.ndarray:
        width = 3 * C.group_lights(queries.shape[1])
        answers = self.answers.get(width)
        if answers is None or len(answers) < len(queries):
            answers = self.answers[width] = np.full((2 * len(queries), width), self.rgb, dtype=np.float32)
        return answers[: len(queries)]


def view(mi, surface, integrator: dict, size: int, spp: int) -> dict:
    """The ratios section's scene around one surface (a rectangle of half-width 2 at the origin)."""
    zenith = math.radians(ZENITH_DEG)
    origin = [0.0, -3.0 * math.sin(zenith), 3.0 * math.cos(zenith)]
    return {
        "type": "scene",
        "integrator": integrator,
        "sensor": {
            "type": "perspective",
            "fov": 30,
            "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=[0, 0, 0], up=[0, 0, 1]),
            "film": {"type": "hdrfilm", "width": size, "height": size},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "sun": {"type": "directional", "direction": [-0.6, 0.3, -0.5], "irradiance": 3.0},
        "sky": {"type": "constant", "radiance": 0.1},
        "surface": surface,
    }


def material_name(args) -> str:
    """The model's name: ``--material`` itself, or the stem of a description file (``x/stones.toml``)."""
    return Path(args.material).stem


def geometry_resolution(args) -> int:
    """Height samples per tile side of the reference geometry: ``--geometry-resolution``, else the description's."""
    from neumip.groundtruth.description import find_description

    return args.geometry_resolution or find_description(args.material).resolution


SERVER_PROTOCOLS = ("msgpack", "shm")
"""How the renders through a server (``--server``) send their queries: msgpack bodies, and shared memory
(`neumip.client.shared_memory`; the server is started with it allowed)."""


def ratio_scenes(mi, args) -> dict:
    """name -> (scene, evaluator key or None) of the renders the ratios section times."""
    from neumip.groundtruth import mesh
    from neumip.groundtruth.description import find_description, resolve

    desc = find_description(args.material)
    desc.resolution = geometry_resolution(args)
    to_world = mi.ScalarTransform4f().scale([2.0, 2.0, 2.0])
    depth = {"max_depth": args.max_depth, "rr_depth": args.rr_depth}
    neural_bsdf = {"type": "neumip", "material": material_name(args), "uv_scale": float(args.tiles)}

    def plane(bsdf: dict) -> dict:
        return {"type": "rectangle", "to_world": to_world, "bsdf": bsdf}

    reference = mesh.reference_surface(mi, resolve(desc), args.tiles, to_world)
    neural = view(mi, plane(neural_bsdf), {"type": "neumip_path", **depth}, args.size, args.spp)
    one_emitter = view(mi, plane(neural_bsdf), {"type": "neumip_path", "all_emitters": False, **depth}, args.size,
                       args.spp)
    before = {"neural, kernel before": (neural, "kernel before")} if args.kernel_before else {}
    served = {f"neural, server {p}": (neural, f"server {p}") for p in args.protocols}
    return {
        "reference (path)": (view(mi, reference, {"type": "path", **depth}, args.size, args.spp), None),
        "neural (neumip_path)": (neural, "kernel"),
        "neural, one emitter": (one_emitter, "kernel"),
        **before,
        "neural, ONNX Runtime": (neural, "local"),
        **served,
        "constant (neumip_path)": (neural, "constant kernel"),
        "constant, one emitter": (one_emitter, "constant kernel"),
        "constant, buffered": (neural, "constant"),
        "diffuse (path)": (view(mi, plane({"type": "diffuse"}), {"type": "path", **depth}, args.size,
                                args.spp), None),
    }


def time_render(mi, scene, evaluator, spp: int, seed: int, max_lanes: int,
                server_pid: int | None = None) -> tuple[float, float, float, int]:
    """(wall seconds, CPU seconds of this process (and of the server process ``server_pid``), seconds inside
    neural evaluation, the answers evaluated: a query group of K lights counting K) of one render."""
    from neumip.client.mitsuba.render import RenderConfig, render_scene

    def cpu_now() -> float:
        return time.process_time() + (process_cpu_seconds(server_pid) if server_pid else 0.0)

    start, cpu = time.perf_counter(), cpu_now()
    if evaluator is None:
        np.array(mi.render(scene, spp=spp, seed=seed))
        inside, answers = 0.0, 0
    else:
        stats = render_scene(scene, evaluator, RenderConfig(spp=spp, seed=seed, max_lanes=max_lanes)).stats
        inside, answers = stats.seconds, stats.queries
    return time.perf_counter() - start, cpu_now() - cpu, inside, answers


def ratios(args) -> None:
    from neumip.client.http import MaterialClient

    args.protocols = ("msgpack",) if args.server_url else SERVER_PROTOCOLS if args.server else ()
    if args.server_url:  # a server already running (a container): its CPU is not counted
        with MaterialClient(args.server_url, protocol="msgpack") as client:
            return ratios_with(args, ({"msgpack": client}, None))
    if not args.server:
        return ratios_with(args, None)
    from bench_server import Server  # this folder is on sys.path when run as a script

    with tempfile.TemporaryDirectory() as tmp:
        server = Server(Path(args.models), Path(tmp) / "server.log", engine=args.server, shared_memory=True)
        clients = {p: MaterialClient(server.url, protocol=p) for p in SERVER_PROTOCOLS}
        try:
            ratios_with(args, (clients, server.process.pid))
        finally:
            for client in clients.values():
                client.close()
            server.stop()


def ratios_with(args, served: tuple | None) -> None:
    """The ratios section; ``served``: ({protocol: a client of a `neumip serve` process}, its pid), rendered
    through each too."""
    from neumip.engines.local import LocalMaterials
    from neumip.engines.kernel import KernelMaterials, namespace_of
    from neumip.client.mitsuba.render import mi

    local = LocalMaterials(args.models)
    material = material_name(args)
    evaluators = {"kernel": KernelMaterials(args.models, namespace_of(mi.Float)), "local": local, "constant": ConstantEvaluator(material),
                  "constant kernel": ConstantKernel(material), None: None}
    server_pid = None
    if served is not None:
        clients, server_pid = served
        evaluators.update({f"server {p}": client for p, client in clients.items()})
    if args.kernel_before:  # another checkout's in-kernel engine, for before/after runs
        from kernel_before import Before  # this folder is on sys.path when run as a script

        evaluators["kernel before"] = Before(args.kernel_before, args.models, namespace_of(mi.Float))
    scenes = {name: (mi.load_dict(scene), evaluators[ev])
              for name, (scene, ev) in ratio_scenes(mi, args).items()}
    print(f"## ratios: {args.material} on a plane at {ZENITH_DEG:g} deg, {args.tiles} x {args.tiles} tiles, "
          f"{args.size}^2 px, {args.spp} spp, max_depth {args.max_depth}, rr_depth {args.rr_depth}, "
          f"geometry {geometry_resolution(args)}^2 per tile, model {local.get(material).config['resolution']}^2; "
          f"median of {args.rounds} interleaved rounds   [{load_avg()}]", flush=True)
    pids = {name: server_pid if name.startswith("neural, server") else None for name in scenes}  # whose CPU counts too
    for name, (scene, evaluator) in scenes.items():  # warm-up: compile (or load cached) kernels
        time_render(mi, scene, evaluator, args.spp, 0, args.max_lanes, pids[name])
    times = {name: [] for name in scenes}  # (wall, CPU) per round
    # the evaluation's seconds and answers of the every-emitter neural render of each evaluator (the one-emitter
    # render shares the kernel's evaluator but not its work)
    timed = {"kernel": "neural (neumip_path)", "local": "neural, ONNX Runtime", "kernel before": "neural, kernel before",
             **{f"server {p}": f"neural, server {p}" for p in args.protocols}}
    timed = {key: name for key, name in timed.items() if name in scenes}
    evaluation = {key: [] for key in timed}
    counts = {}  # answers a render evaluates (the same in every round but for the noise's paths)
    for r in range(args.rounds):
        for name, (scene, evaluator) in scenes.items():
            wall, cpu, inside, answers = time_render(mi, scene, evaluator, args.spp, r + 1, args.max_lanes, pids[name])
            times[name].append((wall, cpu))
            for key, timed_name in timed.items():
                if name == timed_name:
                    evaluation[key].append(inside)
                    counts[key] = answers
    wall = {name: statistics.median(t[0] for t in v) for name, v in times.items()}
    cpu = {name: statistics.median(t[1] for t in v) for name, v in times.items()}
    for name in scenes:
        print(f"  {name:<24} {wall[name]:7.3f} s wall   {cpu[name]:7.3f} CPU s")
    print("  (neural evaluation inside the neural renders, wall: "
          + ", ".join(f"{key} {statistics.median(values):.3f} s" for key, values in evaluation.items())
          + f"; {max(counts.values(), default=0) / 1e6:.2f} M answers a render)")
    which = f"{args.server_url}" if args.server_url else f"NEUMIP_ENGINE={args.server}"
    served_rows = [(f"through a server ({which}, {p}): neural / reference", f"neural, server {p}",
                    "reference (path)", 1.0) for p in args.protocols]
    before = [("kernel before: neural / reference", "neural, kernel before", "reference (path)", 1.0),
              ("in-kernel after / before", "neural (neumip_path)", "neural, kernel before", 1.05)] if args.kernel_before else []
    for label, a, b, target in (("neural / reference", "neural (neumip_path)", "reference (path)", 1.0),
                                ("one emitter chosen: neural / reference", "neural, one emitter", "reference (path)",
                                 1.0), *before,
                                ("overhead / diffuse", "constant (neumip_path)", "diffuse (path)", 1.5),
                                ("one emitter chosen: overhead / diffuse", "constant, one emitter", "diffuse (path)",
                                 1.5),
                                ("ONNX Runtime: neural / reference", "neural, ONNX Runtime", "reference (path)", 1.0),
                                ("ONNX Runtime: overhead / diffuse", "constant, buffered", "diffuse (path)", 1.5),
                                *served_rows):
        print(f"{label}: {wall[a] / wall[b]:.2f}x wall, {cpu[a] / cpu[b]:.2f}x CPU (target <= {target})")
    if args.floor and counts.get("kernel"):
        floor(args, wall, statistics.median(evaluation["kernel"]), counts["kernel"])
    print(f"[{load_avg()}]", flush=True)


def floor(args, wall: dict, evaluation: float, answers: int) -> None:
    """``--floor``: the in-kernel render if its evaluation ran at this machine's peak rate of vector instructions
    (`kernel_ops.py`: the kernel's instructions a lane for a group of three lights, an fma one; the peak from its
    kernel of interleaved fmas, measured now), against the geometry. An estimate, not a proof: the peak is of fmas
    alone (adds and compares may issue beside them), and the count is of this engine's LLVM IR for the model, not
    the least the model needs. The evaluation's time also holds the gathers and scatters around the kernel, so its
    share of the peak understates the model's own."""
    from kernel_ops import count, fma_rate, kernel_ir  # this folder is on sys.path when run as a script

    figures = count(kernel_ir(Path(args.models) / f"{material_name(args)}.onnx", 3)[1])
    instructions = figures["arithmetic"] - figures["fma"]  # an fma one instruction
    peak = fma_rate(4, 25, 4) / 2  # vector instructions a second, lanes counted (each of its fmas one)
    groups = answers / 3
    at_peak = groups * instructions / peak
    render = wall["neural (neumip_path)"] - evaluation + at_peak
    print(f"floor: {groups / 1e6:.2f} M groups of 3 lights, {instructions} instructions a lane a group "
          f"({figures['arithmetic']} operations, an fma two); the machine's peak {peak / 1e9:.0f} G lane-instructions "
          f"a second; the evaluation {groups * instructions / evaluation / 1e9:.0f} G a second, "
          f"{groups * instructions / evaluation / peak:.2f}x the peak: {evaluation:.3f} s, {at_peak:.3f} s at the "
          f"peak; the neural render at the peak {render:.3f} s, {render / wall['reference (path)']:.2f}x the "
          f"geometry's time (the rest of the render, {wall['neural (neumip_path)'] - evaluation:.3f} s, as measured)")


# --- stages: what each stage of the model costs in the render -------------------------------------------


def stage_variants(model_path: Path, folder: Path) -> dict[str, Path]:
    """Write the model at `model_path` as is and without each of its stages (the same weights, the graph of the
    config without the stage: its answers are wrong, its cost is the rest's) into subfolders of `folder`, one
    file of the material's name each; -> {label: subfolder}."""
    from dataclasses import replace

    import onnx

    from neumip.core import weights as W
    from neumip.training.export.graph import build_onnx, save_onnx
    from neumip.training.export.read import read_model

    config, weights, _, finest = read_model(onnx.load(str(model_path)))
    configs = {"as is": config}
    if config.relief:
        configs["no relief"] = replace(config, relief=0)
        if config.relief_steps > 1:
            configs[f"relief {config.relief_steps // 2} steps"] = replace(config, relief_steps=config.relief_steps // 2)
    if config.offset:
        configs["no neural offset"] = replace(config, offset=False)
    if config.local_frame:
        configs["no local frame"] = replace(config, local_frame=False)
    if config.visibility_input:
        configs["no visibility input"] = replace(config, visibility_input=False)
    if config.base:  # the decoder's additive outputs answer alone
        configs["no classical base"] = replace(config, base=0, local_frame=False, terminator="all", visibility_input=False)
    if config.energy_azimuths:  # the table's cells averaged over the azimuths
        configs["energy table without azimuths"] = replace(config, energy_azimuths=0)
    if config.energy_bins:
        configs["no energy table"] = replace(config, energy_bins=0, energy_azimuths=0, energy_luminance=False)
    out = {}
    columns, first = {}, config.channels  # each optional input's first-layer columns of the decoder
    for row in config.decoder_inputs():
        columns[row.name], first = range(first, first + row.width), first + row.width
    for label, cfg in configs.items():
        w = dict(weights)
        kept = {row.name for row in cfg.decoder_inputs()}
        drop = {i for name, cols in columns.items() if name not in kept for i in cols}  # the inputs it goes without
        if drop:
            keep = [i for i in range(weights[W.weight(W.DECODER, 0)].shape[1]) if i not in drop]
            w[W.weight(W.DECODER, 0)] = weights[W.weight(W.DECODER, 0)][:, keep]
        if cfg.energy_bins < config.energy_bins:
            del w[W.ENERGY]
        elif cfg.energy_azimuths < config.energy_azimuths:
            table = w[W.ENERGY]
            w[W.ENERGY] = table.reshape(-1, config.energy_azimuths, table.shape[1]).mean(1).astype(np.float32)
        if config.base and not cfg.base:
            last = config.layers - 1
            w[W.weight(W.DECODER, last)] = w[W.weight(W.DECODER, last)][3:]
            w[W.bias(W.DECODER, last)] = w[W.bias(W.DECODER, last)][3:]
        sub = folder / label.replace(" ", "_")
        sub.mkdir()
        save_onnx(build_onnx(cfg, w, finest_level=finest), sub / model_path.name)
        out[label] = sub
    return out


def stages(args) -> None:
    """The neural plane of the ratios section rendered with the model as is, without each of its stages, and with
    the same material from the ``--compare`` folders, in interleaved rounds with the reference geometry."""
    from neumip.engines.kernel import KernelMaterials, namespace_of
    from neumip.client.mitsuba.render import mi

    material = material_name(args)
    with tempfile.TemporaryDirectory() as tmp:
        folders = stage_variants(args.models / f"{material}.onnx", Path(tmp))
        folders.update({str(d): d for d in args.compare})
        scenes = ratio_scenes(mi, args)
        reference, neural = (mi.load_dict(scenes[name][0]) for name in ("reference (path)", "neural (neumip_path)"))
        runs = {"reference (path)": (reference, None),
                **{label: (neural, KernelMaterials(d, namespace_of(mi.Float))) for label, d in folders.items()}}
        print(f"## stages: {args.material} on a plane at {ZENITH_DEG:g} deg, {args.tiles} x {args.tiles} tiles, "
              f"{args.size}^2 px, {args.spp} spp, geometry {geometry_resolution(args)}^2 per tile; median of "
              f"{args.rounds} interleaved rounds   [{load_avg()}]",
              flush=True)
        for scene, evaluator in runs.values():  # warm-up: compile (or load cached) kernels
            time_render(mi, scene, evaluator, args.spp, 0, args.max_lanes)
        wall = {name: [] for name in runs}
        inside = {name: [] for name in runs}
        names = list(runs)
        for r in range(args.rounds):  # each round in another order: the render after the reference's runs slower
            for name in names[r % len(names):] + names[:r % len(names)]:
                scene, evaluator = runs[name]
                w, _, e, _ = time_render(mi, scene, evaluator, args.spp, r + 1, args.max_lanes)
                wall[name].append(w)
                inside[name].append(e)
    med = {name: statistics.median(v) for name, v in wall.items()}
    ref, whole = med["reference (path)"], med["as is"]
    print(f"  {'':<32} {'wall s':>8} {'/ reference':>12} {'evaluation s':>13} {'stage: / reference':>19}")
    for name in runs:
        stage = f"{(whole - med[name]) / ref:19.3f}" if name not in ("reference (path)", "as is") else ""
        print(f"  {name:<32} {med[name]:8.3f} {med[name] / ref:12.3f} {statistics.median(inside[name]):13.3f} {stage}")
    print(f"[{load_avg()}]", flush=True)


# --- demo: in-process vs HTTP -------------------------------------------------------------------------


def stand_in_models(folder: Path) -> Path:
    """Write constant-colour materials of the default architecture under the demo's names."""
    from neumip.core.config import MaterialConfig
    from neumip.training.export.graph import build_onnx, constant_weights, save_onnx

    cfg = MaterialConfig()
    for name, rgb in DEMO_MATERIALS.items():
        weights = constant_weights(cfg, [c / np.pi for c in rgb])
        save_onnx(build_onnx(cfg, weights, f"benchmark stand-in ({name})"), folder / f"{name}.onnx")
    return folder


def process_cpu_seconds(pid: int) -> float:
    """User + system CPU seconds a process has used so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def render_demo(evaluator, args, size: int, spp: int, server_pid: int | None = None, all_emitters: bool = True):
    """Render the demo; returns (result, CPU seconds of this process plus the server's). ``all_emitters``
    False: `neumip_path` chooses one emitter per shading point (`PathConfig.all_emitters`)."""
    from neumip.client.mitsuba.render import RenderConfig, load_scene, render_scene

    scene = load_scene(SCENE, resx=str(size), resy=str(size), spp=str(spp))
    scene.integrator().config.all_emitters = all_emitters
    cpu = time.process_time() + (process_cpu_seconds(server_pid) if server_pid else 0.0)
    result = render_scene(scene, evaluator, RenderConfig(spp=spp, seed=args.seed, max_lanes=args.max_lanes))
    cpu = time.process_time() + (process_cpu_seconds(server_pid) if server_pid else 0.0) - cpu
    return result, cpu


def report(label: str, result, cpu: float) -> None:
    s = result.stats
    print(
        f"{label:>11}: {result.seconds:6.1f} s total ({cpu:6.1f} CPU s) | {s.seconds:6.1f} s neural evaluation "
        f"({100 * s.seconds / result.seconds:4.1f} %) | {s.queries:>12,} queries in {s.calls} calls | "
        f"{result.passes} passes | {s.queries / max(s.seconds, 1e-9) / 1e6:.2f} M queries/s evaluated",
        flush=True,
    )


def demo(args) -> None:
    from neumip.client.http import MaterialClient
    from neumip.engines.local import LocalMaterials
    from neumip.engines.kernel import KernelMaterials, namespace_of
    from neumip.client.mitsuba.render import mi
    from bench_server import Server  # this folder is on sys.path when run as a script

    with tempfile.TemporaryDirectory() as tmp:
        models = stand_in_models(Path(tmp)) if args.stand_in else args.models
        local = LocalMaterials(models)
        print(f"## demo scene {SCENE.name}, {args.demo_size}^2, {args.demo_spp} spp; materials from {models}: "
              f"{', '.join(local.materials())}   [{load_avg()}]", flush=True)
        kernel = KernelMaterials(models, namespace_of(mi.Float))
        render_demo(kernel, args, args.demo_size, args.demo_spp)  # warm-up: compiles every kernel
        in_kernel, cpu_kernel = render_demo(kernel, args, args.demo_size, args.demo_spp)
        report("in-kernel", in_kernel, cpu_kernel)
        render_demo(kernel, args, args.demo_size, args.demo_spp, all_emitters=False)
        one, cpu_one = render_demo(kernel, args, args.demo_size, args.demo_spp, all_emitters=False)
        report("one emitter", one, cpu_one)
        print(f"in-kernel, every emitter / one emitter chosen: {in_kernel.seconds / one.seconds:.2f}x wall time, "
              f"{cpu_kernel / cpu_one:.2f}x CPU time", flush=True)
        render_demo(local, args, args.demo_size, args.demo_spp)
        in_process, cpu_local = render_demo(local, args, args.demo_size, args.demo_spp)
        report("in-process", in_process, cpu_local)
        diff = np.abs(in_kernel.image - in_process.image)
        print(f"in-kernel / in-process ONNX Runtime: {in_kernel.seconds / in_process.seconds:.2f}x wall time, "
              f"{cpu_kernel / cpu_local:.2f}x CPU time; image difference max {diff.max():.2e}, "
              f"mean {diff.mean():.2e}", flush=True)
        server = Server(Path(models), Path(tmp) / "server.log")
        try:
            for protocol in ("msgpack", "v2"):
                with MaterialClient(server.url, protocol=protocol) as client:
                    render_demo(client, args, 64, 2)
                    remote, cpu_remote = render_demo(client, args, args.demo_size, args.demo_spp,
                                                     server.process.pid)
                report(f"HTTP {protocol}", remote, cpu_remote)
                diff = np.abs(remote.image - in_process.image)
                print(f"HTTP {protocol} / in-process ONNX Runtime: {remote.seconds / in_process.seconds:.2f}x wall time, "
                      f"{cpu_remote / cpu_local:.2f}x CPU time (client + server); "
                      f"image difference max {diff.max():.2e}, mean {diff.mean():.2e}", flush=True)
        finally:
            server.stop()


def set_variant(variant: str | None) -> None:
    """Select a Mitsuba variant before the renderer is imported (it keeps a JIT variant already set)."""
    if variant:
        import mitsuba

        mitsuba.set_variant(variant)
        print(f"# Mitsuba variant {variant}")


def kernels(args) -> None:
    """Section ``kernels``: where the overhead renders spend their time, from drjit's kernel history - the constant
    material in `neumip_path` with one emitter chosen, and stock `path` with `diffuse` - one render each after a
    warm-up: the kernels' count, lanes and execution time, the heaviest five with their operation counts."""
    import drjit as dr

    from neumip.client.mitsuba.render import mi

    material = material_name(args)
    scenes = ratio_scenes(mi, args)
    picked = {"constant, one emitter": ConstantKernel(material), "diffuse (path)": None}
    print(f"## kernels: {args.material}, {args.size}^2 px, {args.spp} spp, max_depth {args.max_depth}; drjit's kernel "
          f"history of one render   [{load_avg()}]", flush=True)
    for name, evaluator in picked.items():
        scene = mi.load_dict(scenes[name][0])
        time_render(mi, scene, evaluator, args.spp, 0, args.max_lanes)  # compile (or load cached) kernels
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()  # cleared
        wall = time_render(mi, scene, evaluator, args.spp, 1, args.max_lanes)[0]
        history = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        total = sum(h["execution_time"] for h in history) / 1e3
        print(f"  {name}: {wall:.3f} s wall, {len(history)} kernels running {total:.3f} s, "
              f"{sum(h['size'] for h in history) / 1e6:.1f} M lanes in all")
        for h in sorted(history, key=lambda h: -h["execution_time"])[:5]:
            print(f"    {h['execution_time'] / 1e3:7.3f} s  {h['size']:>9,} lanes  {h['operation_count']:>6,} ops  "
                  f"{h['input_count']:>3} in / {h['output_count']:>3} out")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sections", default="ratios", help="comma-separated: ratios, stages, demo, kernels")
    parser.add_argument("--models", type=Path, default=ROOT / "models", help="model folder")
    parser.add_argument("--material", default="rock",
                        help="ratios: a shipped material, or a description file NAME.toml with NAME.onnx in --models")
    parser.add_argument("--tiles", type=int, default=8, help="ratios: material tiles across the plane")
    parser.add_argument("--size", type=int, default=256, help="ratios: image width and height")
    parser.add_argument("--spp", type=int, default=64, help="ratios: samples per pixel")
    parser.add_argument("--max-depth", type=int, default=6, help="ratios: longest path (both integrators)")
    parser.add_argument("--geometry-resolution", type=int, metavar="R",
                        help="ratios, stages: trace the reference geometry's height field at R^2 per tile "
                        "(default: the description's, the material's real geometry)")
    parser.add_argument("--rr-depth", type=int, default=4, help="ratios: Russian roulette depth (both)")
    parser.add_argument("--rounds", type=int, default=5, help="ratios: interleaved rounds")
    parser.add_argument("--stand-in", action="store_true", help="demo: use untrained stand-in materials")
    parser.add_argument("--demo-size", type=int, default=512, help="demo: image width and height")
    parser.add_argument("--demo-spp", type=int, default=64, help="demo: samples per pixel")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-lanes", type=int, default=2**21,
                        help="lanes per render pass of neumip_path (stock path renders in one pass); on a GPU, "
                        "passes of 2^21 lanes leave it idle between them")
    parser.add_argument("--kernel-before", metavar="FILE", help="ratios: also render in-kernel with another checkout's "
                        "engines/kernel.py (git show 906263c:engines/kernel.py > FILE), interleaved")
    parser.add_argument("--compare", type=Path, nargs="*", default=[], metavar="DIR",
                        help="stages: also render the material's file in these folders (another export of it)")
    parser.add_argument("--floor", action="store_true",
                        help="ratios: also the in-kernel render if its evaluation ran at this machine's peak rate of "
                        "vector instructions (`kernel_ops.py`)")
    parser.add_argument("--server", nargs="?", const="auto", metavar="ENGINE",
                        help="ratios: also render through a real `neumip serve` of this engine (default: auto, the "
                        "server's default: the kernel engine where it runs), msgpack and shared memory on loopback; CPU seconds count "
                        "the server process too")
    parser.add_argument("--server-url", metavar="URL",
                        help="the ratios: also render through a server already running at URL (a container: "
                        "`docker compose up`), msgpack; its CPU is not counted")
    parser.add_argument("--variant", help="Mitsuba variant of every render (default: the renderer's, llvm_ad_rgb; "
                        "cuda_ad_rgb on an NVIDIA GPU)")
    args = parser.parse_args()
    set_variant(args.variant)

    sections = args.sections.split(",")
    if "ratios" in sections:
        ratios(args)
    if "stages" in sections:
        stages(args)
    if "demo" in sections:
        demo(args)
    if "kernels" in sections:
        kernels(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
