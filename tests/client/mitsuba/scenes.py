"""Small test scenes (dicts and XML) shared by the Mitsuba tests."""

from __future__ import annotations

import numpy as np

from neumip.client.mitsuba.bsdf import mi

LAMBERT = {"type": "neumip", "material": "lambert", "uv_scale": 2.0}
"""The fixture material answering 0.5 / pi everywhere."""
DIFFUSE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}
"""What LAMBERT must render like."""

WIDTH, DISTANCE, FOV = 32, 3.0, 30.0
"""`facing_plane`'s film width (pixels), camera distance and field of view (degrees)."""


def _look_at(origin, target):
    return mi.ScalarTransform4f().look_at(origin=origin, target=target, up=[0, 1, 0])


def facing_plane(uv_scale: float, rfilter: str = "gaussian") -> dict:
    """A 2 x 2 rectangle (uv 0..1) seen head-on from DISTANCE, filling the view."""
    return {
        "type": "scene",
        "integrator": {"type": "neumip_path", "max_depth": 2},
        "sensor": {
            "type": "perspective", "fov": FOV,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, DISTANCE], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": WIDTH, "height": WIDTH, "rfilter": {"type": rfilter}},
        },
        "sky": {"type": "constant"},
        "plane": {"type": "rectangle", "bsdf": {"type": "neumip", "material": "lambert", "uv_scale": uv_scale}},
    }


def simple(bsdf: dict, integrator: dict, size: int = 48, spp: int = 64) -> dict:
    """A floor and a sphere, both with `bsdf`, under an area light and a constant sky."""
    return {
        "type": "scene",
        "integrator": integrator,
        "sensor": {
            "type": "perspective",
            "fov": 40,
            "to_world": _look_at([0, 3, 4], [0, 0.3, 0]),
            "film": {"type": "hdrfilm", "width": size, "height": size},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "light": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([0, 4, 0]).rotate([1, 0, 0], 90),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 5.0}},
        },
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.3}},
        "floor": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(3),
            "bsdf": bsdf,
        },
        "ball": {"type": "sphere", "center": [0, 0.7, 0], "radius": 0.7, "bsdf": bsdf},
    }


def mixed(bsdf: dict, integrator: dict, size: int = 48, spp: int = 64) -> dict:
    """`bsdf` on a sphere among diffuse, conductor and dielectric objects; area light + sky."""
    scene = simple(DIFFUSE, integrator, size, spp)
    scene["floor"]["bsdf"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.3, 0.5, 0.2]}}
    scene["ball"] = {"type": "sphere", "center": [-0.8, 0.5, 0], "radius": 0.5, "bsdf": bsdf}
    scene["metal"] = {
        "type": "sphere", "center": [0.8, 0.5, 0], "radius": 0.5,
        "bsdf": {"type": "roughconductor", "material": "Cu", "alpha": 0.2},
    }
    scene["glass"] = {
        "type": "sphere", "center": [0, 0.4, 1.0], "radius": 0.4,
        "bsdf": {"type": "dielectric", "int_ior": 1.5},
    }
    return scene


SCENE_XML = """<scene version="3.0.0">
    <default name="spp" value="16"/>
    <integrator type="neumip_path"/>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world"><lookat origin="0, 3, 4" target="0, 0.3, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
        <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="32"/></film>
    </sensor>
    <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
    <shape type="rectangle">
        <transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/></transform>
        <bsdf type="diffuse"/>
    </shape>
    <shape type="sphere">
        <point name="center" x="-0.6" y="0.5" z="0"/><float name="radius" value="0.5"/>
        <bsdf type="neumip"><string name="material" value="{a}"/><float name="uv_scale" value="2"/></bsdf>
    </shape>
    <shape type="sphere">
        <point name="center" x="0.6" y="0.5" z="0"/><float name="radius" value="0.5"/>
        <bsdf type="neumip"><string name="material" value="{b}"/><float name="uv_scale" value="3"/></bsdf>
    </shape>
</scene>
"""
"""An XML scene with two neural spheres (materials `{a}`, `{b}`) on a diffuse floor."""


def write_xml(folder, a: str = "lambert", b: str = "rand16") -> str:
    path = folder / "scene.xml"
    path.write_text(SCENE_XML.replace("{a}", a).replace("{b}", b))
    return str(path)


BLOCK = 8
"""Side of the blocks whose means the known-answer renders compare."""
MAX_DEPTH = 6
"""Path depth of the known-answer renders."""


def block_means(image: np.ndarray) -> np.ndarray:
    """(H, W, C) -> (H/BLOCK, W/BLOCK, 3) block means."""
    h, w = image.shape[0] // BLOCK, image.shape[1] // BLOCK
    rgb = image[: h * BLOCK, : w * BLOCK, :3]
    return rgb.reshape(h, BLOCK, w, BLOCK, 3).mean(axis=(1, 3))


def stock(scene_fn, bsdf, seed: int) -> np.ndarray:
    scene = mi.load_dict(scene_fn(bsdf, {"type": "path", "max_depth": MAX_DEPTH}))
    return np.array(mi.render(scene, spp=64, seed=seed))


def block_error(a: np.ndarray, b: np.ndarray) -> float:
    """Root-mean-square difference of the block means."""
    return float(np.sqrt(np.mean((block_means(a) - block_means(b)) ** 2)))
