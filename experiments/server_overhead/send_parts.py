"""A request body sent whole against in parts of 4 MiB, 1 MiB and 256 KiB (`client.http.SEND_PART_BYTES`): the
client's CPU and the wall time a request, msgpack bodies, one `neumip serve` of the kernel engine on loopback,
interleaved rounds in one client process.

    .venv/bin/python experiments/server_overhead/send_parts.py --model rock --rounds 3

httpcore sends a body part by slicing off what each socket ``send`` took, so a whole body is copied again after
every send; parts bound that copying. 2^20 queries go as two requests (28 MB and 1.4 MB: `ClientConfig.max_rows`).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="rock")
    parser.add_argument("--folder", type=Path, default=ROOT / "models")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--batches", default="17,20", help="log2 of the queries a request")
    args = parser.parse_args()
    from bench_server import Server

    from neumip.client import http
    from neumip.client.http import MaterialClient
    from neumip.core import contract as C

    sizes = {"whole": 1 << 40, "4 MiB": 4 << 20, "1 MiB": 1 << 20, "256 KiB": 256 << 10}
    with tempfile.TemporaryDirectory() as tmp:
        server = Server(args.folder, Path(tmp) / "server.log", engine="kernel")
        try:
            for bits in (int(b) for b in args.batches.split(",")):
                q = C.random_queries(1 << bits, seed=3)
                calls = max(4, (1 << 22) // (1 << bits))
                results = {k: [] for k in sizes}
                with MaterialClient(server.url, protocol="msgpack") as client:
                    for _ in range(args.rounds):
                        for label, size in sizes.items():
                            http.SEND_PART_BYTES = size
                            client.evaluate(args.model, q)
                            time.sleep(0.05)
                            cpu, wall = time.process_time(), time.perf_counter()
                            for _ in range(calls):
                                client.evaluate(args.model, q)
                            results[label].append(((time.process_time() - cpu) / calls, (time.perf_counter() - wall) / calls))
                print(f"## 2^{bits} queries a request ({q.nbytes / 1e6:.1f} MB of rows), {calls} requests a round, "
                      f"the best of {args.rounds} rounds  [load {os.getloadavg()[0]:.2f}]")
                whole = min(w for _, w in results["whole"])
                for label, v in results.items():
                    best_wall = min(w for _, w in v)
                    print(f"  {label:8s} client CPU {min(c for c, _ in v) * 1e3:6.2f} ms, wall {best_wall * 1e3:7.2f} ms a request"
                          f" ({whole / best_wall:.2f}x the requests a second of whole bodies)", flush=True)
        finally:
            server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
