"""The demo scene renders (small) with stand-ins for its four materials, each queried."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from neumip.client import cli
from neumip.engines.local import LocalMaterials
from neumip.client.mitsuba.bsdf import mi
from neumip.client.mitsuba.render import RenderConfig, load_scene, render_scene
from neumip.client.mitsuba.shading import scene_materials

DEMO = Path(__file__).resolve().parents[3] / "scenes" / "demo.xml"
NAMES = ["foam", "rock", "turtle", "yarn"]


def stand_ins(model_dir, folder: Path) -> Path:
    """The fixture's materials under the demo's names (test stand-ins, not trained materials)."""
    for name, source in zip(NAMES, ["lambert", "rand16", "flat16", "lambert"]):
        shutil.copy(model_dir / f"{source}.onnx", folder / f"{name}.onnx")
    return folder


def test_demo_uses_the_shipped_material_names():
    scene = load_scene(DEMO, resx="8", resy="8")
    assert scene_materials(scene) == NAMES
    kinds = {shape.bsdf().class_name() for shape in scene.shapes()}
    assert {"SmoothDiffuse", "RoughConductor", "SmoothDielectric"} <= kinds
    assert scene.emitters()  # area light and environment


@pytest.mark.parametrize("scene, param, replaced", [
    (DEMO, "cube", "rock"), (DEMO, "cylinder", "foam"), (DEMO, "left_sphere", "yarn"),
    (DEMO, "right_sphere", "turtle"), (DEMO.with_name("closeup.xml"), "material", "yarn"),
])
def test_scene_parameters_name_the_neural_materials(scene, param, replaced):
    """`-D cube=bricks` puts one's own material in the demo without editing XML; the others stay."""
    defaults = scene_materials(load_scene(scene, resx="8", resy="8"))
    mine = scene_materials(load_scene(scene, resx="8", resy="8", **{param: "bricks"}))
    assert mine == sorted(set(defaults) - {replaced} | {"bricks"})


def test_demo_renders_all_materials(model_dir, tmp_path):
    models = stand_ins(model_dir, tmp_path)
    scene = load_scene(DEMO, resx="64", resy="64")
    result = render_scene(scene, LocalMaterials(models), RenderConfig(spp=4))
    assert sorted(result.stats.per_material) == NAMES
    # foam sits on two shapes with different uv scales; still at most two calls (groups, single
    # queries) per material per bounce (max_depth 5: four bounces with shading), in one pass
    assert result.passes == 1 and result.stats.calls <= 2 * len(NAMES) * 4
    assert np.isfinite(result.image).all() and result.image.mean() > 0.05


def test_demo_command_line(model_dir, tmp_path, capsys):
    (tmp_path / "models").mkdir()
    models = stand_ins(model_dir, tmp_path / "models")
    out = tmp_path / "demo.png"
    rc = cli.main(["render", str(DEMO), "-o", str(out), "--models", str(models), "--spp", "2",
                   "-D", "resx=48", "-D", "resy=32"])
    assert rc == 0
    assert "s total" in capsys.readouterr().out
    assert np.array(mi.Bitmap(str(out))).shape[:2] == (32, 48)


SHIPPED = DEMO.parents[1] / "models"


@pytest.mark.skipif(
    not all((SHIPPED / f"{n}.onnx").exists() for n in NAMES),
    reason=f"the trained materials {', '.join(NAMES)} are not in models/ (bash models/make_models.sh)",
)
def test_demo_renders_with_the_shipped_materials():
    scene = load_scene(DEMO, resx="64", resy="64")
    result = render_scene(scene, LocalMaterials(SHIPPED), RenderConfig(spp=4))
    assert sorted(result.stats.per_material) == NAMES
    assert np.isfinite(result.image).all() and result.image.mean() > 0.05
