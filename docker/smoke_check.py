"""Helpers of docker/smoke.sh, run with the host's Python (needs neumip[train] for `make-models`).

    python docker/smoke_check.py make-models DIR     # two small exported materials
    python docker/smoke_check.py check URL DIR       # real queries over HTTP vs in-process answers
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np


def make_models(folder: Path) -> None:
    from neumip.core.config import MaterialConfig
    from neumip.training.export.graph import build_onnx, random_weights, save_onnx

    folder.mkdir(parents=True, exist_ok=True)
    for name, cfg in (("smoke64", MaterialConfig(resolution=64)), ("smoke16", MaterialConfig(resolution=16, offset=False))):
        save_onnx(build_onnx(cfg, random_weights(cfg, seed=7), f"docker smoke test {name}"), folder / f"{name}.onnx")
        (folder / f"{name}.onnx").chmod(0o644)
    folder.chmod(0o755)


def check(url: str, folder: Path) -> None:
    """Every served material answers msgpack and v2 binary queries, plain and in query groups of two
    lights, bit-identically to the same engine here: the kernel engine (the image's default) or ONNX Runtime
    (an image built with KERNEL_ENGINE=0), as the model metadata's platform says."""
    import httpx
    import tritonclient.http as triton

    from neumip.core import contract as C
    from neumip.core import wire
    from neumip.engines.local import LocalMaterials

    client = triton.InferenceServerClient(url.split("://", 1)[1])
    with httpx.Client(base_url=url, timeout=60) as http:
        platform = http.get(f"/v2/models/{LocalMaterials(folder).materials()[0]}").raise_for_status().json()["platform"]
        if platform == "neumip_drjit_llvm":  # the same kernels on the same CPU: the same bits
            from neumip.engines.kernel import KernelMaterials

            local = KernelMaterials(folder)
        else:  # each row gets the same bits however a batch is cut: the multi-worker evaluator matches exactly
            local = LocalMaterials(folder)
        print(f"smoke: the image serves with {platform}")
        listed = [m["name"] for m in http.get(wire.MATERIALS_PATH).raise_for_status().json()["materials"]]
        assert listed == local.materials(), f"server lists {listed}, folder holds {local.materials()}"
        for i, name in enumerate(listed):
            q = C.random_queries(50_000, seed=i)
            groups = np.hstack([q[:20_000], C.random_queries(20_000, seed=100 + i)[:, C.WI_X:C.WI_Y + 1]])
            for sent in (q, groups):  # (N, 7) -> (N, 3); (N, 9) -> (N, 6)
                ref = local.evaluate(name, sent)
                resp = http.post(
                    wire.EVALUATE_PATH.format(name=name),
                    content=wire.encode_request(sent),
                    headers={"content-type": wire.MSGPACK_MEDIA_TYPE},
                ).raise_for_status()
                answer = wire.decode_response(resp.content)
                assert np.array_equal(answer, ref), f"{name} {sent.shape}: msgpack answer differs"
                tensor = triton.InferInput(C.ONNX_INPUT, list(sent.shape), "FP32")
                tensor.set_data_from_numpy(sent, binary_data=True)
                out = client.infer(name, [tensor]).as_numpy(C.ONNX_OUTPUT)
                assert np.array_equal(out, ref), f"{name} {sent.shape}: v2 binary answer differs"
            print(f"smoke: {name}: 50000 queries and 20000 groups of two lights, msgpack and v2 answers "
                  "bit-identical to in-process")
        bad = http.post(wire.EVALUATE_PATH.format(name=listed[0]), content=b"\x00garbage",
                        headers={"content-type": wire.MSGPACK_MEDIA_TYPE})
        assert bad.status_code == 400 and "error" in bad.json(), bad.text
        assert http.get("/v2/health/live").status_code == 200
        assert "neumip_query_rows_total" in http.get("/metrics").text
    # Triton's extensions: configuration, statistics (both requests above went through the batcher)
    # and the repository index
    config = client.get_model_config(listed[0])
    assert config["max_batch_size"] > 0 and config["input"][0]["dims"] == [-1], config  # -1: any group width
    stats = client.get_inference_statistics(listed[0])["model_stats"][0]
    assert stats["inference_count"] == 140_000 and stats["inference_stats"]["success"]["count"] == 4, stats
    assert {m["name"]: m["state"] for m in client.get_model_repository_index()} == dict.fromkeys(listed, "READY")
    print(f"smoke: {listed[0]}: config, statistics ({stats['execution_count']} engine calls) and repository index")


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "make-models":
        make_models(Path(sys.argv[2]))
    elif len(sys.argv) == 4 and sys.argv[1] == "check":
        check(sys.argv[2], Path(sys.argv[3]))
    else:
        sys.exit(__doc__)
