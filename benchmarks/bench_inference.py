"""In-process inference speed of an exported material: the shipped graph vs the first export and torch.

    .venv/bin/python benchmarks/bench_inference.py                 # everything (about 10 minutes)
    .venv/bin/python benchmarks/bench_inference.py --sections graphs --batches 10,14,20 --threads 1
    .venv/bin/python benchmarks/bench_inference.py --sections graphs --model before=/tmp/before.onnx

The material is 256^2 with the neural offset and random weights (speed does not depend on training);
queries are uniformly random (u, v, sigma over all levels, directions): the worst case for the texel
caches; one row of the graphs table reads coherent, renderer-like queries instead. Consecutive calls read different queries from a pool
of 2^20. Other jobs share this machine's cores, so every table interleaves its variants round by
round and reports the median of the rounds, twice: queries per wall-clock second, and queries per
CPU second of this process (what a query costs, whatever the other jobs take). Compare ratios within
one table, and read the load average printed with it. Sections:

- graphs:  the shipped graph (`neumip.training.export.graph`), the first export's graph (`export_modulo.py`,
           int64 Mod on single texels), `LocalMaterials.evaluate` and torch eager, one call per batch
           of 2^10 ... 2^20 queries; and `LocalMaterials.evaluate` on query groups of two lights (what
           the renderer sends: 2^(k-1) groups, counted as 2^k answers), random and coherent; the same
           groups through `KernelMaterials.evaluate` (the renderer's in-kernel engine: the ONNX graph
           compiled by drjit; numpy in and out, with the `kernel` extra); and each ``--model NAME=FILE``, a model of the same material
           written elsewhere (an older version of the export: in its checkout, ``python -c "from
           bench_inference import *; m = material(256, 0); open('/tmp/before.onnx', 'wb').write(
           build_onnx(m.config, weights_from_state(m.state_dict(), m.config)).SerializeToString())"``
           run in benchmarks/).
- kernel:  the in-kernel engine (`KernelMaterials.evaluate`: the shipped graph interpreted as drjit
           arithmetic, `engines/onnx_kernel.py`) against another checkout's (``--kernel-before FILE``,
           its ``engines/kernel.py``; `kernel_before.py`), single queries and groups of two lights,
           interleaved in one process, with the largest difference from torch.
- session: the shipped graph on 2 cores: ONNX Runtime's intra-op pool (spinning or not, arena,
           optimization level) against one-thread sessions running chunks on 2 threads.
- chunk:   `run_chunked` on 2^20 queries for several chunk sizes.
- load:    seconds to open a session: each graph, and the shipped one from a cached optimized model.
- ops:     one elementwise op on (N, 1) vs (N, 1) <op> (1, 1) shapes (ONNX Runtime's slow broadcast),
           and what a Gather costs per row (small and large tables).
- profile: where a query's time goes in the shipped graph: ONNX Runtime's per-node profile
           (`SessionOptions.enable_profiling`) of 2^20 random queries in calls of 2^14 rows on one
           thread, summed by op type and for the heaviest nodes.
- stages:  where a query's time goes, by taking stages away (the profiler's per-node times are
           inflated on a busy machine): the shipped graph, the same material's graph without the
           neural offset, and its two MLPs alone (same shapes, fed a fixed linear map of the
           queries); one thread, calls of 4096 rows, random and coherent queries, nanoseconds of
           CPU per query and the differences.
- quantized: the two MLPs alone as ONNX Runtime's quantization tools write them (int8 weights,
           uint8 activations: static QDQ and QOperator calibrated on 4 x 4096 random queries, and
           dynamic, MatMulInteger) against float32 (one query per row, and the export's column-major
           form): speed on one thread in calls of 4096 rows, and the largest error against float32
           relative to the largest answer.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import os
import statistics
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

# torch's OpenMP threads busy-wait between ops by default; on a machine shared with other jobs that
# made 2-thread torch eager ~50x slower. ONNX Runtime's pool threads do not spin here either.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import onnxruntime as ort  # noqa: E402
import torch  # noqa: E402

from neumip.core import contract as C  # noqa: E402
from neumip.core.contract import random_queries  # noqa: E402
from neumip.engines.local import LocalMaterials, run_call, run_chunked, split_chunk  # noqa: E402
from neumip.core.config import MaterialConfig  # noqa: E402
from neumip.training.export.graph import build_onnx, weights_from_state  # noqa: E402
from neumip.training.model.material import NeuMIPMaterial  # noqa: E402

from bench_render import set_variant  # noqa: E402  (benchmarks/, beside this script)
from export_modulo import modulo_onnx  # noqa: E402

SHIPPED = "shipped (quad tables)"
GRAPHS = {"modulo (first export)": modulo_onnx, SHIPPED: build_onnx}
"""Graphs the graphs and load sections compare (name -> builder(config, weights) -> ModelProto)."""


@dataclass
class Session:
    """What a session section varies: ONNX Runtime options for one session."""

    threads: int = 2
    """intra_op_num_threads (0: ONNX Runtime's default, one per physical core)."""
    spinning: bool = True
    """session.intra_op.allow_spinning: idle pool threads spin instead of sleeping."""
    arena: bool = True
    """enable_cpu_mem_arena."""
    level: str = "all"
    """Graph optimization level: basic, extended, all."""
    config: dict = field(default_factory=dict)
    """Extra session config entries."""

    def options(self) -> ort.SessionOptions:
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = self.threads
        opts.inter_op_num_threads = 1
        opts.enable_cpu_mem_arena = self.arena
        opts.graph_optimization_level = {
            "disabled": ort.GraphOptimizationLevel.ORT_DISABLE_ALL,
            "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
            "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED,
            "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL,
        }[self.level]
        opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if self.spinning else "0")
        for key, value in self.config.items():
            opts.add_session_config_entry(key, value)
        return opts


