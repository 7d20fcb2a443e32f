"""The render with in-kernel evaluation (`engines/kernel.py`) matches the buffered render (ONNX
Runtime); the evaluation itself is tested in tests/engines/test_kernel.py."""

from __future__ import annotations

import numpy as np
import pytest

from neumip.engines.local import LocalMaterials

pytest.importorskip("mitsuba")

from neumip.engines.kernel import KernelMaterial, KernelMaterials, namespace_of  # noqa: E402
from neumip.client.mitsuba.render import RenderConfig, mi, render_scene  # noqa: E402

from .scenes import simple  # noqa: E402


def test_a_render_in_kernel_matches_the_buffered_render(model_dir):
    """The same scene (two neural materials, several bounces), seed and spp rendered with the answers
    computed in the kernel and by ONNX Runtime: the images agree to the answers' own difference."""
    images, stats, kernel = {}, {}, KernelMaterials(model_dir, backend=namespace_of(mi.Float))
    for name, evaluator in (("kernel", kernel), ("onnxruntime", LocalMaterials(model_dir))):
        scene = simple({"type": "neumip", "material": "rand16", "uv_scale": 2.0}, {"type": "neumip_path"}, 24, 4)
        scene["floor"]["bsdf"] = {"type": "neumip", "material": "flat16", "uv_scale": 3.0}
        result = render_scene(mi.load_dict(scene), evaluator, RenderConfig(spp=4, seed=3))
        images[name], stats[name] = result.image[..., :3], result.stats
    assert images["onnxruntime"].mean() > 0.01
    np.testing.assert_allclose(images["kernel"], images["onnxruntime"], rtol=1e-4, atol=1e-5)
    assert stats["kernel"].queries >= stats["onnxruntime"].queries > 0  # every light of a lane is computed
    assert stats["kernel"].per_material.keys() == {"rand16", "flat16"}
    assert [kernel.kernel(m).traces for m in ("rand16", "flat16")] == [1, 1]  # every bounce replays it


def test_a_material_on_nearly_every_lane_is_computed_without_compaction(model_dir, monkeypatch):
    """A neural floor that fills the view around a small diffuse ball: the first bounce's kernel runs
    over the whole wavefront, the ball's lanes included (`shading.DENSE_LANES`, here a half), a later
    bounce's over its few compacted lanes, with one trace; the image still matches the buffered render."""
    import drjit as dr

    from neumip.client.mitsuba import shading

    from .scenes import DIFFUSE, _look_at

    monkeypatch.setattr(shading, "DENSE_LANES", 0.5)
    widths, answers = [], KernelMaterial.answers
    monkeypatch.setattr(KernelMaterial, "answers", lambda self, cols: widths.append(dr.width(cols[0])) or answers(self, cols))
    images, kernel = {}, KernelMaterials(model_dir, backend=namespace_of(mi.Float))
    for name, evaluator in (("kernel", kernel), ("onnxruntime", LocalMaterials(model_dir))):
        scene = simple({"type": "neumip", "material": "rand16", "uv_scale": 2.0},
                       {"type": "neumip_path", "max_depth": 3}, 32, 2)
        scene["sensor"]["to_world"] = _look_at([0, 1.0, 0.01], [0, 0, 0])  # straight down: the floor fills the view
        scene["ball"].update(center=[0, 0.4, 0.0], radius=0.1, bsdf=DIFFUSE)  # a few per cent of it
        images[name] = render_scene(mi.load_dict(scene), evaluator, RenderConfig(spp=2, seed=1)).image[..., :3]
    assert widths[0] == 32 * 32 * 2  # the whole wavefront, not only the floor's lanes
    assert 0 < min(widths) < widths[0] // 2  # a later bounce: compacted
    assert kernel.kernel("rand16").traces == 1
    assert images["onnxruntime"].mean() > 0.01
    np.testing.assert_allclose(images["kernel"], images["onnxruntime"], rtol=1e-4, atol=1e-5)


def test_a_foreign_lambertian_renders_in_kernel_like_stock_diffuse(tmp_path, checkerboard):
    """A material written with onnx.helper (scenes/checkerboard.py, both squares albedo 0.5, no neumip
    metadata) renders in the kernel like Mitsuba's own `diffuse` 0.5 with the stock `path`: with one
    seed the images agree closely (`neumip_path` draws its random numbers as `path` does, and chooses one
    emitter as it does)."""
    from .scenes import DIFFUSE, LAMBERT

    onnx_model = checkerboard(light=(0.5,) * 3, dark=(0.5,) * 3)
    (tmp_path / "lambert.onnx").write_bytes(onnx_model.SerializeToString())
    kernel = KernelMaterials(tmp_path, backend=namespace_of(mi.Float))
    integrator = {"type": "neumip_path", "max_depth": 4, "all_emitters": False}
    ours = render_scene(mi.load_dict(simple(LAMBERT, integrator)), kernel,
                        RenderConfig(spp=16, seed=7)).image
    reference = np.array(mi.render(mi.load_dict(simple(DIFFUSE, {"type": "path", "max_depth": 4})), spp=16, seed=7))
    assert reference.mean() > 0.01
    assert np.abs(ours - reference).mean() < 1e-3 * reference.mean()
