"""Benchmark: start-up time and resident memory of `neumip serve` with eager and lazy loading, and
what the LRU memory budget does under concurrent load.

Section ``startup``: a folder of ``--count`` copies of one model (default the shipped rock, 454 KB);
`neumip serve` is started with ``NEUMIP_LOAD=eager`` and ``=lazy`` and timed from process start to
``/v2/health/ready`` answering 200; its resident memory (VmRSS) is read then, and (lazy) again after
requests to three materials; a lazy server over one model gives the process's own start-up. Section ``lru``: a lazy server with a budget of ``--budget-models``
models serves ``--clients`` threads that each send ``--requests`` requests of 4096 queries to a
random one of ``--materials`` materials; printed: throughput, latency percentiles, loads, unloads,
the largest resident model bytes seen on /metrics (sampled every 20 ms) against the budget, errors. Section
``folders``: `neumip serve` over each of ``--folders`` as it is, with its default settings, in ``--rounds``
interleaved rounds: the folder's bytes, ready seconds and resident memory when ready and after a request to each
material (median and range of the rounds). Section ``arena``: ONNX Runtime's sessions over the first of
``--folders`` with an arena each, one shared arena, or none (`arena_worker`): resident memory and speed. Section
``fullload``: `neumip serve` over the first of ``--folders`` (its default engine; ``--server-env KEY=VALUE``, e.g.
the Docker image's ``MALLOC_MMAP_THRESHOLD_=4194304``) under ``--clients`` threads sending requests of 2M queries
(msgpack, each to one of the folder's materials in turn) for ``--seconds``: resident memory when ready, its peak
(sampled every 0.5 s), and 1, 3 and 6 s after the clients stop (the server trims its heap after 1 s idle).

    .venv/bin/python benchmarks/bench_loading.py                   # startup and lru
    .venv/bin/python benchmarks/bench_loading.py --sections lru --clients 8
    .venv/bin/python benchmarks/bench_loading.py --sections folders --folders OLD_MODELS,models --rounds 3
    .venv/bin/python benchmarks/bench_loading.py --sections arena --folders models --rounds 3
    .venv/bin/python benchmarks/bench_loading.py --sections fullload --clients 6 --seconds 25 \
        --server-env MALLOC_MMAP_THRESHOLD_=4194304
"""

from __future__ import annotations

import argparse
import re
import shutil
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from neumip.core import wire
from neumip.core.contract import random_queries
from neumip.server.process import ServerProcess


class Server:
    def __init__(self, folder: Path, **env) -> None:
        self.process = ServerProcess.start(folder, **env)
        self.url, self.proc, self.ready_s = self.process.url, self.process.process, self.process.ready_s

    def rss_mb(self) -> float:  # MiB
        return self.process.rss_bytes() / 2**20

    def metric(self, name: str, **labels) -> float:
        total = 0.0
        for line in httpx.get(self.url + "/metrics").text.splitlines():
            m = re.match(rf"^{name}(?:{{(.*)}})? (\S+)$", line)
            if m and all(f'{k}="{v}"' in (m.group(1) or "") for k, v in labels.items()):
                total += float(m.group(2))
        return total

    def evaluate(self, name: str, q: np.ndarray) -> httpx.Response:
        return httpx.post(self.url + wire.EVALUATE_PATH.format(name=name), content=wire.encode_request(q),
                          headers={"content-type": wire.MSGPACK_MEDIA_TYPE}, timeout=120)

    def stop(self) -> None:
        self.process.stop(30)


def copies(model: Path, folder: Path, count: int) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        shutil.copy(model, folder / f"m{i:03d}.onnx")
    return folder


def startup(args, tmp: Path) -> None:
    folder = copies(args.model, tmp / "startup", args.count)
    size = args.model.stat().st_size
    print(f"startup: {args.count} copies of {args.model.name} ({size:,} bytes each)")
    for mode in ("eager", "lazy"):
        server = Server(folder, load=mode, poll_s=0)
        line = f"  {mode:5s}: ready in {server.ready_s:.2f} s, RSS {server.rss_mb():.0f} MB"
        if mode == "lazy":
            for name in ("m000", "m001", "m002"):
                server.evaluate(name, random_queries(1024))
            line += f"; after 3 materials' first requests {server.rss_mb():.0f} MB"
        print(line)
        server.stop()
    one = copies(args.model, tmp / "one", 1)
    server = Server(one, load="lazy", poll_s=0)
    print(f"  lazy with 1 model (the process's own start-up): ready in {server.ready_s:.2f} s, RSS {server.rss_mb():.0f} MB")
    server.stop()


