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
interleaved rounds: the folder's bytes, ready seconds and resident memory (median and range of the rounds).

    .venv/bin/python benchmarks/bench_loading.py                   # startup and lru
    .venv/bin/python benchmarks/bench_loading.py --sections lru --clients 8
    .venv/bin/python benchmarks/bench_loading.py --sections folders --folders OLD_MODELS,models --rounds 3
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
    ready, rss = {p: [] for p in paths}, {p: [] for p in paths}
    for _ in range(args.rounds):
        for path in paths:
            server = Server(path)
            ready[path].append(server.ready_s)
            rss[path].append(server.rss_mb())
            server.stop()
    for path in paths:
        models = sorted(path.glob("*.onnx"))
        size = sum(m.stat().st_size for m in models)
        print(f"{path}: {len(models)} models, {size / 1e6:.2f} MB; ready in {np.median(ready[path]):.2f} s "
              f"({min(ready[path]):.2f}-{max(ready[path]):.2f}), RSS {np.median(rss[path]):.0f} MiB "
              f"({min(rss[path]):.0f}-{max(rss[path]):.0f}); {args.rounds} rounds")


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
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for section in args.sections.split(","):
            {"startup": startup, "lru": lru, "folders": folders}[section](args, Path(tmp))


if __name__ == "__main__":
    main()
