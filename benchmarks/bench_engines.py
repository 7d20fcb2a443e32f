"""Every engine on the shipped models, beside the decoder MLP alone: file size, load time, queries/s.

    .venv/bin/python benchmarks/bench_engines.py                          # yarn, rock, flat (~1 min)
    .venv/bin/python benchmarks/bench_engines.py --models yarn --rounds 7 --batch 17
    .venv/bin/python benchmarks/bench_engines.py --ort level=basic,spin=1,intra=2+workers=1 --profile

Per model (``--folder``/NAME.onnx): the file's size; seconds to load it in ONNX Runtime (`load_material`:
read, check, open a session) and in the kernel engine (`KernelMaterial`: read, check, a trial trace), and
the kernel's first call (compiling, or drjit's disk cache); then queries/s of 2^batch random single
queries per call, in interleaved rounds (every model and engine once a round; medians of the rounds):

- onnxruntime: `LocalMaterials.evaluate` as shipped (`--threads` chunk workers, one-thread sessions);
- kernel: `KernelMaterials.evaluate` (drjit LLVM, one call over every core);
- mlp-only: an ONNX graph of the model's decoder MLP alone (its widths, random weights: speed does not
  depend on them), Gemm per layer on an (N, in) input, run as `LocalMaterials` runs a model;
- each ``--ort SPEC``: ONNX Runtime with other options, run like `LocalMaterials` (`run_chunked`). SPEC
  is tokens joined by ``+``, each changing the shipped options (``shipped``: none):
  ``level=disabled|basic|extended|all``, ``saved`` (the optimised graph saved by `optimized_model_filepath`,
  loaded without optimising again), ``spin=0|1``, ``intra=N`` (intra-op threads a session), ``workers=N``
  (chunk threads; 1: the chunks one after another), ``chunk=N`` (answers a call), ``parallel``
  (ORT_PARALLEL, 2 inter-op threads), ``arena=0``, ``mempattern=0``, ``cfg:KEY=VALUE`` (a session config entry).

``--server``: also each engine behind a real `neumip serve` (`NEUMIP_ENGINE=onnxruntime` and ``kernel``, both
running, default settings but shared memory allowed, serving these models), sent the same batches as msgpack
by one `MaterialClient`, and by another through shared memory (``, shm``: Triton's system shared-memory
extension, the rows in ``/dev/shm``); and, in process and through each server, the renderer's query groups of
two lights (2^batch groups: twice the answers). ``/in-proc``: a served engine's rate over the same engine's in
process, on the same queries. Its ``CPU M/s`` counts the server's CPU time too. ``--server-env KEY=VALUE ...`` starts a second
server of each engine with those environment variables, measured in the same interleaved rounds (an A/B of a
setting, e.g. glibc's ``MALLOC_MMAP_THRESHOLD_``).

Ratios are per round, then the median: ``/mlp`` to the mlp-only graph, ``/kernel`` to the kernel engine
(the same kind: in process or served, single queries or groups). Groups count answers (2 a group).
``bits``: ``same`` where the answers equal the shipped onnxruntime's bit for bit, else the largest
difference. ``--profile``: ONNX Runtime's per-node profile of each model (1 thread, calls of
`DEFAULT_CHUNK`), by op: its share of the kernel time (nodes a call); then its reads alone: each of its
Gathers as a one-node graph on a table of the same shape, random rows, beside numpy's `take` of them (`gather_floor`).
``bound``: the rate the model's arithmetic allows at the MLP-only graph's rate of arithmetic (`graph_cost.py`: the
operations a query of each graph, from their shapes: an estimate), and each engine's share of it.
The machine is shared: read the load averages printed at the start and end.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnx import TensorProto, helper, numpy_helper

from graph_cost import graph_cost, operations  # this folder is on sys.path when run as a script
from neumip.core import contract as C
from neumip.core import weights as W
from neumip.core.modelfile import read_model_file
from neumip.engines.kernel import KernelMaterial, KernelMaterials
from neumip.engines.local import (
    DEFAULT_CHUNK,
    SESSION_CONFIG,
    LocalMaterials,
    load_material,
    run_call,
    run_chunked,
    split_chunk,
)

SETTLE_S = 0.1
"""Pause before each measurement: drjit's workers (and ONNX Runtime's spinning ones) spin for tens of
milliseconds after a call, taking CPU from the measurement after them."""

LEVELS = {"disabled": ort.GraphOptimizationLevel.ORT_DISABLE_ALL, "basic": ort.GraphOptimizationLevel.ORT_ENABLE_BASIC,
          "extended": ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED, "all": ort.GraphOptimizationLevel.ORT_ENABLE_ALL}


def load_text() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min) on {os.cpu_count()} cores"


def parse_spec(spec: str, threads: int) -> dict:
    """An ``--ort`` SPEC -> its settings (the shipped ones where it says nothing)."""
    s = {"level": "all", "saved": False, "spin": "0", "intra": 1, "workers": threads, "chunk": DEFAULT_CHUNK,
         "parallel": False, "arena": True, "mempattern": True, "config": {}}
    for token in filter(None, spec.split("+")):
        key, _, value = token.partition("=")
        if key.startswith("cfg:"):
            s["config"][key[4:]] = value
        elif key == "shipped":
            pass
        elif key in ("saved", "parallel"):
            s[key] = True
        elif key in ("arena", "mempattern"):
            s[key] = value != "0"
        elif key in ("intra", "workers", "chunk"):
            s[key] = int(value)
        elif key in ("level", "spin"):
            s[key] = value
        else:
            raise SystemExit(f"unknown --ort token {token!r}")
    return s


def options(s: dict, level: str | None = None) -> ort.SessionOptions:
    """Session options of settings `s` (`load_material`'s, changed where `s` says)."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = s["intra"]
    opts.inter_op_num_threads = 2 if s["parallel"] else 1
    opts.log_severity_level = 3
    opts.graph_optimization_level = LEVELS[level or s["level"]]
    opts.enable_cpu_mem_arena = s["arena"]
    opts.enable_mem_pattern = s["mempattern"]
    if s["parallel"]:
        opts.execution_mode = ort.ExecutionMode.ORT_PARALLEL
    for key, value in {**SESSION_CONFIG, "session.intra_op.allow_spinning": s["spin"], **s["config"]}.items():
        opts.add_session_config_entry(key, value)
    return opts


def open_variant(data: bytes, s: dict, folder: str) -> tuple[ort.InferenceSession, float]:
    """A session of settings `s` on the model `data`, and the seconds it took to open (``saved``: to
    open the saved optimised graph, written first into `folder`)."""
    source, opts = data, options(s)
    if s["saved"]:
        source = Path(folder) / f"saved{len(os.listdir(folder))}.onnx"
        opts.optimized_model_filepath = str(source)
        ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])
        source, opts = str(source), options(s, "disabled")
    start = time.perf_counter()
    return ort.InferenceSession(source, opts, providers=["CPUExecutionProvider"]), time.perf_counter() - start


