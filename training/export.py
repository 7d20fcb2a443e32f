"""ONNX export: the material as one graph, textures stored as initializers.

The graph takes ``queries`` (N, 7) float32 and returns ``rgb`` (N, 3) float32, N dynamic, and
computes exactly what `material.NeuMIPMaterial.forward` computes: the neural offset, a trilinear
lookup that gathers 8 texels per query from a flat atlas of all pyramid levels, then the decoder MLP.
The model config, contract version and a description travel in the ONNX metadata.

`build_onnx` needs only numpy and onnx (weights as numpy arrays); `export_checkpoint` reads a torch
checkpoint.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from neumip.client import contract as C

from .config import MaterialConfig

OPSET = 18
IR_VERSION = 9  # onnxruntime 1.31 reads IR <= 13; onnx 1.23 would write 14 by default.


def weights_from_state(state: dict, config: MaterialConfig) -> dict[str, np.ndarray]:
    """Torch state dict of `NeuMIPMaterial` -> the numpy weights `build_onnx` takes."""
    arr = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in state.items()}
    weights = {
        "pyramid": np.concatenate(
            [arr[f"pyramid.{i}"].reshape(-1, config.channels) for i in range(config.levels + 1)]
        )
    }
    prefixes = ["decoder"] + (["offset_mlp"] if config.offset else [])
    for prefix in prefixes:
        for i in range(config.layers):
            weights[f"{prefix}.{i}.weight"] = arr[f"{prefix}.{2 * i}.weight"]
            weights[f"{prefix}.{i}.bias"] = arr[f"{prefix}.{2 * i}.bias"]
    if config.offset:
        weights["offset_texture"] = arr["offset_texture"].reshape(-1, config.offset_channels)
    return weights


class _Graph:
    """Tiny helper that names nodes and constants while a graph is written."""

    def __init__(self) -> None:
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self._n = 0

    def _name(self, hint: str) -> str:
        self._n += 1
        return f"{hint}_{self._n}"

    def const(self, value, dtype=np.float32, name: str | None = None) -> str:
        name = name or self._name("c")
        self.inits.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def op(self, op_type: str, *inputs: str, outputs: int = 1, **attrs):
        names = [self._name(op_type.lower()) for _ in range(outputs)]
        self.nodes.append(helper.make_node(op_type, list(inputs), names, **attrs))
        return names[0] if outputs == 1 else names

    def mlp(self, x: str, weights: dict, prefix: str, layers: int) -> str:
        """Gemm + Relu chain; no Relu after the last layer."""
        for i in range(layers):
            w = self.const(weights[f"{prefix}.{i}.weight"], name=f"{prefix}.{i}.weight")
            b = self.const(weights[f"{prefix}.{i}.bias"], name=f"{prefix}.{i}.bias")
            x = self.op("Gemm", x, w, b, transB=1)
            if i < layers - 1:
                x = self.op("Relu", x)
        return x

    def bilinear(self, u: str, v: str, size: str, start: str) -> tuple[str, str]:
        """u, v (N, 1) in [0, 1]; size, start (N, L) or (1, 1) int64 -> rows, weights (N, L, 4)."""
        sizef = self.op("Cast", size, to=TensorProto.FLOAT)
        half = self.const(0.5)
        one = self.const(1.0)
        x = self.op("Sub", self.op("Mul", u, sizef), half)
        y = self.op("Sub", self.op("Mul", v, sizef), half)
        x0f, y0f = self.op("Floor", x), self.op("Floor", y)
        fx, fy = self.op("Sub", x, x0f), self.op("Sub", y, y0f)
        x0 = self.op("Mod", self.op("Cast", x0f, to=TensorProto.INT64), size)
        y0 = self.op("Mod", self.op("Cast", y0f, to=TensorProto.INT64), size)
        one_i = self.const(1, np.int64)
        x1 = self.op("Mod", self.op("Add", x0, one_i), size)
        y1 = self.op("Mod", self.op("Add", y0, one_i), size)
        row0 = self.op("Add", start, self.op("Mul", y0, size))
        row1 = self.op("Add", start, self.op("Mul", y1, size))
        axis = self.const([-1], np.int64)
        taps = [self.op("Add", r, c) for r, c in ((row0, x0), (row0, x1), (row1, x0), (row1, x1))]
        rows = self.op("Concat", *[self.op("Unsqueeze", t, axis) for t in taps], axis=-1)
        gx, gy = self.op("Sub", one, fx), self.op("Sub", one, fy)
        ws = [self.op("Mul", a, b) for a, b in ((gx, gy), (fx, gy), (gx, fy), (fx, fy))]
        weights = self.op("Concat", *[self.op("Unsqueeze", w, axis) for w in ws], axis=-1)
        return rows, weights

    def gather_blend(self, table: str, rows: str, weights: str, taps: int) -> str:
        """Gather `taps` rows per query of (T, C) `table` and blend with `weights` -> (N, C)."""
        flat = self.const([-1, taps], np.int64)
        rows = self.op("Reshape", rows, flat)
        weights = self.op("Reshape", weights, flat)
        texels = self.op("Gather", table, rows, axis=0)  # (N, K, C)
        weighted = self.op("Mul", texels, self.op("Unsqueeze", weights, self.const([-1], np.int64)))
        return self.op("ReduceSum", weighted, self.const([1], np.int64), keepdims=0)


def _wrap(g: _Graph, u: str) -> str:
    return g.op("Sub", u, g.op("Floor", u))


def build_onnx(
    config: MaterialConfig,
    weights: dict[str, np.ndarray],
    description: str = "",
    extra_metadata: dict[str, str] | None = None,
) -> onnx.ModelProto:
    """The material's inference graph: (N, 7) float32 queries -> (N, 3) float32 RGB."""
    g = _Graph()
    cols = g.op("Split", C.ONNX_INPUT, axis=1, num_outputs=C.QUERY_DIM, outputs=C.QUERY_DIM)
    u, v, sigma, wi_x, wi_y, wo_x, wo_y = cols

    # --- neural offset: u += r * wo_xy / max(wo_z, min_cos) ------------------------------------
    if config.offset:
        res = g.const([[config.resolution]], np.int64)
        rows, w = g.bilinear(_wrap(g, u), _wrap(g, v), res, g.const([[0]], np.int64))
        otex = g.const(weights["offset_texture"], name="offset_texture")
        feat = g.gather_blend(otex, rows, w, 4)
        depth = g.mlp(g.op("Concat", feat, wo_x, wo_y, axis=1), weights, "offset_mlp", config.layers)
        depth = g.op("Mul", depth, g.const(config.offset_scale))
        one = g.const(1.0)
        r2 = g.op("Add", g.op("Mul", wo_x, wo_x), g.op("Mul", wo_y, wo_y))
        wo_z = g.op("Sqrt", g.op("Max", g.op("Sub", one, r2), g.const(0.0)))
        scale = g.op("Div", depth, g.op("Max", wo_z, g.const(config.offset_min_cos)))
        u = g.op("Add", u, g.op("Mul", scale, wo_x))
        v = g.op("Add", v, g.op("Mul", scale, wo_y))

    # --- trilinear pyramid lookup ----------------------------------------------------------------
    tiny = np.finfo(np.float32).tiny
    scaled = g.op("Mul", g.op("Max", sigma, g.const(tiny)), g.const(float(config.resolution)))
    lod = g.op("Div", g.op("Log", scaled), g.const(math.log(2.0)))
    lod = g.op("Clip", lod, g.const(0.0), g.const(float(config.levels)))
    lo = g.op("Floor", lod)
    t = g.op("Sub", lod, lo)
    lo_i = g.op("Cast", lo, to=TensorProto.INT64)
    hi_i = g.op("Min", g.op("Add", lo_i, g.const(1, np.int64)), g.const(config.levels, np.int64))
    levels = g.op("Concat", lo_i, hi_i, axis=1)  # (N, 2)
    size = g.op("Gather", g.const(config.level_sizes(), np.int64), levels, axis=0)
    start = g.op("Gather", g.const(config.level_starts(), np.int64), levels, axis=0)
    rows, w = g.bilinear(_wrap(g, u), _wrap(g, v), size, start)  # (N, 2, 4)
    level_w = g.op("Concat", g.op("Sub", g.const(1.0), t), t, axis=1)
    w = g.op("Mul", w, g.op("Unsqueeze", level_w, g.const([-1], np.int64)))
    atlas = g.const(weights["pyramid"], name="pyramid")
    features = g.gather_blend(atlas, rows, w, 8)

    # --- decoder ---------------------------------------------------------------------------------
    x = g.op("Concat", features, wi_x, wi_y, wo_x, wo_y, axis=1)
    rgb = g.mlp(x, weights, "decoder", config.layers)
    g.nodes.append(helper.make_node("Relu", [rgb], [C.ONNX_OUTPUT]))

    graph = helper.make_graph(
        g.nodes,
        "neumip_material",
        [helper.make_tensor_value_info(C.ONNX_INPUT, TensorProto.FLOAT, ["N", C.QUERY_DIM])],
        [helper.make_tensor_value_info(C.ONNX_OUTPUT, TensorProto.FLOAT, ["N", C.RGB_DIM])],
        initializer=g.inits,
    )
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="neumip"
    )
    model.ir_version = IR_VERSION
    meta = {
        C.META_CONTRACT: C.CONTRACT_VERSION,
        C.META_CONFIG: config.to_json(),
        C.META_DESCRIPTION: description,
        **(extra_metadata or {}),
    }
    helper.set_model_props(model, meta)
    onnx.checker.check_model(model, full_check=True)
    return model


