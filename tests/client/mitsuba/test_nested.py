"""A `neumip` BSDF wrapped in another BSDF (twosided, blendbsdf) is refused when the scene loads."""

from __future__ import annotations

import pytest

from neumip.engines.local import LocalMaterials
from neumip.client.mitsuba.bsdf import mi
from neumip.client.mitsuba.render import RenderConfig, RenderError, load_scene, render_scene
from neumip.client.mitsuba.shading import NestedNeuralBSDF

from .scenes import LAMBERT, SCENE_XML, simple

TWOSIDED = '<bsdf type="twosided"><bsdf type="neumip"><string name="material" value="lambert"/></bsdf></bsdf>'


def test_twosided_neumip_in_xml_is_refused_at_load(tmp_path):
    xml = SCENE_XML.replace("{b}", "rand16")
    start = xml.index('<bsdf type="neumip"><string name="material" value="{a}"/>')
    end = xml.index("</bsdf>", start) + len("</bsdf>")
    path = tmp_path / "scene.xml"
    path.write_text(xml[:start] + TWOSIDED + xml[end:])
    with pytest.raises(RenderError, match="neumip BSDF inside TwoSided.* is not supported"):
        load_scene(path)


@pytest.mark.parametrize("wrapper", ["twosided", "blendbsdf"])
def test_wrapped_neumip_in_a_dict_scene_is_refused_at_render(model_dir, wrapper):
    scene = simple(LAMBERT, {"type": "neumip_path"}, size=8, spp=1)
    if wrapper == "twosided":
        scene["ball"]["bsdf"] = {"type": "twosided", "inner": LAMBERT}
    else:
        scene["ball"]["bsdf"] = {"type": "blendbsdf", "weight": 0.5, "a": LAMBERT, "b": {"type": "diffuse"}}
    with pytest.raises(NestedNeuralBSDF, match="attach <bsdf type=\"neumip\"> to the shape directly"):
        render_scene(mi.load_dict(scene), LocalMaterials(model_dir), RenderConfig(spp=1))


def test_twosided_stock_bsdf_is_fine(model_dir):
    scene = simple(LAMBERT, {"type": "neumip_path"}, size=8, spp=1)
    scene["floor"]["bsdf"] = {"type": "twosided", "inner": {"type": "diffuse"}}
    result = render_scene(mi.load_dict(scene), LocalMaterials(model_dir), RenderConfig(spp=1))
    assert result.stats.queries > 0