def folded_mib(data: bytes, scratch: Path) -> float:
    """MiB of constants an ONNX Runtime session of the model holds once it has folded the graph at load (its
    optimised graph's initializers: the quad tables among them)."""
    opts = ort.SessionOptions()
    opts.log_severity_level = 3
    opts.optimized_model_filepath = str(scratch / "folded.onnx")
    ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])
    inits = onnx.load(opts.optimized_model_filepath).graph.initializer
    return sum(int(np.prod(i.dims, dtype=np.int64)) * onnx.helper.tensor_dtype_to_np_dtype(i.data_type).itemsize
               for i in inits) / 2**20


def mlp_only(config) -> tuple[bytes, int]:
    """The decoder MLP alone, widths as the model's: (N, in) -> (N, out) float32, Gemm + Relu; and `in`."""
    inputs, answers = W.mlps(config)[W.DECODER]
    widths = [inputs] + [config.hidden] * (config.layers - 1) + [answers]
    rng, nodes, inits, x = np.random.default_rng(0), [], [], "x"
    for i in range(config.layers):
        w = rng.normal(scale=widths[i] ** -0.5, size=(widths[i + 1], widths[i])).astype(np.float32)
        inits += [numpy_helper.from_array(w, f"w{i}"), numpy_helper.from_array(np.zeros(widths[i + 1], np.float32), f"b{i}")]
        nodes.append(helper.make_node("Gemm", [x, f"w{i}", f"b{i}"], [f"g{i}"], transB=1))
        x = f"g{i}"
        if i < config.layers - 1:
            nodes.append(helper.make_node("Relu", [x], [f"r{i}"]))
            x = f"r{i}"
    graph = helper.make_graph(nodes, "mlp", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["N", inputs])],
                              [helper.make_tensor_value_info(x, TensorProto.FLOAT, ["N", answers])], initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 9
    return model.SerializeToString(), inputs