def folders(args, tmp: Path) -> None:
    paths = [Path(f) for f in args.folders.split(",")]
    ready, rss, warm = ({p: [] for p in paths} for _ in range(3))
    q = random_queries(65536, seed=1)
    for _ in range(args.rounds):
        for path in paths:
            server = Server(path)
            ready[path].append(server.ready_s)
            rss[path].append(server.rss_mb())
            for model in sorted(path.glob("*.onnx")):
                server.evaluate(model.stem, q).raise_for_status()
            warm[path].append(server.rss_mb())
            server.stop()

    def spread(values: list) -> str:
        return f"{np.median(values):.0f} MiB ({min(values):.0f}-{max(values):.0f})"

    for path in paths:
        models = sorted(path.glob("*.onnx"))
        size = sum(m.stat().st_size for m in models)
        print(f"{path}: {len(models)} models, {size / 1e6:.2f} MB; ready in {np.median(ready[path]):.2f} s "
              f"({min(ready[path]):.2f}-{max(ready[path]):.2f}), RSS {spread(rss[path])}, after a 65,536-query "
              f"request to each {spread(warm[path])}; {args.rounds} rounds")


ARENAS = ("own", "shared", "none")
"""ONNX Runtime's CPU memory in section ``arena``: an arena per session (ONNX Runtime's default), one arena of the
process that every session shares (`engines.local.SESSION_CONFIG`, what `LocalMaterials` uses), no arena."""


def arena_worker(mode: str, folder: Path, rounds: int) -> None:
    """One process: sessions over every model of `folder` made as `mode` says (`ARENAS`), as `engines.local` makes
    them otherwise; two threads run a 2^15-query call of each in chunks of 2^14; prints one JSON line: resident MiB
    loaded, after a call each, after `rounds` more, and queries per CPU second of those rounds."""
    import json
    import os
    from concurrent.futures import ThreadPoolExecutor

    os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
    import onnxruntime as ort

    from neumip.engines.local import SESSION_CONFIG, share_arena

    def rss() -> float:  # MiB
        with open("/proc/self/status") as status:
            return int(next(line for line in status if line.startswith("VmRSS")).split()[1]) / 1024

    if mode == "shared":
        share_arena(ort)
    sessions = []
    for path in sorted(folder.glob("*.onnx")):
        opts = ort.SessionOptions()
        opts.intra_op_num_threads, opts.inter_op_num_threads, opts.log_severity_level = 1, 1, 3
        for key, value in SESSION_CONFIG.items():
            if key != "session.use_env_allocators" or mode == "shared":
                opts.add_session_config_entry(key, value)
        opts.enable_cpu_mem_arena = mode != "none"
        sessions.append(ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"]))
    loaded = rss()
    q = random_queries(2 * 16384, seed=1)
    pool = ThreadPoolExecutor(2)

    def each() -> None:
        for session in sessions:
            list(pool.map(lambda part: session.run(["rgb"], {"queries": part}), (q[:16384], q[16384:])))

    each()
    warm = rss()
    cpu = time.process_time()
    for _ in range(rounds):
        each()
    rate = rounds * len(sessions) * len(q) / (time.process_time() - cpu)
    print(json.dumps({"loaded": loaded, "warm": warm, "after": rss(), "rate": rate}))


def arena(args, tmp: Path) -> None:
    """Section ``arena``: `arena_worker` of each mode in a fresh process, modes interleaved over ``--rounds``, with
    the Docker image's ``MALLOC_MMAP_THRESHOLD_=131072``."""
    import json
    import os
    import subprocess
    import sys

    folder = Path(args.folders.split(",")[0])
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "131072"}
    got = {mode: [] for mode in ARENAS}
    for _ in range(args.rounds):
        for mode in ARENAS:
            out = subprocess.run([sys.executable, __file__, "--arena-worker", mode, "--folders", str(folder)],
                                 env=env, capture_output=True, text=True, check=True).stdout
            got[mode].append(json.loads(out.splitlines()[-1]))
    print(f"arena: {folder}, {len(list(folder.glob('*.onnx')))} models, 2 threads, calls of 2^14, 3 rounds after the "
          f"first call; MALLOC_MMAP_THRESHOLD_=131072; median (range) of {args.rounds} processes each")
    for mode in ARENAS:
        cols = {key: [r[key] for r in got[mode]] for key in ("loaded", "warm", "after", "rate")}
        mib = ", ".join(f"{key} {np.median(v):.0f} MiB ({min(v):.0f}-{max(v):.0f})"
                        for key, v in cols.items() if key != "rate")
        rate = cols["rate"]
        print(f"  {mode:6s}: {mib}; {np.median(rate) / 1e6:.3f} M q per CPU s ({min(rate) / 1e6:.3f}-"
              f"{max(rate) / 1e6:.3f})")


