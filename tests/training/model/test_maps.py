"""Map-informed materials: the maps' prefilter (known slopes and moments), the encoder's textures
baked into an export that answers as torch does, checkpoints, and a short training run."""

from dataclasses import replace

import numpy as np
import onnxruntime as ort
import pytest
import torch

from neumip.core import contract as C
from neumip.core.config import MaterialConfig
from neumip.core.contract import random_queries
from neumip.training.loop import checkpoint
from neumip.training.loop.blur import blur_pyramid, blur_texture
from neumip.training.export.graph import export_material
from neumip.training.loop.outputs import export_checkpoint
from neumip.groundtruth.lobe import sampling_lobe
from neumip.training.model.maps import FEATURES, HEIGHT_UNIT, MapConfig, prefilter, resize
from neumip.training.model.material import MapMaterial, NeuMIPMaterial, neighbourhood
from neumip.groundtruth.description import Microgeometry
from neumip.training.loop.train import Trainer, TrainingError
from neumip.training.loop.config import TEST



def geometry(height: np.ndarray, albedo=None, roughness=None) -> Microgeometry:
    albedo = np.full((1, 1, 3), 0.5, np.float32) if albedo is None else albedo
    roughness = np.full((1, 1), 0.4, np.float32) if roughness is None else roughness
    return Microgeometry(height=height.astype(np.float32), base_color=albedo.astype(np.float32),
                         roughness=roughness.astype(np.float32), metallic=np.zeros((1, 1), np.float32),
                         specular=0.5, bsdf=None, normals="smooth")


def grid(res: int) -> tuple[np.ndarray, np.ndarray]:
    t = (np.arange(res) + 0.5) / res
    return np.meshgrid(t, t, indexing="xy")  # x along u (columns), y along v (rows)


SIZES = [16, 8, 4, 2, 1]


def test_a_plane_has_zero_slopes_and_moments_at_every_level():
    for height in (np.zeros((32, 32)), np.full((32, 32), -0.03), np.zeros((1, 1))):
        for f in prefilter(geometry(height), SIZES):
            np.testing.assert_allclose(f[..., 1:6], 0.0, atol=1e-7)
            np.testing.assert_allclose(f[..., 0], height.mean() / HEIGHT_UNIT, atol=1e-6)


def test_a_triangle_ramp_gives_its_slope_and_the_coarse_level_its_spread():
    """h = s (0.5 - |u - 0.5|): slope +s on the left half, -s on the right (central differences
    halve it at the two samples beside each kink, so a half-tile texel reads 31/32 s)."""
    s, res = 0.2, 64
    x, _ = grid(res)
    feats = prefilter(geometry(s * (0.5 - np.abs(x - 0.5))), [2, 1])
    half = feats[0]
    np.testing.assert_allclose(half[:, 0, 1], s * 31 / 32, rtol=1e-5)  # left column: dh/du = +s
    np.testing.assert_allclose(half[:, 1, 1], -s * 31 / 32, rtol=1e-5)
    np.testing.assert_allclose(half[..., 2], 0.0, atol=1e-7)  # nothing along v
    whole = feats[1][0, 0]
    assert abs(whole[1]) < 1e-7  # the slopes cancel over the tile...
    assert whole[3] == pytest.approx(s * np.sqrt((60 + 4 / 4) / 64), rel=1e-5)  # ...their spread stays
    assert whole[4] == pytest.approx(0.0, abs=1e-7) and whole[5] == pytest.approx(0.0, abs=1e-7)


def test_a_slope_along_v_lands_in_the_v_column_and_rows_follow_v():
    s, res = 0.1, 32
    _, y = grid(res)
    feats = prefilter(geometry(s * (0.5 - np.abs(y - 0.5))), [2])[0]
    np.testing.assert_allclose(feats[0, :, 2], s * 15 / 16, rtol=1e-5)  # row 0 is v in [0, 0.5)
    np.testing.assert_allclose(feats[1, :, 2], -s * 15 / 16, rtol=1e-5)
    np.testing.assert_allclose(feats[..., 1], 0.0, atol=1e-7)


