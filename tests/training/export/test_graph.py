"""ONNX export: graph structure, metadata, and torch vs ONNX Runtime parity on random and edge queries."""

import json
from dataclasses import replace

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from neumip.core import contract as C
from neumip.core import weights as W
from neumip.training.loop import checkpoint
from neumip.core.config import MaterialConfig
from neumip.training.export.base import BASE_CONSTANT, BASE_PLACE
from neumip.training.export.graph import build_onnx, constant_weights, random_weights, weights_from_state
from neumip.training.loop.outputs import export_checkpoint
from neumip.training.model.material import NeuMIPMaterial
from neumip.core.contract import random_queries

def torch_eval(material: NeuMIPMaterial, q: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return material(torch.from_numpy(q)).numpy()


PARITY_CASES = {
    "offset": {},
    "no-offset": dict(offset=False),
    "half-vector": dict(half_vector=True),
    "base": dict(base=64),
    "relief": dict(relief=64),
    "relief-base": dict(offset=False, base=64, relief=64),
    "local-frame": dict(half_vector=True, base=64, relief=64, local_frame=True),
    "no-terminator": dict(offset=False, base=64, relief=64, terminator="none"),
    "specular-terminator": dict(offset=False, base=64, relief=64, terminator="specular"),
    "visibility-input": dict(base=64, relief=64, local_frame=True, terminator="none", visibility_input=True),
    "visibility-input-alone": dict(base=64, visibility_input=True),
    "lod-bias": dict(base=64, relief=64, local_frame=True, terminator="none", lod_bias=2),
    "half-textures": dict(base=64, relief=64, local_frame=True, terminator="none", lod_bias=1, half_textures=True),
    "offset-mip": dict(offset_mip=True),
    "offset-mip-maps": dict(base=64, relief=64, local_frame=True, terminator="none", lod_bias=1, half_textures=True,
                            offset_mip=True),
    "energy": dict(base=64, relief=64, local_frame=True, terminator="none", lod_bias=1, half_textures=True,
                   offset_mip=True, energy_bins=6),
    "energy-alone": dict(energy_bins=2),
    "energy-azimuths": dict(base=64, relief=64, local_frame=True, terminator="none", lod_bias=1, half_textures=True,
                            offset_mip=True, energy_bins=6, energy_azimuths=8),
    "energy-azimuths-alone": dict(energy_bins=2, energy_azimuths=3),
    "energy-luminance": dict(base=64, relief=64, local_frame=True, terminator="none", lod_bias=1, half_textures=True,
                             offset_mip=True, energy_bins=6, energy_azimuths=8, energy_luminance=True),
    "coarse-decoder": dict(base=64, relief=64, local_frame=True, terminator="none", lod_bias=1, half_textures=True,
                           offset_mip=True, energy_bins=6, coarse_decoder=2),
    "coarse-decoder-alone": dict(coarse_decoder=3),
}
"""Models whose torch and ONNX answers must agree: `MaterialConfig` fields over a 32^2 material with an offset."""


@pytest.fixture(scope="module", params=list(PARITY_CASES.values()), ids=list(PARITY_CASES))
def pair(request):
    torch.manual_seed(3)
    cfg = MaterialConfig(resolution=32, **request.param)
    material = NeuMIPMaterial(cfg, init_std=0.5)
    if cfg.relief:  # a relief 0.125 tile deep: its shifts span many texels
        material.set_maps(W.RELIEF, [random_weights(cfg, seed=5)[W.RELIEF]])
    if cfg.base:  # maps of a base's ranges, and a decoder that corrects the base (its last layer starts at 0)
        weights = random_weights(cfg, seed=4)
        with torch.no_grad():
            material.base_maps.copy_(torch.from_numpy(weights["base_maps"]))
            for decoder in material.decoders():
                decoder[-1].weight.normal_(0.0, 0.2)
    if cfg.energy_bins:  # gains that differ by level, angle, azimuth and channel
        with torch.no_grad():
            material.energy.uniform_(0.5, 2.0)
            W.tie_normal_cells(material.energy, cfg)
    # make the offset large enough to matter (random init gives tiny depths)
    if cfg.offset:
        with torch.no_grad():
            material.offset_mlp[-1].bias.fill_(0.5)
    model = build_onnx(cfg, weights_from_state(material.state_dict(), cfg), "test")
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return material, model, session


def test_parity_random_queries(pair, assert_parity):
    material, _, session = pair
    q = random_queries(20000, seed=11)
    want = torch_eval(material, q)
    got = session.run(None, {C.ONNX_INPUT: q})[0]
    assert got.shape == (20000, 3) and got.dtype == np.float32
    assert want.std() > 1e-3, "test material must not be constant"
    assert_parity(got, want)


def test_parity_edge_queries(pair, edge_queries, assert_parity):
    material, _, session = pair
    q = edge_queries(material.config.resolution)
    want = torch_eval(material, q)
    got = session.run(None, {C.ONNX_INPUT: q})[0]
    assert np.isfinite(got).all() and (got >= 0).all()
    assert_parity(got, want)


CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


CUDA_STRAYS = 1e-4
"""Share of answers a GPU may give outside the parity contract, each still within `CUDA_STRAY_RTOL`. The relief
march is discontinuous in its inputs (the first of its steps below the height field), and the GPU's kernels round
differently (fused multiply-adds): where a ray grazes a crossing, one last bit can move the landing point. An H200
gave 1 such answer in 60 000 (4.6e-5, relative 1.5e-4) with a lod bias of 2."""
CUDA_STRAY_RTOL = 1e-3


@CUDA
def test_cuda_answers_as_the_graph(pair, edge_queries, assert_parity, parity_tolerances):
    """The material on a GPU (how `neumip train --device cuda` trains) answers what the exported graph answers: all
    within the parity contract without a relief; with one, all but a `CUDA_STRAYS` share (`CUDA_STRAY_RTOL`)."""
    material, _, session = pair
    on_gpu = NeuMIPMaterial(material.config).to("cuda")
    on_gpu.load_state_dict(material.state_dict())
    for q in (random_queries(20000, seed=12), edge_queries(material.config.resolution)):
        with torch.no_grad():
            got = on_gpu(torch.from_numpy(q).to("cuda")).cpu().numpy()
        want = session.run(None, {C.ONNX_INPUT: q})[0]
        if not material.config.relief:
            assert_parity(got, want)
            continue
        atol, rtol = parity_tolerances
        stray = ~np.isclose(got, want, atol=atol, rtol=rtol).all(axis=1)
        assert stray.mean() <= CUDA_STRAYS, f"{stray.sum()} of {len(q)} answers outside parity"
        np.testing.assert_allclose(got, want, atol=atol, rtol=CUDA_STRAY_RTOL)


def test_the_ceiling_clamps_answers_in_torch_and_in_the_graph_alike(assert_parity):
    """`MaterialConfig.ceiling`: no answer above it, torch and the graph agree, and the loss's unclamped answers
    (``ceiling=False``) are the same material's."""
    torch.manual_seed(5)
    free = NeuMIPMaterial(MaterialConfig(resolution=16), init_std=0.5)
    q = random_queries(20000, seed=13)
    unclamped = torch_eval(free, q)
    ceiling = float(np.float32(np.median(unclamped)))
    material = NeuMIPMaterial(replace(free.config, ceiling=ceiling))
    material.load_state_dict(free.state_dict())
    want = torch_eval(material, q)
    assert want.max() == ceiling and (unclamped > ceiling).mean() > 0.3
    np.testing.assert_array_equal(want, np.minimum(unclamped, ceiling))
    with torch.no_grad():
        np.testing.assert_array_equal(material(torch.from_numpy(q), ceiling=False).numpy(), unclamped)
    model = build_onnx(material.config, weights_from_state(material.state_dict(), material.config), "test")
    got = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]).run(
        None, {C.ONNX_INPUT: q})[0]
    assert got.max() <= ceiling
    assert_parity(got, want)


