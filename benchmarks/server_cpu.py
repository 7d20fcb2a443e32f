"""Where a served request's time goes: wall time against the engine in process, and every thread's CPU a request.

    .venv/bin/python benchmarks/server_cpu.py                                  # rock, kernel engine (~1 min)
    .venv/bin/python benchmarks/server_cpu.py --batches 17 --clients 2 --server-env NEUMIP_MAX_WAIT_MS=0

Starts one `neumip serve` (``--engine``, shared memory allowed) on ``models/MODEL.onnx``. For each batch size
2^b of ``--batches`` and each ``--protocols`` entry, in interleaved rounds: one `MaterialClient` sends requests
of 2^b random queries back to back for ``--seconds``, and the same engine answers the same queries in process
(`KernelMaterials.evaluate` or `LocalMaterials.evaluate`) for as long. Each timing starts after a pause, so that
drjit's workers, which spin for 20 ms after a call (nanothread), do not take the cores of what is measured next.

Prints, per size and protocol (medians of the rounds): milliseconds a request through the server and in process,
their ratio, and CPU milliseconds a request: in process (every thread), of the client process and of each kind of
server thread, read from
``/proc``: the event loop (HTTP, decoding, checking, answering), the engine's calling threads (the batcher's
workers: the upload to the engine, the engine's share of the work, the copies back) and drjit's pool workers
(the rest of the kernel's work, and their spinning between calls). With ``--clients N`` > 1, N client processes
send at once (each its own requests): the sum of their answers a second against one in-process caller's, the
most that keeping the server busy gives. ``--server-env KEY=VALUE``: settings of the server. ``--copy-mb M``:
also the median in-process call made right after copying M MB (untimed), as the server's requests copy their rows
between its calls.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAUSE_S = 0.05
"""Pause before each timing: longer than drjit's workers spin after a call (20 ms)."""
STARTUP_S = 3.0
"""Seconds given the client processes to start (imports, a first request) before they are timed together."""


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default="rock", help="a model of --folder (default rock)")
    p.add_argument("--folder", type=Path, default=ROOT / "models")
    p.add_argument("--engine", choices=("kernel", "onnxruntime"), default="kernel")
    p.add_argument("--batches", default="0,14,17,20", help="log2 of the queries a request (comma-separated)")
    p.add_argument("--protocols", default="shm,msgpack", help="how the client sends them (comma-separated)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--seconds", type=float, default=1.0, help="each timing's length")
    p.add_argument("--clients", type=int, default=1, help="client processes sending at once")
    p.add_argument("--server-env", nargs="*", default=[], metavar="KEY=VALUE")
    p.add_argument("--copy-mb", type=float, default=0.0,
                   help="also time in-process calls each after copying this many MB (the server's copies between "
                        "calls evict the engine's data from cache)")
    return p.parse_args()