def chunked(session, x: np.ndarray, chunk: int, workers: int, executor) -> np.ndarray:
    """`x` through `session` in calls as `LocalMaterials.evaluate` cuts a batch (any widths in and out)."""
    rows = split_chunk(len(x), workers, chunk)
    parts = list(range(0, len(x), rows))
    name = session.get_inputs()[0].name

    def call(lo: int) -> np.ndarray:
        return session.run(None, {name: x[lo:lo + rows]})[0]
    return np.concatenate(list(executor.map(call, parts)) if executor and len(parts) > 1 else [call(lo) for lo in parts])


def process_cpu_s(pid: int | None = None) -> float:
    """CPU seconds (user + system) of process `pid` (None: this one)."""
    if pid is None:
        return time.process_time()
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def throughput(fn, rows: int, seconds: float, server: int | None = None) -> tuple[float, float]:
    """(answers per wall-clock second, per CPU second of this process and the `server` process, if
    any) of `fn()`, which gives `rows` answers, repeated for at least `seconds`."""
    def cpu_s() -> float:
        return process_cpu_s() + (process_cpu_s(server) if server else 0.0)
    calls, start, cpu = 0, time.perf_counter(), cpu_s()
    while True:
        fn()
        calls += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return calls * rows / elapsed, calls * rows / max(cpu_s() - cpu, 1e-9)


def pairs(queries: np.ndarray) -> np.ndarray:
    """(N, 9) query groups of two lights: each query and the wi of another one (`bench_server.pairs`)."""
    other = np.roll(queries, len(queries) // 2, axis=0)[:, C.WI_X:C.WI_Y + 1]
    return np.ascontiguousarray(np.hstack([queries, other]))


def start_servers(folder: Path, names: list[str], scratch: Path, env: dict[str, str] | None = None) -> dict:
    """A `neumip serve` of each engine on a folder of the models `names`, shared memory allowed: {engine: (server,
    {protocol: client})}, a msgpack client and one that passes the rows through shared memory (``shm``); with
    `env`, a second one of each engine with those environment variables, named "ENGINE KEY=VALUE"."""
    from neumip.client.http import ClientConfig, MaterialClient
    from neumip.server.process import ServerProcess

    served = scratch / "served"
    served.mkdir()
    for name in names:
        (served / f"{name}.onnx").symlink_to((folder / f"{name}.onnx").resolve())
    servers = {}
    variants = [(engine, {}) for engine in ("onnxruntime", "kernel")]
    if env:
        variants += [(engine, env) for engine in ("onnxruntime", "kernel")]
    for engine, extra in variants:
        name = " ".join([engine, *(f"{k}={v}" for k, v in extra.items())])
        server = ServerProcess.start(served, scratch / f"{name.replace(' ', '_')}.log", env=extra, engine=engine,
                                     allow_shared_memory="true")
        servers[name] = (server, {protocol: MaterialClient(server.url, ClientConfig(timeout_s=120), protocol=protocol)
                                  for protocol in ("msgpack", "shm")})
        print(f"# server {name} ready in {server.ready_s:.1f} s")
    return servers


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def profile(path: Path) -> None:
    """ONNX Runtime's per-node kernel time of the model, summed by op type; then its reads alone (`gather_floor`)."""
    with tempfile.TemporaryDirectory() as folder:
        opts = options(parse_spec("", 1))
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(folder) / "profile")
        opts.optimized_model_filepath = str(Path(folder) / "optimised.onnx")
        sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        q = C.random_queries(1 << 17, seed=20)
        for lo in range(0, len(q), DEFAULT_CHUNK):
            run_call(sess, q[lo:lo + DEFAULT_CHUNK])
        events = json.loads(Path(sess.end_profiling()).read_text())
        optimised = onnx.load(str(Path(folder) / "optimised.onnx"))
    per_op, count, per_node = collections.Counter(), collections.Counter(), collections.Counter()
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            op = e["args"].get("op_name", "?")
            per_op[op] += e["dur"]
            count[op] += 1
            shapes = " x ".join(str(next(iter(t.values()))) for t in e["args"].get("input_type_shape", []))
            per_node[f"{op} {e['name'][:-12]} {shapes}"] += e["dur"]
    total, calls = sum(per_op.values()), len(q) // DEFAULT_CHUNK
    print(f"\n## {path.stem}: ONNX Runtime profile, {total / len(q) * 1e3:.0f} ns of kernel time a query "
          f"(1 thread, calls of {DEFAULT_CHUNK})   [{load_text()}]")
    print("  " + ", ".join(f"{op} {100 * us / total:.1f} % ({count[op] // calls})" for op, us in per_op.most_common(12)))
    print("  heaviest nodes: " + ", ".join(f"{n} {100 * us / total:.1f} %" for n, us in per_node.most_common(6)))
    reads = gather_floor(optimised, per_node, DEFAULT_CHUNK)
    ort_ns, numpy_ns = (sum(r[k] for r in reads) for k in ("ort", "numpy"))
    print(f"  its reads alone (each Gather of a table as a one-node graph, random rows, best of 7): {ort_ns:.0f} ns "
          f"a query in ONNX Runtime, {numpy_ns:.0f} with numpy's take, {sum(r['rows'] for r in reads)} rows: "
          + ", ".join(f"{r['table']} x {r['rows']} {r['ort'] / r['rows']:.1f}/{r['numpy'] / r['rows']:.1f} ns a row"
                      for r in reads))