def test_graph_stores_textures_as_initializers_and_metadata(pair):
    material, model, _ = pair
    onnx.checker.check_model(model, full_check=True)
    assert [i.name for i in model.graph.input] == [C.ONNX_INPUT]
    assert [o.name for o in model.graph.output] == [C.ONNX_OUTPUT]
    inits = {i.name: i for i in model.graph.initializer}
    assert tuple(inits["pyramid"].dims) == (material.config.atlas_rows(), material.config.channels)
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta[C.META_CONTRACT] == C.CONTRACT_VERSION
    assert MaterialConfig.from_json(meta[C.META_CONFIG]) == material.config


def test_dynamic_batch_sizes(pair):
    _, _, session = pair
    for n in (0, 1, 7, 1025):
        assert session.run(None, {C.ONNX_INPUT: random_queries(n)})[0].shape == (n, 3)


def test_export_checkpoint_roundtrip(tmp_path, assert_parity):
    cfg = MaterialConfig(resolution=8)
    material = NeuMIPMaterial(cfg, init_std=0.5)
    ckpt = checkpoint.save(tmp_path / "m.pt", material, {"validation": {"mse": [1.0]}})
    out = export_checkpoint(ckpt, tmp_path / "m.onnx", "roundtrip")
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    q = random_queries(500, seed=5)
    assert_parity(session.run(None, {C.ONNX_INPUT: q})[0], torch_eval(material, q))
    meta = session.get_modelmeta().custom_metadata_map
    assert meta[C.META_DESCRIPTION] == "roundtrip"
    assert json.loads(meta[C.META_VALIDATION]) == {"mse": [1.0]}


