"""Inference server speed over loopback: msgpack (/v1) and Open Inference Protocol binary (/v2)
throughput against in-process ONNX Runtime, for plain queries and for query groups of two lights (what
the renderer sends: (N, 9) in, (N, 6) out), latency under 1/4/16 concurrent clients, 16-row latency
with and without a slow uploader, a 10^6-query request, and the server's resident memory before and
after the load.

    .venv/bin/python benchmarks/bench_server.py                    # about 2 minutes
    .venv/bin/python benchmarks/bench_server.py --model models/foo.onnx --rows 65536 --rounds 9
    .venv/bin/python benchmarks/bench_server.py --engine kernel    # the kernel engine, throughput only

Starts a real `neumip serve` process on 127.0.0.1 (default settings unless NEUMIP_* variables say
otherwise) and talks to it from this process, so client-side encoding and decoding are part of every
end-to-end figure. msgpack goes through the product client, `MaterialClient` (one kept-alive
httpx.Client); v2 through `MaterialClient(protocol="v2")` and through tritonclient. The default model is the default `MaterialConfig` (256^2, neural offset) with
random weights, as in bench_inference.py (speed does not depend on training); `--model` takes an
exported file, e.g. one of `models/`. In-process = `LocalMaterials`
with its defaults (a worker per core). Other jobs share this machine's cores: the throughput table
interleaves in-process, msgpack and v2 round by round and reports medians and the median per-round
ratio; read the load average printed with it.

``--split-cores`` (kernel engine) puts the server on half of the cores and this process on the other half,
so that the in-process base and the server have as many cores each and the clients' work is not the
server's: the server's own cost, as where it has a machine or container of its own. The halves swap
every other round, so that a core slower than the other for a while counts against both sides alike.

With ``--engine kernel`` the server runs ``NEUMIP_ENGINE=kernel`` (drjit LLVM kernels) and the in-process
base is the same engine, `KernelMaterials.evaluate` (one call at a time: drjit spreads each call over
every core; in-process ONNX Runtime, `LocalMaterials`, is printed beside it for scale). It prints only
the throughput table, at ``--kernel-rows`` queries a request, for 1 and
``--clients-kernel`` concurrent clients (each its own kept-alive `MaterialClient`, as a renderer's
evaluation threads would send); in process, the same queries are evaluated one request after another
in this process. Server and client share this machine's cores; each measurement starts after a pause
(`SETTLE_S`) in which both processes' drjit workers stop spinning. Beside each figure: the CPU time per
request of this process (the client, or in-process evaluation) and of the server process, split into its
main thread (the event loop: HTTP, decoding, encoding) and the others (the batcher's worker and drjit's
pool); in 10 ms ticks, so read them as medians of coarse samples. They say where the time goes.
Beside the server runs `bare_server.py`, the HTTP floor: a bare uvicorn app that reads, decodes and
checks each request and answers zeros, without evaluating (rows ``bare uvicorn``); with ``--split-cores``
the table ends with the bound that floor sets: in-process CPU / (engine CPU + bare loop CPU).
"""

from __future__ import annotations

import argparse
import functools
import os
import socket
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from neumip.core import contract as C
from neumip.core import wire
from neumip.client.http import ClientConfig, MaterialClient, ServerError
from neumip.engines.local import LocalMaterials
from neumip.server.process import ServerProcess
from neumip.server.uvicorn_run import ServeError


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", type=Path, help="an exported .onnx material (default: 256^2 random, see above)")
    p.add_argument("--rows", type=int, default=1 << 16, help="queries per throughput request")
    p.add_argument("--rounds", type=int, default=7, help="interleaved throughput rounds")
    p.add_argument("--latency-rows", type=int, default=4096, help="queries per request in the latency runs")
    p.add_argument("--latency-seconds", type=float, default=6.0, help="duration of each latency run")
    p.add_argument("--clients", default="1,4,16", help="concurrent clients of the latency runs")
    p.add_argument("--big", type=int, default=1_000_000, help="queries of the single large request")
    p.add_argument("--big-rounds", type=int, default=3, help="interleaved rounds of the large request")
    p.add_argument("--engine", choices=("onnxruntime", "kernel"), default="onnxruntime", help="the server's engine")
    p.add_argument("--kernel-rows", default="65536,262144", help="queries per request with --engine kernel")
    p.add_argument("--clients-kernel", type=int, default=2, help="concurrent clients with --engine kernel")
    p.add_argument("--split-cores", action="store_true",
                   help="with --engine kernel: the server on one half of this machine's cores, the clients "
                   "and the in-process base on the other (as on a server with cores of its own); the halves "
                   "swap every other round")
    return p.parse_args()




