"""Material descriptions: a small TOML file describing one periodic tile of microgeometry.

The user guide, with every key's units and a worked example, is MATERIALS.md beside this file. Format (every key but ``name`` optional; paths are relative to the file)::

    name = "yarn"                 # identifier (defaults to the file name)
    summary = "plain-woven yarn"  # one line for listings
    resolution = 256              # heightfield samples per tile side (the mesh has 2 R^2 triangles per tile)
    height_scale = 0.05           # tile units per unit of the height map (height 1 -> 0.05 tile)
    normals = "smooth"            # "smooth" (from the height gradient) or "flat" (facet normals)
    specular = 0.5                # principled BSDF specular (a constant: Mitsuba does not texture it)

    [procedural]                  # maps from a generator (neumip.groundtruth.procedural)
    generator = "yarn"
    seed = 1
    threads = 6                   # any further keys are the generator's parameters

    [maps]                        # maps from files or constants; they override the generator's
    height = "height.png"         # .png (8/16 bit, [0, 1]), .exr or .npy; the whole map is periodic
    base_color = { file = "albedo.png", srgb = true }   # PNG colour maps are sRGB by default
    roughness = 0.6               # a constant in [0, 1]
    metallic = "metal.npy"

    [bsdf]                        # or: a homogeneous Mitsuba BSDF (a mi.load_dict dictionary)
    type = "diffuse"              # replaces the principled maps; height may still be given
    reflectance = { type = "rgb", value = [0.5, 0.5, 0.5] }

Geometry convention: the tile spans ``[0, 1)^2`` of the local xy plane (x along +u, y along +v), the
height map is ``height_scale * map`` shifted so that its **maximum is 0**: the reference plane of the
MBTF is the top of the microgeometry, and all geometry lies below it. Without a height map the
material is a flat plane. Reflectance maps may have any resolution (they become Mitsuba bitmaps with
``repeat`` wrapping); a height map of another size is resampled (bilinear, periodic) to ``resolution``.
"""

from __future__ import annotations

import hashlib
import json
import logging
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from neumip.core.errors import NeumipError

from neumip.groundtruth import images
from neumip.groundtruth.procedural import GENERATORS

log = logging.getLogger(__name__)

MAP_NAMES = ("height", "base_color", "roughness", "metallic")
"""Maps a description may give in its ``[maps]`` table."""

_TOP_KEYS = {"name", "summary", "resolution", "height_scale", "normals", "specular", "procedural", "maps", "bsdf"}
LIBRARY = "neumip.groundtruth.library"
"""Package holding the shipped descriptions (``<name>.toml``)."""


class DescriptionError(NeumipError, ValueError):
    """A material description that is malformed or refers to missing data."""


