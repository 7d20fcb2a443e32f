"""Material descriptions: the TOML format, validation errors, maps from PNG/EXR/NPY, the shipped library."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from neumip.groundtruth import images
from neumip.groundtruth.description import (
    DescriptionError,
    MaterialDescription,
    find_description,
    library_names,
    load_description,
    resolve,
)


def write(tmp_path, text: str, name: str = "mat.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_library_has_the_required_kinds():
    names = library_names()
    assert {"yarn", "rock", "turtle", "foam", "flat"} <= set(names)
    for name in names:
        desc = find_description(name)
        assert desc.name == name and desc.summary


def test_library_materials_with_parallax_are_deep():
    """At least two shipped materials have strong relief: depth over a tenth of their feature size."""
    deep = [n for n in ("yarn", "rock", "turtle", "foam") if resolve(find_description(n)).depth >= 0.05]
    assert len(deep) >= 2


def test_flat_is_the_known_answer_control():
    geo = resolve(find_description("flat"))
    assert geo.depth == 0 and geo.bsdf["type"] == "diffuse"


def test_toml_with_file_maps_and_constants(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "h.npy", rng.random((16, 16)).astype(np.float32))
    albedo = (rng.random((8, 8, 3)) * 255).astype(np.uint8)
    Image.fromarray(albedo).save(tmp_path / "albedo.png")
    path = write(tmp_path, """
        resolution = 32
        height_scale = 0.1
        [maps]
        height = "h.npy"
        base_color = "albedo.png"
        roughness = 0.3
    """)
    desc = load_description(path)
    assert desc.name == "mat"  # from the file name
    geo = resolve(desc)
    assert geo.height.shape == (32, 32)  # resampled to the resolution
    assert geo.height.max() == 0 and geo.depth == pytest.approx(
        0.1 * np.ptp(images.resample_periodic(np.load(tmp_path / "h.npy"), 32)), rel=1e-5
    )
    np.testing.assert_allclose(geo.base_color, images.srgb_to_linear(albedo / 255.0), atol=1e-6)
    assert geo.roughness.shape == (1, 1) and geo.roughness[0, 0] == pytest.approx(0.3)
    assert "height" in desc.to_dict()["map_sha256"]


def test_png_colour_can_be_declared_linear(tmp_path):
    Image.fromarray(np.full((4, 4, 3), 128, np.uint8)).save(tmp_path / "c.png")
    desc = MaterialDescription.from_dict(
        {"name": "x", "maps": {"base_color": {"file": "c.png", "srgb": False}}}, base_dir=tmp_path
    )
    assert resolve(desc).base_color[0, 0, 0] == pytest.approx(128 / 255)


def test_exr_maps_are_read(tmp_path, mi):
    data = np.random.default_rng(1).random((8, 8, 3)).astype(np.float32)
    mi.Bitmap(data).write(str(tmp_path / "c.exr"))
    desc = MaterialDescription.from_dict({"name": "x", "maps": {"base_color": "c.exr"}}, base_dir=tmp_path)
    np.testing.assert_allclose(resolve(desc).base_color, data, atol=1e-3)  # EXR may store half floats


def test_sixteen_bit_png_height(tmp_path):
    h = (np.arange(64).reshape(8, 8) * 1000).astype(np.uint16)
    Image.fromarray(h).save(tmp_path / "h.png")
    assert images.read_image(tmp_path / "h.png").max() == pytest.approx(63000 / 65535)


@pytest.mark.parametrize(
    "data, message",
    [
        ({"name": "x", "colour": 1}, "unknown keys"),
        ({"resolution": 8}, "needs a 'name'"),
        ({"name": "x", "resolution": 0}, "resolution"),
        ({"name": "x", "normals": "bumpy"}, "normals"),
        ({"name": "x", "procedural": {"generator": "marble"}}, "unknown generator"),
        ({"name": "x", "maps": {"albedo": 0.5}}, "unknown maps"),
        ({"name": "x", "maps": {"height": "nowhere.png"}}, "does not exist"),
        ({"name": "x", "maps": {"height": 0.5}}, "must be a file"),
        ({"name": "x", "maps": {"roughness": 1.5}}, "constant in"),
        ({"name": "x", "maps": {"base_color": [0.1, 0.2]}}, "constant in"),
        ({"name": "x", "bsdf": {"reflectance": 0.5}}, "'type'"),
        ({"name": "x", "bsdf": {"type": "diffuse"}, "maps": {"roughness": 0.2}}, "replaces the principled"),
    ],
)
def test_bad_descriptions_say_what_is_wrong(tmp_path, data, message):
    with pytest.raises(DescriptionError, match=message):
        MaterialDescription.from_dict(data, base_dir=tmp_path)


def test_bad_generator_parameter_is_reported():
    desc = MaterialDescription.from_dict({"name": "x", "procedural": {"generator": "yarn", "colour": 1}})
    with pytest.raises(DescriptionError, match="colour"):
        resolve(desc)


def test_invalid_toml_and_unknown_names(tmp_path):
    with pytest.raises(DescriptionError, match="not valid TOML"):
        load_description(write(tmp_path, "name = "))
    with pytest.raises(DescriptionError, match="neither a description file nor a shipped material"):
        find_description("no-such-material")


def test_unsupported_and_non_finite_map_files(tmp_path):
    (tmp_path / "h.jpg").write_bytes(b"")
    with pytest.raises(images.ImageError, match="unsupported"):
        images.read_image(tmp_path / "h.jpg")
    np.save(tmp_path / "nan.npy", np.full((4, 4), np.nan))
    with pytest.raises(images.ImageError, match="non-finite"):
        images.read_image(tmp_path / "nan.npy")


def test_periodic_resampling_keeps_values_and_wraps():
    arr = np.random.default_rng(2).random((8, 8)).astype(np.float32)
    np.testing.assert_array_equal(images.resample_periodic(arr, 8), arr)
    up = images.resample_periodic(arr, 16)
    # sample 0 of the upsampled map lies a quarter texel before texel 0's centre: it mixes in the last texel
    expected = 0.0625 * arr[7, 7] + 0.1875 * (arr[7, 0] + arr[0, 7]) + 0.5625 * arr[0, 0]
    assert up[0, 0] == pytest.approx(expected, rel=1e-5)
    assert up.mean() == pytest.approx(arr.mean(), rel=1e-5)