def open_session(model: bytes | str, session: Session) -> ort.InferenceSession:
    return ort.InferenceSession(model, session.options(), providers=["CPUExecutionProvider"])


def coherent_queries(n: int, resolution: int) -> np.ndarray:
    """(n, 7) queries in the order a renderer issues them: scanlines of an image of a plane tiled 8
    times across, one pixel a little over one finest texel wide (sigma = 1.3 texels), a fixed light
    and a view direction that turns slowly across the image."""
    side = int(np.ceil(np.sqrt(n)))
    y, x = np.divmod(np.arange(n), side)
    u, v = 8.0 * x / side, 8.0 * y / side
    sigma = np.full(n, 1.3 / resolution)
    wi = np.tile([0.3, -0.2], (n, 1))
    angle = np.pi * x / side
    wo = 0.5 * np.stack([np.cos(angle), np.sin(angle)], axis=1) * (y / side)[:, None]
    return C.pack_queries(u, v, sigma, wi, wo)


def throughput(fn, rows: int, seconds: float) -> tuple[float, float]:
    """`fn()` evaluates `rows` queries; repeated for at least `seconds` (one call at least).

    Returns (queries per wall-clock second, queries per CPU second of this process, all threads).
    The second figure is what a query costs in CPU, whatever other jobs take of the machine (but it
    also counts the time ONNX Runtime's pool threads spin while they wait).
    """
    fn()  # warm-up: first-call allocations
    calls, start, cpu = 0, time.perf_counter(), time.process_time()
    while True:
        fn()
        calls += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return calls * rows / elapsed, calls * rows / max(time.process_time() - cpu, 1e-9)