@dataclass
class MaterialDescription:
    """A parsed material description (see the module docstring for the file format)."""

    name: str
    """Identifier of the material."""
    summary: str = ""
    """One-line description for listings and metadata."""
    resolution: int = 256
    """Heightfield samples per tile side."""
    height_scale: float = 0.05
    """Tile units per unit of the height map."""
    normals: str = "smooth"
    """Shading normals of the heightfield mesh: "smooth" or "flat"."""
    specular: float = 0.5
    """Constant specular of the principled BSDF."""
    procedural: dict[str, Any] | None = None
    """``{"generator": name, "seed": int, **params}`` or None."""
    maps: dict[str, Any] = field(default_factory=dict)
    """Map name -> file path, ``{file, srgb}`` table, or constant (number or RGB list)."""
    bsdf: dict[str, Any] | None = None
    """Homogeneous Mitsuba BSDF dictionary replacing the principled maps, or None."""
    base_dir: Path | None = None
    """Folder that relative map paths are resolved against."""

    def __post_init__(self) -> None:
        self._validate()

    @classmethod
    def from_dict(cls, data: dict[str, Any], base_dir: str | Path | None = None) -> "MaterialDescription":
        unknown = set(data) - _TOP_KEYS
        if unknown:
            raise DescriptionError(f"unknown keys {sorted(unknown)}; allowed: {sorted(_TOP_KEYS)}")
        if "name" not in data:
            raise DescriptionError("a material description needs a 'name'")
        kwargs = {k: data[k] for k in _TOP_KEYS if k in data}
        return cls(**kwargs, base_dir=Path(base_dir) if base_dir is not None else None)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form, with a content hash of every map file (identifies the data in metadata)."""
        out: dict[str, Any] = {
            "name": self.name,
            "summary": self.summary,
            "resolution": self.resolution,
            "height_scale": self.height_scale,
            "normals": self.normals,
            "specular": self.specular,
            "procedural": self.procedural,
            "maps": self.maps,
            "bsdf": self.bsdf,
        }
        hashes = {k: _sha256(self._path(spec)) for k, spec in self.maps.items() if _file_of(spec)}
        if hashes:
            out["map_sha256"] = hashes
        return json.loads(json.dumps(out))

    # --- validation ----------------------------------------------------------------------------------

    def _validate(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise DescriptionError("'name' must be a non-empty string")
        if not isinstance(self.resolution, int) or not 1 <= self.resolution <= 4096:
            raise DescriptionError(f"'resolution' must be an integer in [1, 4096], got {self.resolution!r}")
        if not isinstance(self.height_scale, (int, float)) or not 0 <= self.height_scale <= 10:
            raise DescriptionError(f"'height_scale' must be a number in [0, 10] tile units, got {self.height_scale!r}")
        if self.normals not in ("smooth", "flat"):
            raise DescriptionError(f"'normals' must be 'smooth' or 'flat', got {self.normals!r}")
        if not isinstance(self.specular, (int, float)) or not 0 <= self.specular <= 1:
            raise DescriptionError(f"'specular' must be in [0, 1], got {self.specular!r}")
        if self.procedural is not None:
            generator = self.procedural.get("generator")
            if generator not in GENERATORS:
                raise DescriptionError(f"unknown generator {generator!r}; known: {sorted(GENERATORS)}")
        unknown = set(self.maps) - set(MAP_NAMES)
        if unknown:
            raise DescriptionError(f"unknown maps {sorted(unknown)}; allowed: {list(MAP_NAMES)}")
        for name, spec in self.maps.items():
            self._check_map_spec(name, spec)
        if self.bsdf is not None:
            if not isinstance(self.bsdf, dict) or "type" not in self.bsdf:
                raise DescriptionError("[bsdf] must be a table with a 'type' (a Mitsuba BSDF plugin)")
            clash = set(self.maps) - {"height"}
            if clash:
                raise DescriptionError(f"[bsdf] replaces the principled maps; remove maps {sorted(clash)}")

    def _check_map_spec(self, name: str, spec: Any) -> None:
        path = _file_of(spec)
        if path is not None:
            if not self._path(spec).is_file():
                raise DescriptionError(f"map '{name}': file {self._path(spec)} does not exist")
            return
        if name == "height":
            raise DescriptionError("map 'height' must be a file (use height_scale = 0 for a flat plane)")
        values = np.atleast_1d(np.asarray(spec, dtype=object))
        ok = values.size in ((1, 3) if name == "base_color" else (1,)) and all(
            isinstance(x, (int, float)) and 0 <= x <= 1 for x in values
        )
        if not ok:
            raise DescriptionError(f"map '{name}': expected a file name or a constant in [0, 1], got {spec!r}")

    def _path(self, spec: Any) -> Path:
        path = Path(_file_of(spec))
        return path if path.is_absolute() or self.base_dir is None else self.base_dir / path


def _file_of(spec: Any) -> str | None:
    if isinstance(spec, str):
        return spec
    if isinstance(spec, dict):
        if "file" not in spec or set(spec) - {"file", "srgb"}:
            raise DescriptionError(f"a map table takes 'file' and optionally 'srgb', got {spec!r}")
        return spec["file"]
    return None


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --- loading ---------------------------------------------------------------------------------------


def _parse_toml(text: str, origin: str) -> dict[str, Any]:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DescriptionError(f"{origin}: not valid TOML: {exc}") from None


def load_description(path: str | Path) -> MaterialDescription:
    """Parse a description file; its name defaults to the file name."""
    path = Path(path)
    if not path.is_file():
        raise DescriptionError(f"material description {path} does not exist")
    data = _parse_toml(path.read_text(), str(path))
    data.setdefault("name", path.stem)
    return MaterialDescription.from_dict(data, base_dir=path.parent)


def library_names() -> list[str]:
    """Names of the shipped materials."""
    folder = resources.files(LIBRARY)
    return sorted(p.name[: -len(".toml")] for p in folder.iterdir() if p.name.endswith(".toml"))


def find_description(name_or_path: str | Path) -> MaterialDescription:
    """A description from a file path, or a shipped material by name (``yarn``, ``rock``, ...)."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.is_file():
        return load_description(path)
    resource = resources.files(LIBRARY) / f"{name_or_path}.toml"
    if not resource.is_file():
        raise DescriptionError(
            f"{name_or_path!r} is neither a description file nor a shipped material "
            f"({', '.join(library_names())})"
        )
    with resources.as_file(resource) as file:
        return load_description(file)