def lru(args, tmp: Path) -> None:
    folder = copies(args.model, tmp / "lru", args.materials)
    size = args.model.stat().st_size
    budget = args.budget_models * size
    server = Server(folder, load="lazy", poll_s=0, memory_budget_mb=budget / 2**20)
    q = random_queries(4096, seed=1)
    latencies, errors, peaks, stop = [], [], [], threading.Event()

    def client(seed: int) -> None:
        rng = np.random.default_rng(seed)
        for _ in range(args.requests):
            start = time.perf_counter()
            resp = server.evaluate(f"m{rng.integers(args.materials):03d}", q)
            latencies.append(time.perf_counter() - start)
            if resp.status_code != 200:
                errors.append(resp.status_code)

    def watch() -> None:
        while not stop.is_set():
            peaks.append(server.metric("neumip_model_resident_bytes"))
            time.sleep(0.02)

    watcher = threading.Thread(target=watch)
    watcher.start()
    threads = [threading.Thread(target=client, args=(i,)) for i in range(args.clients)]
    start = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - start
    stop.set()
    watcher.join()
    p50, p99 = np.percentile(latencies, [50, 99]) * 1e3
    print(f"lru: {args.clients} clients x {args.requests} requests of 4096 queries over {args.materials} "
          f"materials, budget {args.budget_models} models ({budget:,} bytes)")
    print(f"  {len(latencies) / wall:.1f} requests/s, latency p50 {p50:.0f} ms, p99 {p99:.0f} ms, errors {len(errors)}")
    print(f"  loads {server.metric('neumip_model_loads_total', outcome='loaded'):.0f}, unloads (memory) "
          f"{server.metric('neumip_model_unloads_total', reason='memory'):.0f}, load p50 "
          f"{1e3 * server.metric('neumip_model_load_seconds_sum') / max(server.metric('neumip_model_load_seconds_count'), 1):.0f} ms mean")
    print(f"  resident model bytes: largest seen {max(peaks):,.0f} ({max(peaks) / size:.1f} models), "
          f"at the end {server.metric('neumip_model_resident_bytes'):,.0f}; RSS {server.rss_mb():.0f} MB")
    server.stop()


def fullload(args, tmp: Path) -> None:
    folder = Path(args.folders.split(",")[0])
    names = sorted(p.stem for p in folder.glob("*.onnx"))
    env = dict(kv.split("=", 1) for kv in args.server_env)
    server = ServerProcess.start(folder, tmp / "fullload.log", env=env)
    try:
        time.sleep(2.0)
        ready = server.rss_bytes() / 2**20
        queries = random_queries(2_000_000, seed=1)
        body = wire.encode_request(queries)
        stop = time.monotonic() + args.seconds
        answered, refused = [0], [0]

        def client(i: int) -> None:
            with httpx.Client(timeout=300) as http:
                k = i
                while time.monotonic() < stop:
                    reply = http.post(server.url + wire.EVALUATE_PATH.format(name=names[k % len(names)]), content=body,
                                      headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
                    (answered if reply.status_code == 200 else refused)[0] += 1
                    k += 1

        threads = [threading.Thread(target=client, args=(i,)) for i in range(args.clients)]
        for thread in threads:
            thread.start()
        peak = ready
        while any(thread.is_alive() for thread in threads):
            peak = max(peak, server.rss_bytes() / 2**20)
            time.sleep(0.5)
        after = []
        for wait in (1, 2, 3):  # 1, 3 and 6 s after
            time.sleep(wait)
            after.append(server.rss_bytes() / 2**20)
        print(f"fullload: {folder} ({len(names)} materials), {args.clients} clients of 2M-query requests for "
              f"{args.seconds:g} s ({answered[0]} answered, {refused[0]} refused), server env {env or 'none'}: "
              f"RSS ready {ready:.0f} MiB, peak {peak:.0f}, after 1 / 3 / 6 s "
              f"{' / '.join(f'{a:.0f}' for a in after)} MiB")
    finally:
        server.stop(30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sections", default="startup,lru")
    parser.add_argument("--folders", default="models", help="section folders: comma-separated model folders")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--model", type=Path, default=Path("models/rock.onnx"))
    parser.add_argument("--count", type=int, default=200)
    parser.add_argument("--materials", type=int, default=20)
    parser.add_argument("--budget-models", type=int, default=4)
    parser.add_argument("--clients", type=int, default=8)
    parser.add_argument("--requests", type=int, default=25)
    parser.add_argument("--seconds", type=float, default=25.0, help="fullload: how long the clients send")
    parser.add_argument("--server-env", nargs="*", default=[], metavar="KEY=VALUE", help="fullload: server settings")
    parser.add_argument("--arena-worker", choices=ARENAS, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.arena_worker:
        return arena_worker(args.arena_worker, Path(args.folders.split(",")[0]), 3)
    with tempfile.TemporaryDirectory() as tmp:
        for section in args.sections.split(","):
            sections = {"startup": startup, "lru": lru, "folders": folders, "arena": arena, "fullload": fullload}
            sections[section](args, Path(tmp))


if __name__ == "__main__":
    main()