def model_folder(args: argparse.Namespace, scratch: Path) -> tuple[Path, str]:
    """A folder holding just the benchmark model, and the model's name."""
    folder = scratch / "models"
    folder.mkdir()
    if args.model is not None:
        (folder / args.model.name).symlink_to(args.model.resolve())
        return folder, args.model.stem
    from neumip.core.config import MaterialConfig
    from neumip.training.export.graph import build_onnx, random_weights, save_onnx

    config = MaterialConfig()
    save_onnx(build_onnx(config, random_weights(config, seed=0), "benchmark: 256^2, random weights"), folder / "bench256.onnx")
    return folder, "bench256"


def pin(pid: int, cores: set[int]) -> None:
    """Move every thread of process `pid` onto `cores` (threads it starts later inherit them)."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            os.sched_setaffinity(int(task.name), cores)
        except OSError:  # a thread that ended meanwhile
            pass


class Server:
    """A `neumip serve` process on a free loopback port."""

    def __init__(self, folder: Path, log: Path, engine: str = "onnxruntime", cores: set[int] | None = None,
                 bare: bool = False, shared_memory: bool = False) -> None:
        """`bare`: not `neumip serve` but the HTTP floor, `bare_server` (evaluates nothing); `shared_memory`: clients
        may pass their rows through shared memory (``NEUMIP_ALLOW_SHARED_MEMORY``)."""
        command = None
        if bare:
            command = [sys.executable, "-m", "uvicorn", "bare_server:app", "--app-dir", str(Path(__file__).parent),
                       "--port", "{port}", "--loop", "uvloop", "--http", "httptools", "--log-level", "warning",
                       "--no-access-log"]
        try:
            self.server = ServerProcess.start(folder, log, command=command, cores=cores, engine=engine,
                                              **({"allow_shared_memory": "true"} if shared_memory else {}))
        except ServeError as exc:
            sys.exit(str(exc))
        self.url, self.process = self.server.url, self.server.process

    def pin(self, cores: set[int]) -> None:
        pin(self.process.pid, cores)

    def rss_mib(self) -> float:
        return self.server.rss_bytes() / 2**20

    def cpu_s(self) -> tuple[float, float]:
        """CPU seconds (user + system) the server's main thread (the event loop: HTTP, decoding,
        encoding) and its other threads (the engine's workers, drjit's pool) have used."""
        loop = other = 0.0
        for task in Path(f"/proc/{self.process.pid}/task").iterdir():
            try:
                fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:  # a thread that ended meanwhile
                continue
            seconds = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            if task.name == str(self.process.pid):
                loop += seconds
            else:
                other += seconds
        return loop, other

    def stop(self) -> int:
        return self.server.stop()


def msgpack_call(client: MaterialClient, name: str, q: np.ndarray, stages: dict | None = None) -> np.ndarray:
    """One evaluation through the product client (`MaterialClient`: keep-alive http.client)."""
    rgb = client.evaluate(name, q)
    if stages is not None:  # the server's own stage durations (Server-Timing header, ms)
        for stage, ms in client.server_timing.items():
            stages.setdefault(stage, []).append(ms)
    return rgb


def v2_call(triton_client, name: str, q: np.ndarray) -> np.ndarray:
    import tritonclient.http as triton

    tensor = triton.InferInput(C.ONNX_INPUT, list(q.shape), "FP32")
    tensor.set_data_from_numpy(q, binary_data=True)
    out = triton.InferRequestedOutput(C.ONNX_OUTPUT, binary_data=True)
    return triton_client.infer(name, [tensor], outputs=[out]).as_numpy(C.ONNX_OUTPUT)


def pairs(pool: np.ndarray) -> np.ndarray:
    """(N, 9) query groups of two lights: each query of `pool` and the wi of another one."""
    other = np.roll(pool, len(pool) // 2, axis=0)[:, C.WI_X:C.WI_Y + 1]
    return np.ascontiguousarray(np.hstack([pool, other]))


def throughput(args, name, local, client, v2_client, triton_client, pool) -> None:
    """Plain queries and groups of two lights, in the same interleaved rounds; each path's ratio is to
    in-process evaluation of the same buffers."""
    n = args.rows
    batches = [pool[i * n : (i + 1) * n] for i in range(len(pool) // n)]
    groups = [pairs(b) for b in batches]  # n shading points, 2 n answers a request
    stages: dict[str, list[float]] = {}
    kinds = {  # label: (evaluate, buffers, label of its in-process base)
        "in-process (LocalMaterials)": (lambda q: local.evaluate(name, q), batches, None),
        "msgpack /v1 (MaterialClient)": (lambda q: msgpack_call(client, name, q, stages), batches, None),
        "v2 binary (MaterialClient)": (lambda q: v2_client.evaluate(name, q), batches, None),
        "v2 binary (tritonclient)": (lambda q: v2_call(triton_client, name, q), batches, None),
        "in-process, groups of 2": (lambda q: local.evaluate(name, q), groups, "in-process, groups of 2"),
        "msgpack /v1, groups of 2": (lambda q: msgpack_call(client, name, q), groups,
                                     "in-process, groups of 2"),
    }
    for fn, buffers, _ in kinds.values():  # warm-up
        fn(buffers[0])
    times = {k: [] for k in kinds}
    for r in range(args.rounds):
        for kind, (fn, buffers, _) in kinds.items():
            q = buffers[(r + 1) % len(buffers)]
            start = time.perf_counter()
            fn(q)
            times[kind].append(time.perf_counter() - start)
    print(f"\n## Throughput, {n} queries (or groups of two lights: {2 * n} answers) per request "
          f"({args.rounds} interleaved rounds; load avg {os.getloadavg()[0]:.2f})")
    print(f"{'path':32s} {'median ms':>10s} {'M answers/s':>12s} {'vs in-process':>14s}")
    for kind, (_, buffers, base_kind) in kinds.items():
        ts, base = times[kind], times[base_kind or "in-process (LocalMaterials)"]
        answers = n * C.group_lights(buffers[0].shape[1])
        ratio = statistics.median(b / t for b, t in zip(base, ts))
        median = statistics.median(ts)
        print(f"{kind:32s} {median * 1e3:10.1f} {answers / median / 1e6:12.3f} {ratio:13.0%}")
    parts = ", ".join(f"{stage} {statistics.median(ms):.1f}" for stage, ms in stages.items())
    print(f"MaterialClient server-side stages, median ms (Server-Timing): {parts}; the rest is HTTP and the client")


def latency(args, name, server, pool) -> None:
    n = args.latency_rows
    print(f"\n## Latency, {n} queries per msgpack request, each client back to back for {args.latency_seconds:.0f} s")
    print(f"{'clients':>7s} {'requests':>9s} {'p50 ms':>8s} {'p99 ms':>8s} {'Mq/s':>7s} {'errors':>7s}")
    for clients in (int(c) for c in args.clients.split(",")):
        samples: list[list[float]] = [[] for _ in range(clients)]
        errors = [0] * clients

        def client(i: int) -> None:
            rng = np.random.default_rng(i)
            deadline = time.monotonic() + args.latency_seconds
            with MaterialClient(server.url, ClientConfig(timeout_s=60, retries=0)) as http:
                while time.monotonic() < deadline:
                    lo = int(rng.integers(0, len(pool) - n))
                    start = time.perf_counter()
                    try:
                        msgpack_call(http, name, pool[lo : lo + n])
                    except ServerError:
                        errors[i] += 1
                        continue
                    samples[i].append(time.perf_counter() - start)

        start = time.perf_counter()
        threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - start
        lat = np.array([s for per in samples for s in per]) * 1e3
        print(f"{clients:7d} {lat.size:9d} {np.percentile(lat, 50):8.1f} {np.percentile(lat, 99):8.1f} "
              f"{lat.size * n / wall / 1e6:7.3f} {sum(errors):7d}")


def p50_16_rows(url: str, name: str, pool, beside_upload: bool, requests: int = 100) -> float:
    """p50 (ms) of `requests` 16-row requests, optionally while a slow upload is in progress."""
    body = wire.encode_request(pool[:16])
    stop = threading.Event()

    def upload() -> None:
        host, port = url.split("://")[1].split(":")
        with socket.create_connection((host, int(port)), timeout=30) as sock:
            sock.sendall(f"POST {wire.EVALUATE_PATH.format(name=name)} HTTP/1.1\r\nHost: x\r\nContent-Type: "
                         f"{wire.MSGPACK_MEDIA_TYPE}\r\nContent-Length: {len(body)}\r\n\r\n".encode())
            for i in range(len(body) - 1):  # never the last byte: the upload lasts the whole run
                if stop.wait(0.01):
                    return
                sock.sendall(body[i : i + 1])

    uploader = threading.Thread(target=upload)
    if beside_upload:
        uploader.start()
        time.sleep(0.1)
    times = []
    try:
        with MaterialClient(url) as client:
            for i in range(requests):
                start = time.perf_counter()
                client.evaluate(name, pool[16 * i : 16 * i + 16])
                times.append(time.perf_counter() - start)
    finally:
        stop.set()
        if beside_upload:
            uploader.join()
    return statistics.median(times) * 1e3


def slow_uploader(args, name, server, pool, rounds: int = 200) -> None:
    """16-row request latency alone, then while another client uploads a body one byte every 10 ms."""
    alone = p50_16_rows(server.url, name, pool, False, rounds)
    beside = p50_16_rows(server.url, name, pool, True, rounds)
    print(f"\n## 16-row requests, p50 of {rounds}: {alone:.2f} ms alone, {beside:.2f} ms beside a slow uploader "
          f"(load avg {os.getloadavg()[0]:.2f})")


def big_request(args, name, local, client, triton_client) -> None:
    q = C.random_queries(args.big, seed=7)
    expected = LocalMaterials(local.folder, threads=1).evaluate(name, q)
    kinds = {
        "in-process": lambda: local.evaluate(name, q),
        "msgpack /v1": lambda: msgpack_call(client, name, q),
        "v2 binary": lambda: v2_call(triton_client, name, q),
    }
    times, identical = {k: [] for k in kinds}, {}
    for _ in range(args.big_rounds):
        for kind, fn in kinds.items():
            start = time.perf_counter()
            rgb = fn()
            times[kind].append(time.perf_counter() - start)
            identical[kind] = np.array_equal(rgb, expected)
    print(f"\n## One request of {args.big} queries ({q.nbytes / 1e6:.0f} MB in, {expected.nbytes / 1e6:.0f} MB out), "
          f"{args.big_rounds} interleaved rounds; load avg {os.getloadavg()[0]:.2f}")
    print(f"{'path':12s} {'median s':>9s} {'max s':>6s}  bit-identical to in-process with 1 worker")
    for kind, ts in times.items():
        print(f"{kind:12s} {statistics.median(ts):9.2f} {max(ts):6.2f}  {identical[kind]}")


def process_cpu_s() -> float:
    """CPU seconds (user + system) this process has used."""
    times = os.times()
    return times.user + times.system


MEASURED_QUERIES = 1 << 20
"""Queries per client in one kernel-engine measurement: smaller requests are sent several times back to
back (a renderer's stream of bounces), so a measurement is not one cold call after the pause."""
SETTLE_S = 0.1
"""Pause before each kernel-engine measurement: drjit's worker threads spin for tens of milliseconds after
a call before they sleep, so without it the in-process run would take CPU from the server run after it
(this process's workers) and the server from the in-process run (the server's)."""


def kernel_throughput(args, name, folder, server, bare, pool, swap=None) -> None:
    """The kernel engine: msgpack /v1 and v2 against in-process `KernelMaterials.evaluate`, plain queries
    and groups of two lights, 1 and ``--clients-kernel`` clients, in the same interleaved rounds; and the
    HTTP floor, `bare` (`bare_server`), sent the same msgpack requests. `swap(round)`, if given, places
    the processes on their cores before each round."""
    from concurrent.futures import ThreadPoolExecutor

    from neumip.engines.kernel import KernelMaterials

    kernel = KernelMaterials(folder)
    config = ClientConfig(timeout_s=120)
    width = args.clients_kernel
    msgpack = [MaterialClient(server.url, config) for _ in range(width)]
    v2 = [MaterialClient(server.url, config, protocol="v2") for _ in range(width)]
    floor = [MaterialClient(bare.url, config) for _ in range(width)]
    pool_threads = ThreadPoolExecutor(width)

    def at_once(clients, requests) -> None:
        """Each client sends its request; all at the same time."""
        for future in [pool_threads.submit(c.evaluate, name, q) for c, q in zip(clients, requests)]:
            future.result()

    def in_process(requests) -> None:
        for q in requests:
            kernel.evaluate(name, q)

    local = LocalMaterials(folder)

    def onnxruntime(requests) -> None:
        for q in requests:
            local.evaluate(name, q)

    for n in (int(r) for r in args.kernel_rows.split(",")):
        batches = [pool[i * n : (i + 1) * n] for i in range(len(pool) // n)]
        # label: (evaluate a list of requests, how many at once, groups?, its in-process base (None: no
        # ratio), the server process whose CPU time is read)
        kinds = {}
        for groups in (False, True):
            tag = ", groups of 2" if groups else ""
            for clients in sorted({1, width}):
                base = f"in-process x{clients}{tag}"
                kinds[base] = (in_process, clients, groups, base, server)
                if clients == 1:  # the ONNX Runtime engine in process, for scale
                    kinds[f"in-process ONNX Runtime x1{tag}"] = (onnxruntime, 1, groups, base, server)
                for path, senders, process in (("msgpack /v1", msgpack, server), ("v2 binary", v2, server),
                                               ("bare uvicorn /v1", floor, bare)):  # the floor: no ratio
                    send = functools.partial(at_once, senders[:clients])
                    ratio_to = base if process is server else None
                    kinds[f"{path} x{clients}{tag}"] = (send, clients, groups, ratio_to, process)

        def requests(round_: int, clients: int, groups: bool) -> list[np.ndarray]:
            picked = [batches[(round_ + j) % len(batches)] for j in range(clients)]
            return [pairs(b) for b in picked] if groups else picked

        repeat = max(1, MEASURED_QUERIES // n)  # request sets back to back in one measurement
        cached = {}
        for kind, (fn, clients, groups, *_) in kinds.items():  # warm-up (traces the frozen calls)
            cached[clients, groups] = {r: requests(r, clients, groups) for r in range(-1, repeat)}
            fn(cached[clients, groups][-1])
        times, cpu = {k: [] for k in kinds}, {k: [] for k in kinds}
        for r in range(args.rounds):
            if swap is not None:
                swap(r)
            for kind, (fn, clients, groups, _, process) in kinds.items():
                time.sleep(SETTLE_S)
                start, own, served = time.perf_counter(), process_cpu_s(), process.cpu_s()
                for j in range(repeat):
                    fn(cached[clients, groups][(r + j) % repeat])
                times[kind].append((time.perf_counter() - start) / repeat)
                now = process.cpu_s()
                cpu[kind].append([(process_cpu_s() - own) / repeat] + [(b - a) / repeat for a, b in zip(served, now)])
        print(f"\n## Kernel engine throughput, {n} queries (or groups of two lights: {2 * n} answers) per request, "
              f"xC: C clients at once, each sending {repeat} back to back per measurement ({args.rounds} interleaved "
              f"rounds; load avg {os.getloadavg()[0]:.2f}); times per request set")
        print(f"{'path':40s} {'median ms':>10s} {'M answers/s':>12s} {'vs in-process':>14s} "
              f"{'CPU ms/request: client':>23s} {'server loop':>12s} {'engine':>7s}")
        for kind, (_, clients, groups, base, _) in kinds.items():
            ts = times[kind]
            answers = n * clients * (2 if groups else 1)
            ratio = " " * 12 + "-"
            if base:
                ratio = f"{statistics.median(b / t for b, t in zip(times[base], ts)):13.0%}"
            median = statistics.median(ts)
            own, loop, engine = (statistics.median(c[i] for c in cpu[kind]) * 1e3 / clients for i in range(3))
            print(f"{kind:40s} {median * 1e3:10.1f} {answers / median / 1e6:12.3f} {ratio} "
                  f"{own:23.1f} {loop:12.1f} {engine:7.1f}")
        print("bare uvicorn: the HTTP floor (bare_server.py: read, decode and check each request, answer "
              "zeros; no evaluation).")
        if swap is None:  # on shared cores CPU time is not wall time (drjit's workers spin): no bound from it
            continue
        print("A server whose event loop cost only that, with the engine's CPU above, would be at most "
              "in-process CPU / (engine CPU + bare loop CPU) of in-process (CPU medians, a core a side):")
        for groups in (False, True):
            tag = ", groups of 2" if groups else ""
            cpu_of = lambda kind, i: statistics.median(c[i] for c in cpu[kind])  # noqa: E731
            base, served = f"in-process x1{tag}", f"msgpack /v1 x1{tag}"
            bound = cpu_of(base, 0) / (cpu_of(served, 2) + cpu_of(f"bare uvicorn /v1 x1{tag}", 1))
            now = cpu_of(base, 0) / (cpu_of(served, 2) + cpu_of(served, 1))
            print(f"  x1{tag}: at most {bound:.0%} (with the server's own event loop: {now:.0%})")
    for client in msgpack + v2 + floor:
        client.close()
    pool_threads.shutdown()


def main() -> None:
    args = parse_args()
    if args.engine == "kernel":
        with tempfile.TemporaryDirectory() as scratch:
            folder, name = model_folder(args, Path(scratch))
            print(f"model {name} ({folder / (name + '.onnx')}), {os.cpu_count()} CPUs, server engine kernel")
            cores = sorted(os.sched_getaffinity(0))
            half = len(cores) // 2
            halves = (set(cores[:half]), set(cores[half : 2 * half]))  # this process's, the servers'
            server_cores = halves[1] if args.split_cores else None
            server = Server(folder, Path(scratch) / "server.log", engine="kernel", cores=server_cores)
            try:
                bare = Server(folder, Path(scratch) / "bare.log", cores=server_cores, bare=True)
            except SystemExit:
                server.stop()
                raise
            if not server_cores:
                swap = None
            else:
                import drjit as dr

                pin(os.getpid(), halves[0])
                dr.set_thread_count(half)  # as the servers size their pools

                def swap(round_: int) -> None:
                    """Even rounds as at the start, odd ones with the halves swapped: one core can be slower
                    than another for a while (another tenant on its sibling), which must not count against
                    one side."""
                    mine, theirs = halves if round_ % 2 == 0 else halves[::-1]
                    pin(os.getpid(), mine)  # every thread: the clients' pool, ONNX Runtime's, drjit's
                    server.pin(theirs)
                    bare.pin(theirs)

                print(f"split cores: the servers on {sorted(halves[1])}, this process (clients and "
                      f"in-process evaluation) on {sorted(halves[0])}; swapped every other round")
            try:
                pool = C.random_queries(max(max(int(r) for r in args.kernel_rows.split(",")) * 4, 1 << 18))
                kernel_throughput(args, name, folder, server, bare, pool, swap)
            finally:
                bare.stop()  # uvicorn itself: it ends by re-raising SIGTERM
                print(f"server stopped with SIGTERM, exit status {server.stop()}")
        return
    import tritonclient.http as triton

    with tempfile.TemporaryDirectory() as scratch:
        folder, name = model_folder(args, Path(scratch))
        print(f"model {name} ({folder / (name + '.onnx')}), {os.cpu_count()} CPUs")
        server = Server(folder, Path(scratch) / "server.log")
        try:
            local = LocalMaterials(folder)
            pool = C.random_queries(max(args.rows * 4, 1 << 18))
            rss_start = server.rss_mib()
            with MaterialClient(server.url, ClientConfig(timeout_s=120)) as client, \
                    MaterialClient(server.url, ClientConfig(timeout_s=120), protocol="v2") as v2_client:
                triton_client = triton.InferenceServerClient(server.url.split("://")[1], network_timeout=120)
                throughput(args, name, local, client, v2_client, triton_client, pool)
                rss_before_load = server.rss_mib()
                latency(args, name, server, pool)
                rss_after_load = server.rss_mib()
                slow_uploader(args, name, server, pool)
                big_request(args, name, local, client, triton_client)
            print(f"\n## Server resident memory: {rss_start:.0f} MiB after start-up, {rss_before_load:.0f} MiB "
                  f"before the latency runs, {rss_after_load:.0f} MiB after them "
                  f"(growth under load {rss_after_load - rss_before_load:+.1f} MiB), {server.rss_mib():.0f} MiB at the end")
        finally:
            code = server.stop()
            print(f"server stopped with SIGTERM, exit status {code}")


if __name__ == "__main__":
    main()