# --- resolving into arrays -------------------------------------------------------------------------


@dataclass
class Microgeometry:
    """A description resolved into arrays: what the mesh builder and the tracer use."""

    height: np.ndarray
    """(R, R) float32 heights in tile units, maximum 0 (the reference plane is the top)."""
    base_color: np.ndarray
    """(H, W, 3) float32 linear base colour."""
    roughness: np.ndarray
    """(H, W) float32 principled roughness."""
    metallic: np.ndarray
    """(H, W) float32 principled metallic."""
    specular: float
    """Constant principled specular."""
    bsdf: dict[str, Any] | None
    """Homogeneous Mitsuba BSDF dictionary, or None for the principled maps."""
    normals: str
    """"smooth" or "flat" shading normals."""

    @property
    def depth(self) -> float:
        """Height range of the microgeometry in tile units."""
        return max(0.0, float(-self.height.min()))


def resolve(desc: MaterialDescription) -> Microgeometry:
    """Build the maps of a description: run its generator, then apply the ``[maps]`` overrides."""
    res = desc.resolution
    maps: dict[str, np.ndarray] = {}
    if desc.procedural is not None:
        params = {k: v for k, v in desc.procedural.items() if k not in ("generator", "seed")}
        rng = np.random.default_rng(desc.procedural.get("seed", 0))
        try:
            maps = GENERATORS[desc.procedural["generator"]](res, rng, **params)
        except TypeError as exc:
            raise DescriptionError(f"[procedural] of {desc.name!r}: {exc}") from None
    for name, spec in desc.maps.items():
        maps[name] = _load_map(desc, name, spec)
    if "height" in maps:
        height = images.resample_periodic(images.as_gray(maps["height"], "height"), res) * desc.height_scale
    else:
        height = np.zeros((1, 1), np.float32)
    height = (height - height.max()).astype(np.float32)
    return Microgeometry(
        height=height,
        base_color=images.as_rgb(maps.get("base_color", np.full((1, 1, 3), 0.5, np.float32))),
        roughness=images.as_gray(maps.get("roughness", np.full((1, 1), 0.5, np.float32)), "roughness"),
        metallic=images.as_gray(maps.get("metallic", np.zeros((1, 1), np.float32)), "metallic"),
        specular=float(desc.specular),
        bsdf=desc.bsdf,
        normals=desc.normals,
    )


def _load_map(desc: MaterialDescription, name: str, spec: Any) -> np.ndarray:
    file = _file_of(spec)
    if file is None:
        value = np.asarray(spec, dtype=np.float32)
        return value.reshape(1, 1, -1) if value.size == 3 else value.reshape(1, 1)
    path = desc._path(spec)
    srgb_default = name == "base_color" and path.suffix.lower() == ".png"
    srgb = spec.get("srgb", srgb_default) if isinstance(spec, dict) else srgb_default
    try:
        arr = images.read_image(path, srgb=srgb)
    except images.ImageError as exc:
        raise DescriptionError(f"map '{name}': {exc}") from None
    log.debug("map %s from %s: shape %s", name, path, arr.shape)
    return arr