def test_reflectance_maps_are_box_averaged_and_constants_broadcast():
    rng = np.random.default_rng(0)
    albedo = rng.random((16, 16, 3))
    feats = prefilter(geometry(np.zeros((1, 1)), albedo=albedo, roughness=np.full((1, 1), 0.7)), [8, 1])
    np.testing.assert_allclose(feats[0][..., 6:9], resize(albedo, 8), rtol=1e-6)
    np.testing.assert_allclose(feats[0][1, 2, 6:9], albedo[2:4, 4:6].mean(axis=(0, 1)), rtol=1e-6)
    np.testing.assert_allclose(feats[1][0, 0, 6:9], albedo.mean(axis=(0, 1)), rtol=1e-6)
    np.testing.assert_allclose(feats[1][..., 9], 0.7, rtol=1e-6)
    assert [f.shape for f in feats] == [(8, 8, FEATURES), (1, 1, FEATURES)]


def test_neighbourhood_reads_wrapped_neighbours_row_by_row():
    f = torch.arange(16.0).view(4, 4, 1)
    near = neighbourhood(f, 3)
    assert near.shape == (4, 4, 9)
    assert near[0, 0].tolist() == [15, 12, 13, 3, 0, 1, 7, 4, 5]  # rows v-1, v, v+1, wrapped


def random_map_material(config: MaterialConfig, maps: MapConfig = MapConfig(), seed: int = 0) -> MapMaterial:
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    features = [rng.normal(size=(s, s, FEATURES)).astype(np.float32) for s in config.level_sizes()]
    material = MapMaterial(config, maps, features)
    with torch.no_grad():
        for p in material.free_parameters():
            p.normal_(0, 0.1)  # the free parts matter too
        if config.offset:
            material.offset_mlp[-1].bias.fill_(0.5)
    return material.eval()


def answers(material, q) -> np.ndarray:
    with torch.no_grad():
        return material(torch.from_numpy(q)).numpy()


@pytest.mark.parametrize("offset", [True, False], ids=["offset", "no-offset"])
def test_export_bakes_the_encoded_textures_and_answers_as_torch(offset, tmp_path, assert_parity, edge_queries):
    config = MaterialConfig(resolution=16, offset=offset)
    material = random_map_material(config)
    path = export_material(material, tmp_path / "m.onnx", "maps")
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for q in (random_queries(20000, seed=5), edge_queries(16)):
        want = answers(material, q)
        assert want.std() > 1e-3
        assert_parity(session.run(None, {C.ONNX_INPUT: q})[0], want)
    # the file is the paper's graph: a paper model given the baked textures answers the same
    plain = NeuMIPMaterial(config)
    plain.load_state_dict({k: v for k, v in material.state_dict().items() if k in plain.state_dict()})
    np.testing.assert_allclose(answers(plain, random_queries(2000, seed=6)),
                               answers(material, random_queries(2000, seed=6)), rtol=1e-6, atol=1e-7)


def test_checkpoint_round_trip_keeps_the_encoder_and_the_free_parts(tmp_path):
    config = MaterialConfig(resolution=8)
    material = random_map_material(config, MapConfig(neighbourhood=1, residual=8))
    checkpoint.save(tmp_path / "c.pt", material)
    again, _ = checkpoint.load(tmp_path / "c.pt")
    assert isinstance(again, MapMaterial) and again.maps == material.maps
    for a, b in zip(again.free_parameters(), material.free_parameters()):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    q = random_queries(3000, seed=1)
    np.testing.assert_array_equal(answers(again.eval(), q), answers(material, q))


