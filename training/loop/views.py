"""Progress views: a few image grids of one tile (a few lights/views at a few levels of detail) that a
training run renders with its model and compares with ground truth as it goes.

`view_queries` is pure numpy. `trace_views` path-traces the ground truth once with the query tracer
(Mitsuba) and stores it as an ordinary data set folder, so a resumed run reuses it.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from neumip.core import contract as C

log = logging.getLogger(__name__)

VIEWS_GENERATOR = "progress views"
"""meta.json generator name of a progress-view data set (`trace_views`)."""


@dataclass(frozen=True)
class ViewGrid:
    """Which images the progress grid shows."""

    pixels: int = 32
    """Pixels per image side; the image covers one tile, pixel centres on a regular grid."""
    levels: tuple[int, ...] = (0, 2, 4)
    """Levels of detail shown (0 = finest), clamped to the material's pyramid."""
    views: tuple[tuple[float, float, float, float], ...] = (
        (0.0, 30.0, 0.0, 0.0),
        (180.0, 60.0, 0.0, 30.0),
        (0.0, 80.0, 180.0, 45.0),
    )
    """(light azimuth, light zenith, view azimuth, view zenith) in degrees, one image row each; the
    last is a low light (glints and long shadows)."""
    spp: int = 64
    """Path samples per pixel of the ground truth."""


def _direction_xy(azimuth: float, zenith: float) -> tuple[float, float]:
    a, z = np.radians(azimuth), np.radians(zenith)
    return float(np.sin(z) * np.cos(a)), float(np.sin(z) * np.sin(a))


def grid_levels(grid: ViewGrid, resolution: int) -> list[int]:
    """The grid's levels that exist on a pyramid of finest `resolution` (duplicates dropped)."""
    top = int(np.log2(resolution))
    return sorted({min(level, top) for level in grid.levels})


def view_queries(grid: ViewGrid, resolution: int) -> np.ndarray:
    """(views x levels x pixels^2, 7) float32 queries, image after image in row-major pixel order."""
    p = grid.pixels
    t = (np.arange(p) + 0.5) / p
    v, u = np.meshgrid(t, t, indexing="ij")
    blocks = []
    for light_az, light_zen, view_az, view_zen in grid.views:
        wi, wo = _direction_xy(light_az, light_zen), _direction_xy(view_az, view_zen)
        for level in grid_levels(grid, resolution):
            q = np.empty((p * p, C.QUERY_DIM), np.float32)
            q[:, C.U], q[:, C.V] = u.ravel(), v.ravel()
            q[:, C.SIGMA] = C.sigma_for_level(level, resolution) if level > 0 else 0.0
            q[:, C.WI_X], q[:, C.WI_Y] = wi
            q[:, C.WO_X], q[:, C.WO_Y] = wo
            blocks.append(q)
    return np.concatenate(blocks)


def images(values: np.ndarray, grid: ViewGrid, resolution: int) -> np.ndarray:
    """(views x levels x pixels^2, 3) values in `view_queries` order -> (views, levels, p, p, 3)."""
    p = grid.pixels
    return values.reshape(len(grid.views), len(grid_levels(grid, resolution)), p, p, C.RGB_DIM)


def data_material(material_meta: dict, description: str | Path | None = None,
                  base_dir: str | Path | None = None):
    """The `MaterialDescription` of a data set: `description` (a library name or .toml path) if
    given, else the one its meta.json holds (`material_meta`, its relative map paths resolved against
    `base_dir`: the description file's folder, meta.json's ``description_dir``). Raises
    DescriptionError when it cannot be rebuilt (map files moved) or its map files hash otherwise than
    the data's."""
    from neumip.groundtruth.description import DescriptionError, MaterialDescription, find_description

    if description is not None:
        desc = find_description(description)
    elif isinstance(material_meta, dict) and material_meta:
        desc = MaterialDescription.from_dict({k: v for k, v in material_meta.items() if k != "map_sha256"},
                                             base_dir=base_dir)
    else:
        raise DescriptionError("the data set does not describe its material")
    hashes = desc.to_dict().get("map_sha256")
    if isinstance(material_meta, dict) and material_meta and hashes != material_meta.get("map_sha256"):
        raise DescriptionError(f"the map files of {desc.name!r} differ from the training data's")
    return desc


def data_geometry(data: str | Path, material: str | None = None):
    """The `Microgeometry` (maps) of a data set's material, rebuilt from its meta.json (or of `material`, a
    name or description file, when given)."""
    from neumip.groundtruth.dataset import open_dataset
    from neumip.groundtruth.description import resolve

    meta = open_dataset(data).meta
    return resolve(data_material(meta.get("material") or {}, material or None, meta.get("description_dir")))


def trace_views(material_meta: dict, grid: ViewGrid, resolution: int, out: str | Path,
                description: str | Path | None = None, base_dir: str | Path | None = None):
    """Ground truth of the view grid, traced once into the data set folder `out` (reused when it holds
    the same queries). The material is `description` (a library name or .toml path) if given, else
    the one a data set's meta.json describes (`material_meta`, its relative map paths resolved against
    `base_dir`: the description's folder, meta.json's ``description_dir``); its map files must hash as
    in `material_meta`. Returns the opened data set, or None (logged) when the material cannot be
    rebuilt, e.g. map files moved or changed since: then the grid shows the model only.
    """
    from neumip.groundtruth.dataset import open_dataset, write_dataset
    from neumip.groundtruth.description import DescriptionError, resolve
    from neumip.groundtruth.tracer import QueryTracer

    out = Path(out)
    material_meta = material_meta if isinstance(material_meta, dict) else {}
    if description is None and not material_meta:
        log.info("the data set does not describe its material: the progress grid shows the model only")
        return None
    queries = view_queries(grid, resolution)
    if (out / "meta.json").exists():
        try:
            data = open_dataset(out)
            if data.queries.shape == queries.shape and np.array_equal(np.asarray(data.queries), queries):
                return data
        except Exception as exc:  # a stale or broken cache: trace again
            log.warning("progress views at %s unusable (%s): tracing them again", out, exc)
    try:
        geo = resolve(data_material(material_meta, description, base_dir))
    except (DescriptionError, OSError, ValueError, TypeError) as exc:
        log.warning("no ground truth for the progress grid (%s): it shows the model only; "
                    "--views-material PATH.toml names the material's description file", exc)
        return None
    rgb = QueryTracer(geo).estimate(queries, grid.spp, seed=1)
    meta = {"material": material_meta, "generator": {"name": VIEWS_GENERATOR, "spp": grid.spp}}
    clear_stale_views(out)
    return write_dataset(out, queries, rgb, meta)


def clear_stale_views(out: Path) -> None:
    """Remove the data set files of another grid's progress views at `out` (a model of another resolution traced
    there: same count, same meta, other queries), so they are written anew; anything else there is left alone."""
    from neumip.groundtruth.dataset import remove_dataset

    try:
        stale = json.loads((out / "meta.json").read_text())["generator"]["name"] == VIEWS_GENERATOR
    except (OSError, ValueError, KeyError, TypeError):
        return
    if stale:
        remove_dataset(out)