def thread_cpu_s(pid: int) -> dict[int, tuple[str, float]]:
    """{thread id: (its name, CPU seconds so far)} of process `pid`."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        except FileNotFoundError:  # the thread ended meanwhile
            continue
        fields = stat.rsplit(")", 1)[1].split()
        out[int(tid)] = (stat[stat.index("(") + 1:stat.rindex(")")], (int(fields[11]) + int(fields[12])) / tick)
    return out


def kind(pid: int, tid: int, name: str) -> str:
    """Which of the server's threads `tid` is: its event loop (the main thread), drjit's pool (``nt [i]``) or an
    engine caller (the batcher's workers, and any other thread)."""
    if tid == pid:
        return "event loop"
    return "drjit workers" if name.startswith("nt ") else "engine callers"


def client_loop(url: str, name: str, rows: int, protocol: str, seconds: float, start_at: float, out) -> None:
    """A client process: requests of `rows` queries from `start_at` (time.time) for `seconds`; puts
    (requests, seconds, CPU seconds)."""
    from neumip.client.http import ClientConfig, MaterialClient
    from neumip.core import contract as C

    queries = C.random_queries(rows, seed=os.getpid())
    with MaterialClient(url, ClientConfig(timeout_s=300), protocol=protocol) as client:
        client.evaluate(name, queries)  # the shared-memory regions made, the connection open
        time.sleep(max(start_at - time.time(), 0.0))
        calls, began, cpu = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - began < seconds:
            client.evaluate(name, queries)
            calls += 1
        out.put((calls, time.perf_counter() - began, time.process_time() - cpu))


def run_clients(url: str, name: str, rows: int, protocol: str, clients: int, seconds: float,
                during=lambda: None) -> tuple[int, float, float, tuple]:
    """`clients` client processes sending requests of `rows` queries at once for `seconds`: (their requests, the
    seconds they took, their CPU seconds, what `during()` gave when their timing began and when it ended)."""
    ctx = mp.get_context("spawn")
    out = ctx.Queue()
    start_at = time.time() + STARTUP_S
    procs = [ctx.Process(target=client_loop, args=(url, name, rows, protocol, seconds, start_at, out))
             for _ in range(clients)]
    for proc in procs:
        proc.start()
    time.sleep(max(start_at - time.time(), 0.0))
    first = during()
    results = [out.get() for _ in procs]
    last = during()
    for proc in procs:
        proc.join()
    return sum(r[0] for r in results), max(r[1] for r in results), sum(r[2] for r in results), (first, last)


def timed(fn, seconds: float) -> tuple[int, float, float]:
    """(calls, wall seconds, this process's CPU seconds) of `fn()` repeated for `seconds`."""
    calls, began, cpu = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - began < seconds:
        fn()
        calls += 1
    return calls, time.perf_counter() - began, time.process_time() - cpu


def after_copies(fn, megabytes: float, seconds: float) -> float:
    """Median seconds of `fn()` each run right after copying `megabytes` MB from one buffer to another (untimed)."""
    import numpy as np

    source = np.ones(int(megabytes * 2**20) // 8)
    target = np.empty_like(source)
    times, began = [], time.perf_counter()
    while time.perf_counter() - began < seconds:
        np.copyto(target, source)
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    args = parse_args()
    from neumip.core import contract as C
    from neumip.server.process import ServerProcess

    if args.engine == "kernel":
        import drjit as dr

        from neumip.engines.kernel import KernelMaterials
        from neumip.server.settings import available_cores

        dr.set_thread_count(available_cores())  # as the server's kernel engine sizes drjit's pool
        local = KernelMaterials(args.folder)
    else:
        from neumip.engines.local import LocalMaterials

        local = LocalMaterials(args.folder)
    env = {"NEUMIP_ALLOW_SHARED_MEMORY": "true", **dict(kv.split("=", 1) for kv in args.server_env)}
    with tempfile.TemporaryDirectory() as tmp:
        served = Path(tmp) / "models"
        served.mkdir()
        (served / f"{args.model}.onnx").symlink_to((args.folder / f"{args.model}.onnx").resolve())
        server = ServerProcess.start(served, Path(tmp) / "server.log", env=env, engine=args.engine)
        pid = server.process.pid
        print(f"# {args.model}, {args.engine} engine, {args.clients} client process(es), server settings {env}; "
              f"{args.rounds} rounds of {args.seconds:g} s (load avg {os.getloadavg()[0]:.2f})")
        print("queries  protocol  server ms  in-process ms  ratio | CPU ms a request: in process  client  "
              "event loop  engine callers  drjit workers  server")
        try:
            for b in map(int, args.batches.split(",")):
                queries = C.random_queries(1 << b, seed=7)
                local.evaluate(args.model, queries)
                for protocol in args.protocols.split(","):
                    rows = {k: [] for k in ("server", "local", "local cpu", "client", "event loop",
                                            "engine callers", "drjit workers", "after copies")}
                    for _ in range(args.rounds):
                        time.sleep(PAUSE_S)
                        calls, wall, cpu = timed(lambda: local.evaluate(args.model, queries), args.seconds)
                        rows["local"].append(wall / calls)
                        rows["local cpu"].append(cpu / calls)
                        if args.copy_mb:
                            rows["after copies"].append(after_copies(lambda: local.evaluate(args.model, queries),
                                                                     args.copy_mb, args.seconds))
                        requests, wall, client_cpu, (before, after) = run_clients(
                            server.url, args.model, 1 << b, protocol, args.clients, args.seconds,
                            lambda: thread_cpu_s(pid))
                        rows["server"].append(wall / requests)
                        rows["client"].append(client_cpu / requests)
                        spent = dict.fromkeys(("event loop", "engine callers", "drjit workers"), 0.0)
                        for tid, (name, cpu) in after.items():
                            spent[kind(pid, tid, name)] += cpu - before.get(tid, (name, 0.0))[1]
                        for key, value in spent.items():
                            rows[key].append(value / requests)
                    ms = {k: statistics.median(v) * 1e3 for k, v in rows.items() if v}
                    ratio = statistics.median(a / s for a, s in zip(rows["local"], rows["server"]))
                    server_cpu = ms["event loop"] + ms["engine callers"] + ms["drjit workers"]
                    copies = f"   in process after {args.copy_mb:g} MB of copies: {ms['after copies']:.3f} ms" \
                        if args.copy_mb else ""
                    print(f"2^{b:<6d} {protocol:9s} {ms['server']:9.3f} {ms['local']:14.3f} {ratio:6.3f} | "
                          f"{ms['local cpu']:28.3f} {ms['client']:7.3f} {ms['event loop']:11.3f} "
                          f"{ms['engine callers']:15.3f} {ms['drjit workers']:14.3f} {server_cpu:7.3f}{copies}",
                          flush=True)
        finally:
            server.stop()
    print(f"# load avg {os.getloadavg()[0]:.2f}", file=sys.stderr)


if __name__ == "__main__":
    main()