def test_residual_trains_free_textures_on_the_coarse_levels_only():
    config = MaterialConfig(resolution=16)  # levels 16, 8, 4, 2, 1
    trained = [p.requires_grad for p in random_map_material(config, MapConfig(residual=4)).free_parameters()]
    assert trained == [False, False, True, True, True, False]  # the offset texture is the finest level's
    every = MapConfig(residual=16)
    assert all(p.requires_grad for p in random_map_material(config, every).free_parameters())
    assert not any(p.requires_grad for p in random_map_material(config).free_parameters())


def test_map_config_reads_the_residual_of_older_files_and_refuses_a_flag():
    assert MapConfig.from_json('{"residual": false}').residual == 0
    assert MapConfig.from_json('{"residual": true}').residual >= 1 << 16  # every level, as it meant
    assert MapConfig.from_json(MapConfig(residual=8).to_json()) == MapConfig(residual=8)
    with pytest.raises(ValueError, match="level size"):
        MapConfig(residual=True)
    with pytest.raises(ValueError, match="level size"):
        MapConfig(residual=-1)


def test_store_textures_makes_the_material_answer_with_them():
    config = MaterialConfig(resolution=16)
    material = random_map_material(config)
    levels, otex = material.textures()
    blurred, blurred_otex = blur_pyramid(levels, 2.0, 0.2), blur_texture(otex, 1.5)
    material.store_textures([t.detach() for t in blurred], blurred_otex.detach())
    now, now_otex = material.textures()
    for a, b in zip(now, blurred):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(now_otex, blurred_otex, rtol=1e-5, atol=1e-6)


def test_features_must_match_the_pyramid():
    with pytest.raises(ValueError, match="do not match"):
        MapMaterial(MaterialConfig(resolution=8), MapConfig(), [np.zeros((4, 4, FEATURES))] * 4)
    with pytest.raises(ValueError, match="neighbourhood"):
        MapConfig(neighbourhood=5)


@pytest.fixture(scope="module")
def plane_geometry(plane_color) -> Microgeometry:
    """The analytic plane of conftest.plane_mbtf as maps (16^2): its albedo pattern times its colour."""
    x, y = grid(16)
    albedo = (0.6 + 0.3 * np.sin(2 * np.pi * x) * np.cos(2 * np.pi * y))[..., None] * plane_color
    return geometry(np.zeros((1, 1)), albedo=albedo)


@pytest.fixture(scope="module")
def plane(tmp_path_factory, plane_data):
    return plane_data(tmp_path_factory.mktemp("plane") / "data", 20_000, seed=4)


def test_a_map_informed_material_learns_the_plane_and_its_checkpoint_exports(plane, tmp_path, assert_parity, plane_geometry):
    torch.set_num_threads(1)
    config = replace(TEST, steps=150, batch=1024, checkpoint_every=100, validate_every=0)
    trainer = Trainer(plane.path, tmp_path / "c.pt", MaterialConfig(resolution=16), config,
                      maps=(MapConfig(), plane_geometry))
    before = trainer.validate()["overall"]["rel_l1"]
    table = trainer.run()
    assert isinstance(trainer.material, MapMaterial)
    assert table["overall"]["rel_l1"] < 0.5 * before, (before, table["overall"])
    out = export_checkpoint(tmp_path / "c.pt", tmp_path / "m.onnx")
    q = random_queries(5000, seed=2)
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    assert_parity(session.run(None, {C.ONNX_INPUT: q})[0], answers(trainer.material.eval(), q))
    # the maps' sampling lobe (roughness 0.4: alpha 0.16) travels from the run to the file
    assert trainer.sampling == sampling_lobe(plane_geometry) == C.SamplingLobe(pytest.approx(0.16), 0.5)
    assert C.sampling_lobe(dict(session.get_modelmeta().custom_metadata_map)) == trainer.sampling
    # the checkpoint is a map-informed run: resuming it as the paper's model is refused
    with pytest.raises(TrainingError, match="map encoder"):
        Trainer(plane.path, tmp_path / "c.pt", MaterialConfig(resolution=16), config)