def save_onnx(model: onnx.ModelProto, path: str | Path) -> Path:
    """Write `model` to `path` atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(model.SerializeToString())
    os.replace(tmp, path)
    return path


def export_checkpoint(
    checkpoint: str | Path, out: str | Path, description: str = "", extra_metadata: dict | None = None
) -> Path:
    """`neumip export`: read a training checkpoint, write the ONNX model."""
    from .checkpoint import load  # torch only here

    material, extra = load(checkpoint)
    meta = dict(extra_metadata or {})
    if "validation" in extra and C.META_VALIDATION not in meta:
        import json

        meta[C.META_VALIDATION] = json.dumps(extra["validation"])
    model = build_onnx(material.config, weights_from_state(material.state_dict(), material.config),
                       description or extra.get("description", ""), meta)
    return save_onnx(model, out)


# --- weight factories (no torch): known-answer and random materials for tests and benchmarks ------


def _shapes(config: MaterialConfig) -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {"pyramid": (config.atlas_rows(), config.channels)}
    mlps = {"decoder": (config.channels + 4, C.RGB_DIM)}
    if config.offset:
        mlps["offset_mlp"] = (config.offset_channels + 2, 1)
        shapes["offset_texture"] = (config.resolution**2, config.offset_channels)
    for prefix, (n_in, n_out) in mlps.items():
        widths = [n_in] + [config.hidden] * (config.layers - 1) + [n_out]
        for i in range(config.layers):
            shapes[f"{prefix}.{i}.weight"] = (widths[i + 1], widths[i])
            shapes[f"{prefix}.{i}.bias"] = (widths[i + 1],)
    return shapes


def random_weights(config: MaterialConfig, seed: int = 0, scale: float = 0.5) -> dict[str, np.ndarray]:
    """Random weights of the right shapes (a material with texture and direction variation)."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, shape in _shapes(config).items():
        fan_in = shape[1] if name.endswith("weight") else 1
        out[name] = (rng.normal(size=shape) * scale / np.sqrt(fan_in)).astype(np.float32)
    return out


def constant_weights(config: MaterialConfig, rgb) -> dict[str, np.ndarray]:
    """Weights of a material that answers `rgb` for every query (e.g. albedo / pi: a Lambertian)."""
    out = {name: np.zeros(shape, np.float32) for name, shape in _shapes(config).items()}
    out[f"decoder.{config.layers - 1}.bias"] = np.asarray(rgb, np.float32).reshape(C.RGB_DIM)
    return out