def interleaved(fns: dict, rows: int, seconds: float, rounds: int) -> dict[str, tuple[float, float]]:
    """Median (wall, CPU) queries/s of each of `fns` over `rounds` rounds, variants alternating."""
    results: dict[str, list[tuple[float, float]]] = {name: [] for name in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            results[name].append(throughput(fn, rows, seconds))
    return {
        name: (statistics.median(v[0] for v in values), statistics.median(v[1] for v in values))
        for name, values in results.items()
    }


def load_text() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {os.cpu_count()} cores"


def print_table(title: str, columns: list[str], rows: dict[str, list[tuple[float, float]]]) -> None:
    """Two tables of M queries/s, one row per variant: per wall-clock second, per CPU second."""
    name_width = max(len(n) for n in rows) + 2
    for i, unit in enumerate(("M queries / wall-clock s", "M queries / CPU s of this process")):
        print(f"\n## {title}: {unit}   [{load_text()}]")
        print("".ljust(name_width) + "".join(c.rjust(9) for c in columns))
        for name, values in rows.items():
            print(name.ljust(name_width) + "".join(f"{v[i] / 1e6:9.3f}" for v in values))


def material(resolution: int, seed: int) -> NeuMIPMaterial:
    """A random 256^2 material with a visible offset (the parity test's recipe)."""
    torch.manual_seed(seed)
    mat = NeuMIPMaterial(MaterialConfig(resolution=resolution), init_std=0.5).eval()
    with torch.no_grad():
        mat.offset_mlp[-1].bias.fill_(0.5)
    return mat


class Batches:
    """Consecutive batches of `rows` queries from a pool of 2^20, so that repeated calls do not
    re-read the texels the previous call left in cache."""

    def __init__(self, pool: np.ndarray, rows: int) -> None:
        self.slices = [pool[i : i + rows] for i in range(0, len(pool) - rows + 1, rows)]
        self.i = 0

    def next(self) -> np.ndarray:
        self.i = (self.i + 1) % len(self.slices)
        return self.slices[self.i]


def graphs_section(mat, models: dict[str, bytes], args) -> None:
    files = {name: Path(path).read_bytes() for name, path in args.model}
    sessions = {name: open_session(model, Session(threads=args.threads, spinning=False))
                for name, model in {**models, **files}.items()}
    check = random_queries(4096, seed=1)
    with torch.inference_mode():
        want = mat(torch.from_numpy(check)).numpy()
    print("\nmax |ONNX Runtime - torch| on 4096 random queries (parity contract: 1e-5 abs or 1e-4 rel):")
    for name, sess in sessions.items():
        got = sess.run(None, {C.ONNX_INPUT: check})[0]
        print(f"  {name:28s} {np.abs(got - want).max():.2e}")

    pool_rows = max(1 << 20, 2 << max(args.batches))  # two batches at least: calls read fresh rows
    pool = random_queries(pool_rows, seed=20)
    tpool = torch.from_numpy(pool)
    coherent = coherent_queries(pool_rows, args.resolution)
    shipped = sessions[SHIPPED]
    with tempfile.TemporaryDirectory() as folder:
        evaluated = {f"LocalMaterials.evaluate, {args.threads} workers": models[SHIPPED]}
        evaluated.update({f"{name}, LocalMaterials.evaluate": model for name, model in files.items()})
        for i, model in enumerate(evaluated.values()):
            (Path(folder) / f"m{i}.onnx").write_bytes(model)
        local = LocalMaterials(folder, threads=args.threads)
        grouped = f"LocalMaterials.evaluate, {args.threads} workers, groups of 2"
        grouped_coherent = f"{grouped}, coherent"
        kernel_names = ["drjit kernel (KernelMaterials.evaluate)", "drjit kernel (KernelMaterials.evaluate), groups of 2"]
        kernel = kernel_materials(folder, args.variant)
        if kernel:  # the in-kernel engine computes the shipped graph's model: same parity contract
            print(f"  {'drjit kernel (shipped)':28s} {np.abs(kernel.evaluate('m0', check) - want).max():.2e}")
        names = [*sessions, "shipped, coherent queries", *evaluated, grouped, grouped_coherent]
        names += kernel_names if kernel else []
        names += ["torch eager"]
        # query groups of two lights (what the renderer sends): the pool's rows plus another wi
        group_pool = np.ascontiguousarray(np.concatenate([pool[: len(pool) // 2], pool[len(pool) // 2:, 3:5]], 1))
        # and in a renderer's order: the coherent queries' first half, each with a second light
        coherent_groups = np.ascontiguousarray(
            np.concatenate([coherent[: len(pool) // 2], pool[len(pool) // 2:, 3:5]], 1))
        columns, table = [], {name: [] for name in names}
        for log2 in args.batches:
            q, tq = Batches(pool, 1 << log2), Batches(tpool, 1 << log2)
            cq = Batches(coherent, 1 << log2)
            fns = {name: (lambda s=s: s.run(None, {C.ONNX_INPUT: q.next()})) for name, s in sessions.items()}
            fns["shipped, coherent queries"] = lambda: shipped.run(None, {C.ONNX_INPUT: cq.next()})
            for i, name in enumerate(evaluated):
                fns[name] = lambda m=f"m{i}": local.evaluate(m, q.next())
            gq = Batches(group_pool, 1 << (log2 - 1))  # 2^log2 answers per call
            fns[grouped] = lambda: local.evaluate("m0", gq.next())
            cgq = Batches(coherent_groups, 1 << (log2 - 1))
            fns[grouped_coherent] = lambda: local.evaluate("m0", cgq.next())
            if kernel:
                kq, kgq = Batches(pool, 1 << log2), Batches(group_pool, 1 << (log2 - 1))
                fns[kernel_names[0]] = lambda: kernel.evaluate("m0", kq.next())
                fns[kernel_names[1]] = lambda: kernel.evaluate("m0", kgq.next())
            fns["torch eager"] = lambda: torch_eval(mat, tq.next())
            for name, value in interleaved(fns, 1 << log2, args.seconds, args.rounds).items():
                table[name].append(value)
            columns.append(f"2^{log2}")
        print_table(f"graphs, sessions of {args.threads} intra-op threads (no spinning), one run() "
                    "per batch", columns, table)


def kernel_materials(folder: str, variant: str | None = None):
    """The renderer's in-kernel evaluator over `folder` (the material's arithmetic compiled by drjit,
    numpy in and out), or None without the `kernel` extra."""
    try:
        from neumip.engines.kernel import KernelMaterials, namespace_of
    except ImportError:
        return None
    if variant:  # that Mitsuba variant's arrays (drjit.cuda.ad for cuda_ad_rgb)
        import mitsuba

        return KernelMaterials(folder, namespace_of(mitsuba.Float))
    return KernelMaterials(folder)


def kernel_section(mat, models: dict[str, bytes], args) -> None:
    """This checkout's in-kernel engine against ``--kernel-before`` (another checkout's), interleaved."""
    from kernel_before import Before  # this folder is on sys.path when run as a script

    check = random_queries(4096, seed=1)
    with torch.inference_mode():
        want = mat(torch.from_numpy(check)).numpy()
    pool = random_queries(max(1 << 20, 2 << max(args.batches)), seed=20)
    group_pool = np.ascontiguousarray(np.concatenate([pool[: len(pool) // 2], pool[len(pool) // 2:, 3:5]], 1))
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "m0.onnx").write_bytes(models[SHIPPED])
        engines = {"kernel (this checkout)": kernel_materials(folder, args.variant)}
        if args.kernel_before:
            backend = next(iter(engines.values())).backend
            engines[f"kernel ({Path(args.kernel_before).name})"] = Before(args.kernel_before, folder, backend)
        print("\nmax |in-kernel - torch| on 4096 random queries (parity contract: 1e-5 abs or 1e-4 rel):")
        for name, engine in engines.items():
            print(f"  {name:36s} {np.abs(engine.evaluate('m0', check) - want).max():.2e}")
        columns, table = [], {}
        for log2 in args.batches:
            fns = {}
            for name, engine in engines.items():
                q, gq = Batches(pool, 1 << log2), Batches(group_pool, 1 << (log2 - 1))
                fns[name] = lambda e=engine, q=q: e.evaluate("m0", q.next())
                fns[f"{name}, groups of 2"] = lambda e=engine, gq=gq: e.evaluate("m0", gq.next())
            for name, value in interleaved(fns, 1 << log2, args.seconds, args.rounds).items():
                table.setdefault(name, []).append(value)
            columns.append(f"2^{log2}")
        print_table("in-kernel engines, one evaluate() per batch", columns, table)


def torch_eval(mat, queries: torch.Tensor) -> torch.Tensor:
    with torch.inference_mode():
        return mat(queries)


def session_section(model: bytes, args) -> None:
    """Two cores used three ways: ONNX Runtime's intra-op pool (spinning or not), or one-thread
    sessions running chunks of the batch on a 2-thread pool (what `LocalMaterials` does)."""
    variants = {
        "2 intra-op threads, spinning": Session(threads=2),
        "2 intra-op threads, no spinning": Session(threads=2, spinning=False),
        "1 thread": Session(threads=1, spinning=False),
        "2 threads no spin, no arena": Session(threads=2, spinning=False, arena=False),
        "2 threads no spin, level extended": Session(threads=2, spinning=False, level="extended"),
        "2 threads no spin, level basic": Session(threads=2, spinning=False, level="basic"),
    }
    sessions = {name: open_session(model, s) for name, s in variants.items()}
    pool = ThreadPoolExecutor(2)
    single = functools.partial(run_call, sessions["1 thread"])
    columns, table = [], {name: [] for name in [*sessions, "1-thread session, 2 chunk workers"]}
    queries = random_queries(1 << 20, seed=20)
    for log2 in args.session_batches:
        q = Batches(queries, 1 << log2)
        fns = {name: (lambda s=s: s.run(None, {C.ONNX_INPUT: q.next()})) for name, s in sessions.items()}
        chunk = split_chunk(1 << log2, 2)
        fns["1-thread session, 2 chunk workers"] = lambda: run_chunked(single, q.next(), chunk, pool)
        for name, value in interleaved(fns, 1 << log2, args.seconds, args.rounds).items():
            table[name].append(value)
        columns.append(f"2^{log2}")
    pool.shutdown()
    print_table("session options, shipped graph, one batch", columns, table)


def chunk_section(model: bytes, args) -> None:
    """2^20 queries through `run_chunked`: one-thread session with 2 chunk workers, and one
    thread alone, for several chunk sizes."""
    session = open_session(model, Session(threads=1, spinning=False))
    single = functools.partial(run_call, session)
    pool = ThreadPoolExecutor(2)
    q = random_queries(1 << 20, seed=20)
    fns = {}
    for k in args.chunks:
        fns[f"chunk 2^{k}, 2 workers"] = lambda c=1 << k: run_chunked(single, q, c, pool)
        fns[f"chunk 2^{k}, 1 thread"] = lambda c=1 << k: run_chunked(single, q, c)
    fns["one run() of 2^20, 1 thread"] = lambda: session.run(None, {C.ONNX_INPUT: q})
    result = interleaved(fns, len(q), args.seconds, args.rounds)
    pool.shutdown()
    print_table("run_chunked on 2^20 queries, shipped graph", ["2^20"], {n: [v] for n, v in result.items()})


def load_section(models: dict[str, bytes], args) -> None:
    print(f"\n## seconds to open a session (median of {args.rounds})   [{load_text()}]")
    with tempfile.TemporaryDirectory() as folder:
        cached = Path(folder) / "shipped.optimized.onnx"
        opts = Session(threads=args.threads).options()
        opts.optimized_model_filepath = str(cached)
        ort.InferenceSession(models[SHIPPED], opts, providers=["CPUExecutionProvider"])
        sources = dict(models)
        sources["shipped, cached optimized model"] = str(cached)
        for name, source in sources.items():
            level = "disabled" if name.endswith("cached optimized model") else "all"
            times = []
            for _ in range(args.rounds):
                start = time.perf_counter()
                open_session(source, Session(threads=args.threads, level=level))
                times.append(time.perf_counter() - start)
            size = len(source) if isinstance(source, bytes) else cached.stat().st_size
            print(f"  {name:34s} {statistics.median(times):6.3f} s   file {size / 1e6:5.1f} MB")


def ops_section(args) -> None:
    """Why the export writes scalars as (1, 1): one Mul of a (2^14, k) tensor by a constant, per
    shape pair, 1 thread, optimizations off (so ONNX Runtime keeps the 20 chained Muls)."""
    from onnx import TensorProto, helper, numpy_helper

    print(f"\n## microseconds per Mul of (2^14, k) by a constant, 1 thread   [{load_text()}]")
    n = 1 << 14
    cases = [((n, 1), ()), ((n, 1), (1,)), ((n, 1), (1, 1)), ((n,), ()), ((n, 2), ()), ((n, 2), (n, 2))]
    for shape, const_shape in cases:
        nodes, inits, x = [], [], "x"
        for i in range(20):
            inits.append(numpy_helper.from_array(np.full(const_shape, 1.0001, np.float32), f"c{i}"))
            nodes.append(helper.make_node("Mul", [x, f"c{i}"], [f"y{i}"]))
            x = f"y{i}"
        dims = ["N", *shape[1:]]
        graph = helper.make_graph(nodes, "ops", [helper.make_tensor_value_info("x", TensorProto.FLOAT, dims)],
                                  [helper.make_tensor_value_info(x, TensorProto.FLOAT, dims)], initializer=inits)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
        model.ir_version = 9
        sess = open_session(model.SerializeToString(), Session(threads=1, spinning=False, level="disabled"))
        data = {"x": np.ones(shape, np.float32)}
        _, per_cpu_s = throughput(lambda: sess.run(None, data), 1, args.seconds)
        print(f"  ({', '.join(str(d) for d in shape)}) * const of shape {const_shape}: "
              f"{1e6 / per_cpu_s / 20:8.1f} us")

    # Why the level of detail reads no table with Gather: a Gather costs per row, even from a table
    # in L1; 20 Gathers of the same rows, each from its own copy of the table (no common subexpression)
    print(f"\n## nanoseconds per row of a Gather of 2^14 rows, 1 thread   [{load_text()}]")
    rng = np.random.default_rng(0)
    for rows, width, spread in ((257, 1, 257), (257, 10, 257), (257**2, 28, 256), (257**2, 28, 257**2)):
        inits = [numpy_helper.from_array(rng.normal(size=(rows, width)).astype(np.float32), f"t{i}") for i in range(20)]
        nodes = [helper.make_node("Gather", [f"t{i}", "x"], [f"y{i}"], axis=0) for i in range(20)]
        graph = helper.make_graph(nodes, "ops", [helper.make_tensor_value_info("x", TensorProto.INT64, ["N"])],
                                  [helper.make_tensor_value_info(f"y{i}", TensorProto.FLOAT, ["N", width]) for i in range(20)],
                                  initializer=inits)
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
        model.ir_version = 9
        sess = open_session(model.SerializeToString(), Session(threads=1, spinning=False, level="disabled"))
        data = {"x": rng.integers(0, spread, n).astype(np.int64)}
        _, per_cpu_s = throughput(lambda: sess.run(None, data), n, args.seconds)
        print(f"  ({rows}, {width}) table, rows drawn from the first {spread}: {1e9 / per_cpu_s / 20:6.1f} ns")


def profile_section(model: bytes, args) -> None:
    """ONNX Runtime's per-node kernel times of the shipped graph, by op type and by node."""
    with tempfile.TemporaryDirectory() as folder:
        opts = Session(threads=1, spinning=False).options()
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(folder) / "profile")
        sess = ort.InferenceSession(model, opts, providers=["CPUExecutionProvider"])
        queries, rows = random_queries(1 << 20, seed=20), 1 << 14
        for lo in range(0, len(queries), rows):
            sess.run(None, {C.ONNX_INPUT: queries[lo : lo + rows]})
        events = json.loads(Path(sess.end_profiling()).read_text())
    per_node, op_of = collections.Counter(), {}
    for event in events:
        if event.get("cat") == "Node" and event["name"].endswith("_kernel_time"):
            node = event["name"][: -len("_kernel_time")]
            per_node[node] += event["dur"]
            op_of[node] = event["args"].get("op_name", "?")
    total = sum(per_node.values())
    per_op = collections.Counter()
    for node, us in per_node.items():
        per_op[op_of[node]] += us
    print(f"\n## shipped graph, per-node profile: {total / len(queries) * 1e3:.0f} ns of kernel time per query "
          f"(2^20 random queries, calls of 2^14, 1 thread)   [{load_text()}]")
    for op, us in per_op.most_common():
        print(f"  {op:14s} {100 * us / total:5.1f} %")
    print("  heaviest nodes: " + ", ".join(f"{n} ({op_of[n]}) {100 * us / total:.1f} %"
                                          for n, us in per_node.most_common(8)))


def mlps_only_onnx(config: MaterialConfig, weights: dict) -> bytes:
    """Both MLPs of the material alone, fed fixed linear maps of the queries (no texture, no level
    of detail, no parallax): what the MLPs cost in the graph's own shapes."""
    from onnx import helper

    from neumip.training.export.graph import IR_VERSION, OPSET
    from neumip.training.export.onnx_graph import GraphWriter

    g, rng = GraphWriter(), np.random.default_rng(0)
    widths = {"decoder": config.channels + 4, "offset_mlp": config.offset_channels + 2}
    out = None
    for prefix, width in widths.items():
        x = g.product(rng.normal(size=(width, C.QUERY_DIM)), C.ONNX_INPUT, rows=True)  # (width, N)
        y = g.mlp(x, weights, prefix, config.layers)  # (3, N) decoder, (1, N) offset, as the export's
        out = y if out is None else g.op("Add", out, g.op("MatMul", g.const(np.ones((C.RGB_DIM, 1))), y))
    out = g.op("Transpose", out, perm=[1, 0])
    g.nodes.append(helper.make_node("Relu", [out], [C.ONNX_OUTPUT]))
    return g.model(C.ONNX_INPUT, C.QUERY_DIM, C.ONNX_OUTPUT, C.RGB_DIM, OPSET, IR_VERSION).SerializeToString()


def stages_section(mat, args) -> None:
    """The shipped graph against itself without the offset stage and against its MLPs alone."""
    from dataclasses import replace

    config = mat.config
    weights = weights_from_state(mat.state_dict(), config)
    plain = replace(config, offset=False)
    variants = {
        "shipped graph": build_onnx(config, weights).SerializeToString(),
        "without the neural offset": build_onnx(plain, weights_from_state(mat.state_dict(), plain)).SerializeToString(),
        "the two MLPs alone": mlps_only_onnx(config, weights),
    }
    sessions = {name: open_session(model, Session(threads=1, spinning=False)) for name, model in variants.items()}
    rows = 4096
    for kind, pool in (("random", random_queries(1 << 20, seed=20)), ("coherent", coherent_queries(1 << 20, args.resolution))):
        q = Batches(pool, rows)
        fns = {name: (lambda s=s: s.run(None, {C.ONNX_INPUT: q.next()})) for name, s in sessions.items()}
        ns = {name: 1e9 / cpu for name, (_, cpu) in interleaved(fns, rows, args.seconds, args.rounds).items()}
        full, plain_ns, mlps = ns["shipped graph"], ns["without the neural offset"], ns["the two MLPs alone"]
        print(f"\n## stages, {kind} queries: ns of CPU per query, 1 thread, calls of {rows}   [{load_text()}]")
        for name, value in ns.items():
            print(f"  {name:34s} {value:6.0f} ns   ({1e3 / value:.2f} M queries / CPU s)")
        print(f"  -> offset stage (lookup, offset MLP, parallax): {full - plain_ns:.0f} ns ({100 * (full - plain_ns) / full:.0f} %); "
              f"both MLPs: {mlps:.0f} ns ({100 * mlps / full:.0f} %); everything but the MLPs: {full - mlps:.0f} ns "
              f"({100 * (full - mlps) / full:.0f} %)")


def quantized_section(mat, args) -> None:
    from onnx import helper
    from onnxruntime.quantization import (CalibrationDataReader, QuantFormat, QuantType, quantize_dynamic,
                                          quantize_static)

    from neumip.training.export.graph import IR_VERSION, OPSET
    from neumip.training.export.onnx_graph import GraphWriter

    config = mat.config
    weights = weights_from_state(mat.state_dict(), config)
    g, rng = GraphWriter(), np.random.default_rng(0)
    out = None
    for prefix, width in {"decoder": config.channels + 4, "offset_mlp": config.offset_channels + 2}.items():
        x = g.op("MatMul", C.ONNX_INPUT, g.const(rng.normal(size=(width, C.QUERY_DIM)).T))  # as mlps_only_onnx
        for i in range(config.layers):  # one query per row: Gemm (N, in) x (in, out)
            w, b = (g.const(weights[f"{prefix}.{i}.{part}"]) for part in ("weight", "bias"))
            x = g.op("Gemm", x, w, b, transB=1)
            x = g.op("Relu", x) if i < config.layers - 1 else x
        out = x if out is None else g.op("Add", out, g.op("MatMul", x, g.const(np.ones((1, C.RGB_DIM)))))
    g.nodes.append(helper.make_node("Relu", [out], [C.ONNX_OUTPUT]))
    rows_model = g.model(C.ONNX_INPUT, C.QUERY_DIM, C.ONNX_OUTPUT, C.RGB_DIM, OPSET, IR_VERSION)

    class Calibration(CalibrationDataReader):
        def __init__(self) -> None:
            self.batches = iter([{C.ONNX_INPUT: random_queries(4096, seed=100 + k)} for k in range(4)])

        def get_next(self):
            return next(self.batches, None)

    variants = {"float32, one query per row": rows_model.SerializeToString(),
                "float32, column-major (export)": mlps_only_onnx(config, weights)}
    with tempfile.TemporaryDirectory() as folder:
        source = Path(folder) / "rows.onnx"
        source.write_bytes(variants["float32, one query per row"])
        ops = ["Gemm", "MatMul"]
        for name, fmt in (("int8 static QDQ", QuantFormat.QDQ), ("int8 static QOperator", QuantFormat.QOperator)):
            target = Path(folder) / f"{fmt}.onnx"
            quantize_static(str(source), str(target), Calibration(), quant_format=fmt, op_types_to_quantize=ops,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
            variants[name] = target.read_bytes()
        target = Path(folder) / "dynamic.onnx"
        quantize_dynamic(str(source), str(target), weight_type=QuantType.QInt8, op_types_to_quantize=ops)
        variants["int8 dynamic (MatMulInteger)"] = target.read_bytes()
    sessions = {name: open_session(model, Session(threads=1, spinning=False)) for name, model in variants.items()}
    check = random_queries(65536, seed=7)
    want = sessions["float32, one query per row"].run(None, {C.ONNX_INPUT: check})[0]
    q = Batches(random_queries(1 << 20, seed=20), 4096)
    fns = {name: (lambda s=s: s.run(None, {C.ONNX_INPUT: q.next()})) for name, s in sessions.items()}
    result = interleaved(fns, 4096, args.seconds, args.rounds)
    base = result["float32, one query per row"][1]
    print(f"\n## the two MLPs alone, quantized: 1 thread, calls of 4096   [{load_text()}]")
    for name, s in sessions.items():
        err = np.abs(s.run(None, {C.ONNX_INPUT: check})[0] - want).max() / np.abs(want).max()
        cpu = result[name][1]
        print(f"  {name:32s} {cpu / 1e6:6.2f} M queries / CPU s ({cpu / base:4.2f}x)   max error {err:.1e} of the largest answer")


def log2_list(text: str) -> list[int]:
    if "-" in text:
        lo, hi = (int(x) for x in text.split("-"))
        return list(range(lo, hi + 1))
    return [int(x) for x in text.split(",")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sections", default="graphs,session,chunk,load,ops,profile,stages,quantized")
    parser.add_argument("--resolution", type=int, default=256)
    parser.add_argument("--batches", type=log2_list, default=log2_list("10-20"), help="log2 batch sizes")
    parser.add_argument("--session-batches", type=log2_list, default=log2_list("12,14,16,18"))
    parser.add_argument("--chunks", type=log2_list, default=log2_list("11-16"), help="log2 chunk sizes")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=0.3, help="minimum time per measurement")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--model", type=lambda t: tuple(t.split("=", 1)), action="append", default=[],
                        metavar="NAME=FILE", help="another model file of the same material for the graphs section")
    parser.add_argument("--kernel-before", metavar="FILE", help="kernel section: another checkout's engines/kernel.py "
                        "(git show 906263c:engines/kernel.py > FILE)")
    parser.add_argument("--variant", help="Mitsuba variant of the drjit kernel rows (default llvm_ad_rgb; cuda_ad_rgb "
                        "on an NVIDIA GPU)")
    args = parser.parse_args()
    set_variant(args.variant)
    torch.set_num_threads(args.threads)

    mat = material(args.resolution, seed=0)
    weights = weights_from_state(mat.state_dict(), mat.config)
    models = {name: build(mat.config, weights).SerializeToString() for name, build in GRAPHS.items()}
    print(f"# {args.resolution}^2 material with offset; onnxruntime {ort.__version__}, torch {torch.__version__}, "
          f"{args.threads} threads; {load_text()}")
    sections = args.sections.split(",")
    if "graphs" in sections:
        graphs_section(mat, models, args)
    if "kernel" in sections:
        kernel_section(mat, models, args)
    if "session" in sections:
        session_section(models[SHIPPED], args)
    if "chunk" in sections:
        chunk_section(models[SHIPPED], args)
    if "load" in sections:
        load_section(models, args)
    if "ops" in sections:
        ops_section(args)
    if "profile" in sections:
        profile_section(models[SHIPPED], args)
    if "stages" in sections:
        stages_section(mat, args)
    if "quantized" in sections:
        quantized_section(mat, args)


if __name__ == "__main__":
    main()