def test_corrupt_checkpoint_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(checkpoint.CheckpointError, match="not a readable checkpoint"):
        export_checkpoint(bad, tmp_path / "x.onnx")
    assert not (tmp_path / "x.onnx").exists()


def test_constant_material_answers_constant():
    cfg = MaterialConfig(resolution=4)
    model = build_onnx(cfg, constant_weights(cfg, [0.1, 0.2, 0.3]))
    session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    out = session.run(None, {C.ONNX_INPUT: random_queries(100)})[0]
    np.testing.assert_allclose(out, np.tile([0.1, 0.2, 0.3], (100, 1)), rtol=1e-6)


@pytest.mark.parametrize("cfg", [MaterialConfig(), MaterialConfig(resolution=16, offset=False)], ids=["256", "16-no-offset"])
def test_random_material_answers_positive_and_varied_in_every_channel(cfg):
    q = random_queries(2000, seed=3)
    for seed in range(4):
        model = build_onnx(cfg, random_weights(cfg, seed=seed))
        session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        rgb = session.run(None, {C.ONNX_INPUT: q})[0]
        assert (rgb > 0).all(), f"seed {seed}: zero answers"
        assert rgb.std(axis=0).min() > 0.02, f"seed {seed}: a channel barely varies, std {rgb.std(axis=0)}"


def _base_pair(atlas_edit) -> tuple[NeuMIPMaterial, ort.InferenceSession, onnx.ModelProto]:
    """A material with a base (random maps, edited by `atlas_edit`) and a decoder that corrects it; its session."""
    torch.manual_seed(6)
    cfg = MaterialConfig(resolution=16, offset=False, base=32)
    material = NeuMIPMaterial(cfg, init_std=0.5)
    atlas = random_weights(cfg, seed=7)[W.BASE]
    atlas_edit(atlas)
    with torch.no_grad():
        material.base_maps.copy_(torch.from_numpy(atlas))
        material.decoder[-1].weight.normal_(0.0, 0.2)
    model = build_onnx(cfg, weights_from_state(material.state_dict(), cfg), "test")
    return material, ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"]), model


def _base_channels_read(model: onnx.ModelProto) -> list[int]:
    """The map channels the file stores per texel and the graph reads: the base atlas holds them, then the horizons
    (`export.base.BASE_PLACE` places each stored column; the others are one constant row)."""
    inits = {i.name: onnx.numpy_helper.to_array(i) for i in model.graph.initializer}
    place = inits.get(BASE_PLACE)
    channels = [] if place is None else np.argmax(place, axis=1).tolist()
    assert inits[W.BASE].shape[1] == len(channels) + 8 and inits[BASE_CONSTANT].shape == (1, 9)
    return channels


@pytest.mark.parametrize("edit, channels", [
    (lambda a: None, list(range(9))),
    (lambda a: a.__setitem__((slice(None), slice(3, 6)), 0.04), [0, 1, 2, 6, 7, 8]),  # F0 of a dielectric
    (lambda a: a.__setitem__((slice(None), slice(0, 9)), [0.3, 0.2, 0.1, 0.04, 0.04, 0.04, 0.0, 0.0, 0.25]), []),
], ids=["all-vary", "constant-f0", "all-constant"])
def test_a_base_reads_only_its_varying_map_channels_and_answers_as_torch(edit, channels, assert_parity, edge_queries):
    """A map channel that is the same in every texel is a constant of the graph (not read), and the answers are
    the torch material's, which reads every channel."""
    material, session, model = _base_pair(edit)
    assert _base_channels_read(model) == channels
    for q in (random_queries(20000, seed=14), edge_queries(material.config.resolution)):
        assert_parity(session.run(None, {C.ONNX_INPUT: q})[0], torch_eval(material, q))


