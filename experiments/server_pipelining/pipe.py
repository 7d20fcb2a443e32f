"""A/B: a plane rendered through a real server, the client's requests of one call sent one at a time (`MaterialClient`) or
two in flight (a subclass sending its chunks from two threads), with the displaced geometry's render as the yardstick;
interleaved rounds in one process against one `neumip serve` of the default engine.

    .venv/bin/python experiments/server_pipelining/pipe.py MATERIAL ROUNDS
"""
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace
from concurrent.futures import ThreadPoolExecutor
import numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import bench_render as B
from bench_server import Server
from neumip.client.http import MaterialClient
from neumip.core import contract as C
args = SimpleNamespace(material=sys.argv[1], models=Path("models"), tiles=8, size=256, spp=64, max_depth=6,
                       geometry_resolution=None, rr_depth=4, server="auto", kernel_before=None, max_lanes=2**21,
                       variant=None, seed=0)
B.set_variant(None)
from neumip.client.mitsuba.render import mi
pool = ThreadPoolExecutor(2)
class Piped(MaterialClient):
    def evaluate(self, material, queries):
        queries = C.as_queries(queries, groups=True)
        n, lights = queries.shape[0], C.group_lights(queries.shape[1])
        rows = max(self.config.max_rows // lights, 1)
        if n <= rows:
            return super().evaluate(material, queries)
        parts = [(lo, min(lo + rows, n)) for lo in range(0, n, rows)]
        out = np.empty((n, C.RGB_DIM * lights), dtype=C.DTYPE)
        for (lo, hi), rgb in zip(parts, pool.map(lambda p: self._evaluate_once(material, queries[p[0]:p[1]]), parts)):
            out[lo:hi] = rgb
        return out
with tempfile.TemporaryDirectory() as tmp:
    server = Server(args.models, Path(tmp) / "server.log", engine="auto")
    try:
        with MaterialClient(server.url, protocol="msgpack") as plain, Piped(server.url, protocol="msgpack") as piped:
            scenes = B.ratio_scenes(mi, args)
            scene, ref = (mi.load_dict(scenes[name][0]) for name in ("neural, server", "reference (path)"))
            for c in (plain, piped):
                B.time_render(mi, scene, c, 64, 0, args.max_lanes)
            B.time_render(mi, ref, None, 64, 0, args.max_lanes)
            res = {"plain": [], "piped": [], "ref": []}
            for r in range(int(sys.argv[2])):
                for name, c in (("plain", plain), ("piped", piped), ("ref", None)):
                    res[name].append(B.time_render(mi, ref if c is None else scene, c, 64, r + 1, args.max_lanes)[0])
            import statistics as S
            m = {k: S.median(v) for k, v in res.items()}
            print(sys.argv[1], {k: round(v, 3) for k, v in m.items()}, "plain/ref %.2f piped/ref %.2f" % (m["plain"] / m["ref"], m["piped"] / m["ref"]))
    finally:
        server.stop()
