"""Benchmark: a shipped model in ONNX Runtime's OpenVINO execution provider against its default CPU one.

`onnxruntime-openvino` replaces the `onnxruntime` package, so this runs in a venv of its own, with
no neumip import (random queries in the contract's layout are drawn here):

    python3 -m venv /tmp/ov && /tmp/ov/bin/pip install onnxruntime-openvino numpy
    /tmp/ov/bin/python experiments/openvino/bench_openvino.py models/rock.onnx

Prints the largest answer difference, whether OpenVINO answers a row the same in a smaller batch,
and per batch size the median over 3 interleaved rounds of M queries / wall s and / CPU s, both
providers with 2 threads in the same wheel.
"""
import sys
import time

import numpy as np
import onnxruntime as ort

path = sys.argv[1]
rng = np.random.default_rng(0)


def queries(n):
    q = np.empty((n, 7), np.float32)
    q[:, :2] = rng.random((n, 2)) * 4
    q[:, 2] = 2.0 ** rng.uniform(-8, 0, n) / 64  # sigma over all levels of a 64^2 model and finer
    for c in (3, 5):
        r = np.sqrt(rng.random(n)) * 0.99; phi = rng.random(n) * 2 * np.pi
        q[:, c], q[:, c + 1] = r * np.cos(phi), r * np.sin(phi)
    return q


def session(provider):
    o = ort.SessionOptions(); o.intra_op_num_threads = 2; o.log_severity_level = 3
    opts = [{"device_type": "CPU", "num_of_threads": "2"}] if provider == "OpenVINOExecutionProvider" else None
    return ort.InferenceSession(path, o, providers=[provider], provider_options=opts)


cpu, ov = session("CPUExecutionProvider"), session("OpenVINOExecutionProvider")
q = queries(1 << 16)
a, b = cpu.run(None, {"queries": q})[0], ov.run(None, {"queries": q})[0]
print("max |ov - cpu|", float(np.abs(a - b).max()), "max |cpu|", float(np.abs(a).max()))
half = ov.run(None, {"queries": q[:1000]})[0]
print("ov batch-cut identical:", np.array_equal(half, b[:1000]))
for n in (1 << 14, 1 << 16, 1 << 18):
    qq = queries(n); res = {}
    for rnd in range(3):
        for name, s in (("cpu", cpu), ("openvino", ov)):
            s.run(None, {"queries": qq})
            t = time.perf_counter(); c0 = time.process_time()
            for _ in range(3): s.run(None, {"queries": qq})
            res.setdefault(name, []).append((3 * n / (time.perf_counter() - t) / 1e6, 3 * n / (time.process_time() - c0) / 1e6))
    print(n, {k: (round(float(np.median([x[0] for x in v])), 2), round(float(np.median([x[1] for x in v])), 2)) for k, v in res.items()}, "(M/s wall, M/CPU-s)")