def test_cli_trains_a_map_informed_model_from_a_description(plane, tmp_path, capsys):
    from pathlib import Path

    from neumip.client.cli import main

    bumps = Path(__file__).parents[3] / "docs" / "materials" / "bumps.toml"
    out = tmp_path / "plane.onnx"
    argv = ["train", str(plane.path), "-o", str(out), "--preset", "test", "--resolution", "8", "--steps", "5",
            "--batch", "256", "--checkpoint", str(tmp_path / "ck.pt")]
    assert main([*argv, "--maps", str(bumps), "--residual", "2"]) == 0 and out.exists()
    material = checkpoint.load(tmp_path / "ck.pt")[0]
    assert isinstance(material, MapMaterial) and material.maps.residual == 2
    assert main([*argv, "--residual", "2", "--force"]) == 2  # a free residual is the map encoder's
    assert "--residual is a feature of the map-informed model" in capsys.readouterr().err
    # the plane's data set names no material description to take the maps from
    assert main([*argv, "--maps", "--force"]) == 2
    assert "does not describe its material" in capsys.readouterr().err


def test_a_map_informed_run_resumes_as_one(plane, tmp_path, plane_geometry):
    torch.set_num_threads(1)
    config = replace(TEST, steps=10, batch=256, validate_every=0)
    maps = (MapConfig(neighbourhood=1), plane_geometry)
    Trainer(plane.path, tmp_path / "c.pt", MaterialConfig(resolution=8), config, maps=maps).run()
    again = Trainer(plane.path, tmp_path / "c.pt", MaterialConfig(resolution=8), replace(config, steps=20), maps=maps)
    assert isinstance(again.material, MapMaterial) and again.state.step == 10
    again.run()
    assert again.state.step == 20
    with pytest.raises(TrainingError, match="map encoder"):  # another encoder is another run
        Trainer(plane.path, tmp_path / "c.pt", MaterialConfig(resolution=8), config, maps=(MapConfig(), plane_geometry))


def test_horizons_see_a_wall_towards_it_only():
    """A wall one sample wide, 0.1 tile above a plane: the sample two to its left (towards -u) sees
    it at azimuth 0 (+u) under atan(0.1 / (2 / 32)); azimuth 180 degrees sees open sky."""
    height = np.full((32, 32), -0.1)
    height[:, 16] = 0.0
    feats = prefilter(geometry(height), [32], horizons=4)[0]
    assert feats.shape == (32, 32, FEATURES + 4)
    left = feats[5, 14, FEATURES:]  # azimuths 0, 90, 180, 270 degrees
    assert left[0] == pytest.approx(np.arctan(0.1 / (2 / 32)) / (np.pi / 2), rel=1e-5)
    np.testing.assert_allclose(left[1:], [0.0, 0.0, 0.0], atol=1e-7)  # along the wall, away from it
    np.testing.assert_allclose(feats[..., 16, FEATURES:], 0.0, atol=1e-7)  # the wall's top sees the sky
    flat = prefilter(geometry(np.zeros((16, 16))), [16, 1], horizons=8)
    for f in flat:
        np.testing.assert_allclose(f[..., FEATURES:], 0.0, atol=1e-7)


def test_a_map_of_any_size_is_area_averaged_not_point_sampled():
    """A 1000^2 texel checkerboard (mean 0.5) at 256^2, 128^2 and 3^2, sizes it does not divide:
    each texel holds the mean of what it covers (point samples read 0.03-0.97); a random colour map
    keeps its mean."""
    from neumip.training.model.maps import resize

    checker = (np.indices((1000, 1000)).sum(0) % 2).astype(np.float32)
    for size in (256, 128, 3):
        np.testing.assert_allclose(resize(checker, size), 0.5, atol=1e-3)
    rgb = np.random.default_rng(0).random((1000, 1000, 3))
    np.testing.assert_allclose(resize(rgb, 256).mean(axis=(0, 1)), rgb.mean(axis=(0, 1)), atol=1e-5)
