"""Benchmark: the Docker image as `docker compose up` runs it - what its build sends and weighs, how soon it is ready,
what it holds idle and after serving, and whether compose's memory limit holds at full load.

Needs a Docker engine and the image (`docker/smoke.sh` builds it as ``neumip-server:local``). Sections:
- ``image``: the build context the root ``.dockerignore`` admits (what the classic builder says it sends), and the
  image's size.
- ``start``: ``--rounds`` containers over the image's models, each timed from ``docker run`` to
  ``/v2/health/ready`` answering 200; `docker stats`' memory 3 s after readiness (idle) and after one 65,536-query
  msgpack request to each material (warm).
- ``load``: one container under compose's memory limit (``--limit``, compose.yaml's default) and its settings, and
  ``--clients`` clients that for ``--seconds`` send the largest request a client may (``NEUMIP_MAX_ROWS`` queries,
  msgpack; every fourth as v2 asking for a JSON answer), read each answer and send again: the body, queue and answer
  budgets stay spent. Printed: answers by status, the cgroup's peak memory against the limit, whether the kernel
  killed anything (OOM), restarts, and the memory after.
- ``speed``: queries/s through a container of each image (``--image A,B``), beside the in-process engines
  (`speed`). Not in the default sections.

    .venv/bin/python benchmarks/bench_docker.py --rounds 3
    .venv/bin/python benchmarks/bench_docker.py --sections load --clients 16 --seconds 60
    .venv/bin/python benchmarks/bench_docker.py --sections speed --image neumip-server:ort,neumip-server:local --rounds 5
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

from neumip.core import wire
from neumip.core.contract import random_queries
from neumip.server.process import ServerProcess
from neumip.server.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
IMAGE = "neumip-server:local"
"""The image compose builds; ``--image`` names another (one built from an older commit, say)."""


def docker(*args: str, check: bool = True, **kw) -> str:
    return subprocess.run(["docker", *args], capture_output=True, text=True, check=check, **kw).stdout.strip()


def mib(text: str) -> float:
    """'123.4MiB' (the first figure of `docker stats`' MemUsage) -> MiB."""
    number, unit = re.match(r"([\d.]+)\s*([KMG]i?B)", text).groups()
    return float(number) * {"KiB": 1 / 1024, "MiB": 1, "GiB": 1024, "kB": 1 / 1024, "MB": 1, "GB": 1024}[unit]


def stats_mib(name: str) -> float:
    """The container's memory as `docker stats` reports it (the cgroup's use less the page cache)."""
    return mib(docker("stats", "--no-stream", "--format", "{{.MemUsage}}", name))


def cgroup_file(name: str, leaf: str) -> Path:
    """A file of the container's memory cgroup (v1: memory.max_usage_in_bytes, memory.failcnt)."""
    full = docker("inspect", "-f", "{{.Id}}", name)
    for path in (Path("/sys/fs/cgroup/memory/docker") / full / leaf, Path("/sys/fs/cgroup/system.slice") /
                 f"docker-{full}.scope" / leaf):
        if path.exists():
            return path
    raise FileNotFoundError(f"no cgroup file {leaf} for {name}")


class Container:
    """``docker run`` of the image on a network of its own (an engine run with --bridge=none has no default),
    published on loopback, ready when /v2/health/ready answers."""

    def __init__(self, image: str, tag: str, limit: str, env: dict[str, str] | None = None) -> None:
        self.name = f"neumip-bench-{tag}-{os.getpid()}"
        docker("network", "create", self.name)
        envs = [part for k, v in (env or {}).items() for part in ("-e", f"{k}={v}")]
        command = ["docker", "run", "--rm", "--name", self.name, "--network", self.name, "--memory", limit,
                   "--memory-swap", limit, *envs, "-p", "127.0.0.1:{port}:8000", image]
        start = time.perf_counter()
        self.server = ServerProcess.start(ROOT / "models", None, command=command, timeout_s=180)
        self.ready_s = time.perf_counter() - start
        self.url = self.server.url

    def evaluate(self, material: str, q: np.ndarray) -> None:
        httpx.post(self.url + wire.EVALUATE_PATH.format(name=material), content=wire.encode_request(q),
                   headers={"content-type": wire.MSGPACK_MEDIA_TYPE}, timeout=300).raise_for_status()

    def materials(self) -> list[str]:
        return [m["name"] for m in httpx.post(self.url + "/v2/repository/index", json={"ready": True}).json()]

    def stop(self) -> None:
        try:
            self.server.stop(60)
        finally:
            docker("rm", "-f", self.name, check=False)
            docker("network", "rm", self.name, check=False)


def image(args) -> None:
    out = subprocess.run(["docker", "build", "-f-", "."], input="FROM scratch\n", cwd=ROOT, capture_output=True,
                         text=True, env={**os.environ, "DOCKER_BUILDKIT": "0"})
    sent = re.search(r"Sending build context to Docker daemon\s+([\d.]+\s*[kMG]?B)", out.stdout + out.stderr)
    wheels = sum(p.stat().st_size for p in (ROOT / "docker" / "wheels").glob("*.whl"))
    size = int(docker("image", "inspect", "-f", "{{.Size}}", args.image))
    print(f"image: build context {sent.group(1) if sent else '?'} (the classic builder's count; "
          f"{wheels / 1e6:.1f} MB of it docker/wheels/); {args.image} {size / 1e6:.0f} MB")


def start(args) -> None:
    q = random_queries(65536, seed=1)
    ready, idle, warm = [], [], []
    for i in range(args.rounds):
        box = Container(args.image, f"start{i}", args.limit)
        try:
            ready.append(box.ready_s)
            time.sleep(3)
            idle.append(stats_mib(box.name))
            for material in box.materials():
                box.evaluate(material, q)
            warm.append(stats_mib(box.name))
        finally:
            box.stop()

    def spread(v: list, unit: str, f: str) -> str:
        return f"{np.median(v):{f}} {unit} ({min(v):{f}}-{max(v):{f}})"

    print(f"start: {args.image}, {args.rounds} containers; ready after `docker run` {spread(ready, 's', '.2f')}; "
          f"memory idle "
          f"{spread(idle, 'MiB', '.0f')}, after a 65,536-query request to each material {spread(warm, 'MiB', '.0f')}")


def load(args) -> None:
    settings = Settings()
    rows = settings.max_rows
    q = random_queries(rows, seed=2)
    binary = wire.encode_request(q)
    v2_headers, parts = wire.encode_infer_request(q, binary_output=False)
    v2_body = b"".join(parts)
    box = Container(args.image, "load", args.limit)
    statuses, errors = Counter(), Counter()
    stop = time.monotonic() + args.seconds
    materials = box.materials()

    def client(k: int) -> None:
        with httpx.Client(timeout=600) as http:
            n = 0
            while time.monotonic() < stop:
                material = materials[(k + n) % len(materials)]
                try:
                    if (k + n) % 4 == 3:
                        r = http.post(box.url + wire.INFER_PATH.format(name=material), content=v2_body,
                                      headers=v2_headers)
                    else:
                        r = http.post(box.url + wire.EVALUATE_PATH.format(name=material), content=binary,
                                      headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
                    statuses[r.status_code] += 1
                    if r.status_code == 503:
                        time.sleep(0.2)
                except httpx.HTTPError as exc:
                    errors[type(exc).__name__] += 1
                n += 1

    try:
        before = stats_mib(box.name)
        threads = [threading.Thread(target=client, args=(k,)) for k in range(args.clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        peak = int(cgroup_file(box.name, "memory.max_usage_in_bytes").read_text()) / 2**20
        failcnt = int(cgroup_file(box.name, "memory.failcnt").read_text())
        oom, restarts = docker("inspect", "-f", "{{.State.OOMKilled}} {{.RestartCount}}", box.name).split()
        time.sleep(2)
        after = stats_mib(box.name)
    finally:
        box.stop()
    print(f"load: {args.clients} clients x {args.seconds:.0f} s of {rows:,}-query requests (msgpack; every fourth v2 "
          f"with a JSON answer), limit {args.limit}: answers {dict(sorted(statuses.items()))}, client errors "
          f"{dict(errors) or 0}; memory {before:.0f} MiB before, cgroup peak {peak:.0f} MiB (page cache included; "
          f"limit hits {failcnt}), {after:.0f} after; OOM-killed {oom}, restarts {restarts}")


def speed(args) -> None:
    """Queries/s through a container of each image (``--image A,B``: msgpack requests of 2^``--batch`` random
    queries to ``--material``, one client), in interleaved rounds beside the in-process kernel engine and ONNX
    Runtime on the same queries and the image's models (``models/``); medians of the rounds, and each one's ratio
    to the in-process kernel engine, per round."""
    import statistics

    from neumip.client.http import ClientConfig, MaterialClient
    from neumip.engines.kernel import KernelMaterials
    from neumip.engines.local import LocalMaterials

    q, material = random_queries(1 << args.batch, seed=3), args.material
    kernel, local = KernelMaterials(ROOT / "models"), LocalMaterials(ROOT / "models")
    fns = {"in process, kernel": lambda: kernel.evaluate(material, q),
           "in process, onnxruntime": lambda: local.evaluate(material, q)}
    boxes, clients = [], []
    try:
        for i, name in enumerate(args.image.split(",")):
            boxes.append(Container(name, f"speed{i}", args.limit))
            clients.append(MaterialClient(boxes[-1].url, ClientConfig(timeout_s=300)))
            platform = httpx.get(f"{boxes[-1].url}/v2/models/{material}").json()["platform"]
            fns[f"{name} ({platform})"] = lambda c=clients[-1]: c.evaluate(material, q)
        rates = {key: [] for key in fns}
        for fn in fns.values():
            fn()  # warm
        for _ in range(args.rounds):
            for key, fn in fns.items():
                calls, start = 0, time.perf_counter()
                while time.perf_counter() - start < args.seconds_a_round:
                    fn()
                    calls += 1
                rates[key].append(calls * len(q) / (time.perf_counter() - start))
    finally:
        for client in clients:
            client.close()
        for box in boxes:
            box.stop()
    base = rates["in process, kernel"]
    print(f"speed: {material}, {len(q):,} single queries a call, {args.rounds} interleaved rounds")
    for key, values in rates.items():
        ratio = statistics.median(v / b for v, b in zip(values, base))
        print(f"  {key:58s} {statistics.median(values) / 1e6:6.2f} M q/s  {ratio:5.2f}x the in-process kernel engine")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sections", default="image,start,load")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--limit", default=os.environ.get("NEUMIP_MEMORY_LIMIT", "2g"),
                        help="the container's memory limit (compose.yaml's default)")
    parser.add_argument("--clients", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=45.0)
    parser.add_argument("--image", default=IMAGE, help="the image; for --sections speed, several as A,B")
    parser.add_argument("--material", default="rock", help="the material --sections speed asks")
    parser.add_argument("--batch", type=int, default=17, help="--sections speed: 2^batch queries a request")
    parser.add_argument("--seconds-a-round", type=float, default=2.0, help="--sections speed: seconds per engine a round")
    args = parser.parse_args()
    for section in args.sections.split(","):
        {"image": image, "start": start, "load": load, "speed": speed}[section](args)


if __name__ == "__main__":
    main()