def gather_floor(model: onnx.ModelProto, per_node: collections.Counter, rows: int) -> list[dict]:
    """What each `Gather` of the profile (`per_node`: "OP NAME [table] x [index]") costs alone: a one-node graph of a
    table the optimised `model` Gathers from (an initializer, ONNX Runtime's folded quad tables among them) of its shape
    and type, read at random rows, as many a query as in the model, 1 thread, against numpy's `take` of the same rows
    (ns a query)."""
    read = {n.input[0] for n in model.graph.node if n.op_type == "Gather"}
    tables = {tuple(i.dims): i for i in model.graph.initializer if i.name in read and len(i.dims) == 2}
    rng, out = np.random.default_rng(0), []
    for key in per_node:
        if not key.startswith("Gather "):
            continue
        table_shape, index_shape = (tuple(int(v) for v in part.strip().strip("[]").split(",") if v.strip())
                                    for part in key.split(" ", 2)[2].split(" x "))
        if table_shape not in tables:
            continue
        table = numpy_helper.to_array(tables[table_shape])
        index = rng.integers(0, len(table), (rows, max(1, int(np.prod(index_shape)) // rows)))
        graph = helper.make_graph([helper.make_node("Gather", [tables[table_shape].name, "index"], ["rows"], axis=0)],
                                  "read", [helper.make_tensor_value_info("index", TensorProto.INT64, None)],
                                  [helper.make_tensor_value_info("rows", tables[table_shape].data_type, None)],
                                  [tables[table_shape]])
        alone = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=9)
        sess = ort.InferenceSession(alone.SerializeToString(), options(parse_spec("", 1)),
                                    providers=["CPUExecutionProvider"])
        best = {"ort": min(timed(lambda: sess.run(None, {"index": index})) for _ in range(7)),
                "numpy": min(timed(lambda: np.take(table, index, axis=0)) for _ in range(7))}
        out.append({"table": f"[{len(table)}, {table.shape[1]}] {table.dtype}", "rows": index.shape[1],
                    **{k: v / rows * 1e9 for k, v in best.items()}})
    return out


class Batches:
    """Four batches of 2^batch random queries (and as groups of two lights), handed out in turn per caller,
    so that consecutive calls of one engine do not re-read what the previous call left in cache."""

    def __init__(self, rows: int) -> None:
        pool = C.random_queries(4 * rows, seed=1)
        self.single = [pool[i * rows:(i + 1) * rows] for i in range(4)]
        self.groups = [pairs(b) for b in self.single]
        self.turn = collections.Counter()

    def next(self, key, groups: bool = False) -> np.ndarray:
        self.turn[key] += 1
        return (self.groups if groups else self.single)[self.turn[key] % 4]


class Bench:
    """The engines of every model, measured in interleaved rounds."""

    def __init__(self, args, scratch: Path) -> None:
        self.args, self.scratch, self.rows = args, scratch, 1 << args.batch
        self.local = LocalMaterials(args.folder, threads=args.threads, lazy=True)
        self.kernel = KernelMaterials(args.folder)
        self.executor = ThreadPoolExecutor(args.threads) if args.threads > 1 else None
        self.batches = Batches(self.rows)
        env = dict(kv.split("=", 1) for kv in args.server_env)
        self.servers = start_servers(args.folder, args.models, scratch, env) if args.server else {}
        self.server_pids: dict[str, int] = {}  # served engine -> its server's pid (its CPU time counts)
        self.fns, self.answers, self.loads, self.info = {}, {}, {}, {}
        self.results = collections.defaultdict(list)

    def add_model(self, name: str) -> None:
        """Load model `name` in every engine (timed), check the answers, warm each engine up."""
        path = self.args.folder / f"{name}.onnx"
        data = path.read_bytes()
        self.loads[name] = {"onnxruntime": statistics.median(timed(lambda: load_material(path, 1)) for _ in range(3)),
                            "kernel": statistics.median(timed(lambda: KernelMaterial(path)) for _ in range(3)),
                            "kernel first call": timed(lambda: self.kernel.evaluate(name, self.batches.single[0]))}
        config = read_model_file(path, data).config
        engines = self.engines(name, config)
        checks = {"onnxruntime": self.local.evaluate(name, self.batches.single[0]),
                  "kernel": self.kernel.evaluate(name, self.batches.single[0])}
        for spec in self.args.ort:
            run, self.loads[name][f"ort {spec}"] = self.variant(data, spec)
            engines[f"ort {spec}"] = lambda run=run, key=(name, spec): run(self.batches.next(key))
            checks[f"ort {spec}"] = run(self.batches.single[0])
        for engine, fn in engines.items():
            fn()  # warm-up
            self.fns[name, engine] = fn
            self.answers[name, engine] = 2 * self.rows if engine.endswith("groups of 2") else self.rows
        want = checks["onnxruntime"]
        bits = {e: "same" if np.array_equal(a, want) else f"{np.abs(a - want).max():.1e}" for e, a in checks.items()}
        ops = (operations(graph_cost(onnx.load_model_from_string(data))),
               operations(graph_cost(onnx.load_model_from_string(mlp_only(config)[0]))))
        self.info[name] = {"MB": len(data) / 1e6, "bits": bits, "ops": ops, "folded": folded_mib(data, self.scratch)}

    def engines(self, name: str, config) -> dict:
        """{engine: fn()} of model `name`: the shipped engines, the mlp-only graph, with --server the servers."""
        mlp, width = mlp_only(config)
        session = ort.InferenceSession(mlp, options(parse_spec("", 1)), providers=["CPUExecutionProvider"])
        x = np.random.default_rng(2).normal(size=(self.rows, width)).astype(np.float32)
        b = self.batches
        engines = {"onnxruntime": lambda: self.local.evaluate(name, b.next((name, "ort"))),
                   "kernel": lambda: self.kernel.evaluate(name, b.next((name, "kernel"))),
                   "mlp-only": lambda: chunked(session, x, DEFAULT_CHUNK, self.args.threads, self.executor)}
        if self.servers:
            engines["onnxruntime, groups of 2"] = lambda: self.local.evaluate(name, b.next((name, "ort2"), True))
            engines["kernel, groups of 2"] = lambda: self.kernel.evaluate(name, b.next((name, "kernel2"), True))
        for engine, (server, clients) in self.servers.items():
            for protocol, client in clients.items():
                label = f"server {engine}" + ("" if protocol == "msgpack" else f", {protocol}")
                engines[label] = lambda c=client: c.evaluate(name, b.next((name, c)))
                engines[f"{label}, groups of 2"] = lambda c=client: c.evaluate(name, b.next((name, c, 2), True))
                self.server_pids[label] = self.server_pids[f"{label}, groups of 2"] = server.process.pid
        return engines

    def variant(self, data: bytes, spec: str):
        """(run(queries), seconds to open) of the ONNX Runtime variant `spec`."""
        s = parse_spec(spec, self.args.threads)
        session, seconds = open_variant(data, s, str(self.scratch))
        workers, chunk = s["workers"], s["chunk"]
        executor = ThreadPoolExecutor(workers) if workers > 1 else None

        def run(q: np.ndarray) -> np.ndarray:
            return run_chunked(lambda c: run_call(session, c), q, split_chunk(len(q), workers, chunk), executor)
        return run, seconds

    def measure(self) -> None:
        for _ in range(self.args.rounds):
            for key, fn in self.fns.items():
                time.sleep(SETTLE_S)
                server = self.server_pids.get(key[1])
                self.results[key].append(throughput(fn, self.answers[key], self.args.seconds, server))

    def ratio(self, name: str, engine: str, other: str) -> float:
        """Median over the rounds of `engine`'s speed / `other`'s."""
        return statistics.median(a[0] / b[0] for a, b in zip(self.results[name, engine], self.results[name, other]))

    def print(self, name: str) -> None:
        print(f"\n## {name}: {self.info[name]['MB']:.1f} MB (ONNX Runtime's constants after folding: "
              f"{self.info[name]['folded']:.1f} MiB); load s: " +
              ", ".join(f"{e} {s:.3f}" for e, s in self.loads[name].items()))
        print(f"  {'engine':40s} {'M q/s':>7s} {'CPU M/s':>8s} {'/mlp':>6s} {'/kernel':>8s} {'/in-proc':>9s}  bits")
        for engine in [e for (n, e) in self.fns if n == name]:
            groups = ", groups of 2" if engine.endswith("groups of 2") else ""
            like = ("server " if engine.startswith("server") else "") + "kernel" + groups
            wall, cpu = (statistics.median(r[i] for r in self.results[name, engine]) / 1e6 for i in (0, 1))
            served = engine.startswith("server")  # against the same engine in process, on the same kind of queries
            in_process = f"{self.ratio(name, engine, engine.split()[1].rstrip(',') + groups):9.2f}" if served else " " * 9
            print(f"  {engine:40s} {wall:7.2f} {cpu:8.2f} {self.ratio(name, engine, 'mlp-only'):6.2f} "
                  f"{self.ratio(name, engine, like):8.2f} {in_process}  {self.info[name]['bits'].get(engine, '')}")
        model_ops, mlp_ops = self.info[name]["ops"]
        share = mlp_ops / model_ops
        print(f"  bound: the model's graph is ~{model_ops} operations a query, the MLP-only graph's {mlp_ops}: at the "
              f"MLP-only graph's rate of arithmetic the model answers about {share:.2f}x its queries/s; the kernel engine "
              f"reaches {self.ratio(name, 'kernel', 'mlp-only') / share:.2f}x of that, ONNX Runtime "
              f"{self.ratio(name, 'onnxruntime', 'mlp-only') / share:.2f}x")

    def close(self) -> None:
        for server, clients in self.servers.values():
            for client in clients.values():
                client.close()
            server.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--folder", type=Path, default=Path("models"))
    parser.add_argument("--models", type=lambda t: t.split(","), default=["yarn", "rock", "flat"],
                        help="comma-separated model names")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--batch", type=int, default=17, help="log2 of the queries per call")
    parser.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="LocalMaterials' chunk workers")
    parser.add_argument("--seconds", type=float, default=0.25, help="least time of one measurement")
    parser.add_argument("--ort", type=lambda t: t.split(","), default=[], help="ONNX Runtime variants (SPEC,...)")
    parser.add_argument("--profile", action="store_true", help="ONNX Runtime's per-op profile of each model")
    parser.add_argument("--server", action="store_true", help="also through a server of each engine, and groups of two")
    parser.add_argument("--server-env", nargs="*", default=[], metavar="KEY=VALUE",
                        help="with --server, a second server of each engine with these environment variables")
    args = parser.parse_args()
    print(f"# {1 << args.batch} random single queries a call, {args.rounds} rounds; onnxruntime {ort.__version__}, "
          f"{args.threads} threads; {load_text()}")
    with tempfile.TemporaryDirectory() as scratch:
        bench = Bench(args, Path(scratch))
        try:
            for name in args.models:
                bench.add_model(name)
            print(f"# loaded   [{load_text()}]")
            bench.measure()
            print(f"# measured [{load_text()}]")
            for name in args.models:
                bench.print(name)
        finally:
            bench.close()
    if args.profile:
        for name in args.models:
            profile(args.folder / f"{name}.onnx")


if __name__ == "__main__":
    main()