def test_the_horizon_read_per_light_answers_as_all_eight_azimuths(assert_parity):
    """The graph reads the horizons of the two azimuths around each light's (`export_base.horizon_sine`); torch weighs all
    eight. Lights at every multiple of 22.5 degrees (on an azimuth, between two, either side of the +-x axis), at the
    zenith, and random, with horizons high enough to shadow: the same answers."""
    def tall_horizons(a):
        a[:, 9:] = np.random.default_rng(8).uniform(0.0, 0.9, a[:, 9:].shape)

    material, session, _ = _base_pair(tall_horizons)
    q = random_queries(4000, seed=15)
    phi = np.repeat(np.arange(16) * np.pi / 8, 250)
    phi[::2] += np.float32(1e-6) * np.where(np.arange(len(phi))[::2] % 4 == 0, 1, -1)
    s = np.sin(np.deg2rad(np.random.default_rng(9).uniform(0.0, 80.0, len(phi))))
    q[:, C.WI_X], q[:, C.WI_Y] = s * np.cos(phi), s * np.sin(phi)
    q[:10, C.WI_X:C.WI_Y + 1] = 0.0  # the zenith: no azimuth, unshadowed
    q[10:20, C.WI_Y] = -0.0  # -x axis from below and above
    q[10:20, C.WI_X] = -0.5
    want = torch_eval(material, q)
    lit = q[:, C.WI_X] ** 2 + q[:, C.WI_Y] ** 2 > 0.8  # low lights: most are shadowed somewhere
    assert (want[lit] == 0).any() and (want[lit] > 0).any(), "the test's horizons must shadow some lights"
    assert_parity(session.run(None, {C.ONNX_INPUT: q})[0], want)


def test_every_decoder_input_is_computed_in_torch_and_in_the_graph():
    """A row of `core.config.DECODER_INPUTS` needs its torch computation and its graph's, nothing else."""
    from neumip.core.config import DECODER_INPUTS
    from neumip.training.export import graph
    from neumip.training.model import material

    names = [row.name for row in DECODER_INPUTS]
    assert len(set(names)) == len(names)
    assert set(material.DECODER_INPUTS) == set(graph.DECODER_INPUTS) == set(names)


def test_half_textures_are_stored_in_float16_and_read_back_as_the_model_reads_them(tmp_path):
    """`MaterialConfig.half_textures`: the latents, the offset texture, the base's maps and the relief's heights are
    float16 initializers; the file is smaller; reading it back gives the rounded weights (the base's every channel:
    random maps vary in all), and a re-export writes the same file."""
    from neumip.training.export.read import read_model
    from neumip.training.export.upgrade import reexport

    cfg = MaterialConfig(resolution=32, base=64, relief=64, half_textures=True)
    weights = random_weights(cfg, seed=8)
    half = build_onnx(cfg, weights, "half")
    full = build_onnx(replace(cfg, half_textures=False), weights, "full")
    types = {i.name: i.data_type for i in half.graph.initializer}
    textures = (W.PYRAMID, W.OFFSET_TEXTURE, W.BASE, W.RELIEF)
    for name in textures:
        assert types[name] == onnx.TensorProto.FLOAT16, name
    assert half.ByteSize() < 0.6 * full.ByteSize()
    read = read_model(half)[1]
    for name in textures:
        np.testing.assert_array_equal(read[name], weights[name].astype(np.float16).astype(np.float32))
    assert reexport(half).SerializeToString() == half.SerializeToString()
    with pytest.raises(ValueError, match="beyond float16's range"):
        build_onnx(cfg, {**weights, W.PYRAMID: weights[W.PYRAMID] * 1e6}, "overflow")


@pytest.mark.parametrize("half", [True, False], ids=["half", "float32"])
@pytest.mark.parametrize("offset_mip", [False, True], ids=["offset", "offset-mip"])
def test_the_tables_folded_at_load_keep_the_textures_type(half, offset_mip):
    """What an engine computes at load from float16 textures - the quad tables of the latents, the offset texture,
    the base's maps, its horizons and the relief's heights - stays float16 (half the memory), and each query's read is
    cast to float32 after its Gather; float32 textures give float32 tables."""
    from onnx import numpy_helper

    from neumip.engines.onnx_kernel import fold_constants

    cfg = MaterialConfig(resolution=32, base=64, relief=64, half_textures=half, offset_mip=offset_mip)
    model = build_onnx(cfg, random_weights(cfg, seed=8), "tables")
    inits = {i.name: numpy_helper.to_array(i) for i in model.graph.initializer}
    constants, nodes = fold_constants(model.graph.node, inits)
    tables = [n for n in nodes if n.op_type == "Gather" and n.input[0] in constants]
    assert len({n.input[0] for n in tables}) == 5
    assert {constants[n.input[0]].dtype for n in tables} == {np.dtype(np.float16 if half else np.float32)}
    readers = {i: n for n in nodes for i in n.input}
    cast = [readers.get(n.output[0]) for n in tables]
    if half:
        assert all(c.op_type == "Cast" and c.attribute[0].i == onnx.TensorProto.FLOAT for c in cast)
    else:
        assert not any(c.op_type == "Cast" for c in cast)
