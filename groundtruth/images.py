"""Read texture maps from image files (PNG, EXR, NPY) as float32 arrays, and resample them periodically.

PNG (8 or 16 bit) is normalised to [0, 1]; colour maps stored in PNG are sRGB-encoded by convention
and are linearised when ``srgb`` is true. EXR (read through Mitsuba's ``Bitmap``) and NPY hold
linear floats and are returned as they are.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from neumip.core.errors import NeumipError


class ImageError(NeumipError, ValueError):
    """A map file that is missing, unreadable or has the wrong shape."""


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear values (same shape)."""
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def read_image(path: str | Path, *, srgb: bool = False) -> np.ndarray:
    """(H, W) or (H, W, C) float32 array from a .png, .exr or .npy file."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"map file {path} does not exist")
    suffix = path.suffix.lower()
    if suffix == ".npy":
        arr = np.load(path, allow_pickle=False).astype(np.float32)
    elif suffix == ".png":
        arr = _read_png(path)
    elif suffix == ".exr":
        arr = _read_exr(path)
    else:
        raise ImageError(f"map file {path}: unsupported format {suffix!r} (use .png, .exr or .npy)")
    if arr.ndim not in (2, 3) or min(arr.shape[:2]) < 1:
        raise ImageError(f"map file {path}: expected an (H, W) or (H, W, C) image, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ImageError(f"map file {path} holds non-finite values")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    return srgb_to_linear(np.clip(arr, 0, 1)) if srgb else arr


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image

    with Image.open(path) as img:
        if img.mode in ("I;16", "I;16B", "I"):
            return np.asarray(img, dtype=np.float32) / 65535.0
        if img.mode not in ("L", "RGB", "RGBA", "LA"):
            img = img.convert("RGB")
        arr = np.asarray(img, dtype=np.float32) / 255.0
    if arr.ndim == 3 and arr.shape[2] in (2, 4):  # drop alpha
        arr = arr[:, :, :-1]
    return arr


def _read_exr(path: Path) -> np.ndarray:
    from neumip.client.mitsuba.runtime import import_mitsuba

    mi = import_mitsuba()
    try:
        bitmap = mi.Bitmap(str(path))
    except RuntimeError as exc:
        raise ImageError(f"map file {path} could not be read: {exc}") from None
    return np.array(bitmap, dtype=np.float32)


def as_gray(arr: np.ndarray, what: str) -> np.ndarray:
    """(H, W) from an (H, W) map or the mean of an (H, W, 3) map (a grey image saved as RGB)."""
    if arr.ndim == 2:
        return arr
    if arr.shape[2] >= 3:
        return arr[:, :, :3].mean(axis=2)
    raise ImageError(f"{what}: expected a one-channel map, got shape {arr.shape}")


def as_rgb(arr: np.ndarray) -> np.ndarray:
    """(H, W, 3) from an (H, W) or (H, W, >=3) map."""
    if arr.ndim == 2:
        return np.repeat(arr[:, :, None], 3, axis=2)
    return np.ascontiguousarray(arr[:, :, :3])


def resample_periodic(arr: np.ndarray, resolution: int) -> np.ndarray:
    """Bilinear resampling of a periodic (H, W) map to (resolution, resolution), samples at texel centres."""
    h, w = arr.shape
    if (h, w) == (resolution, resolution):
        return arr.astype(np.float32)
    centres = (np.arange(resolution) + 0.5) / resolution
    rows, cols = centres * h - 0.5, centres * w - 0.5
    r0, c0 = np.floor(rows).astype(int), np.floor(cols).astype(int)
    fr, fc = (rows - r0)[:, None], (cols - c0)[None, :]
    r0, r1 = r0 % h, (r0 + 1) % h
    c0, c1 = c0 % w, (c0 + 1) % w
    top = arr[np.ix_(r0, c0)] * (1 - fc) + arr[np.ix_(r0, c1)] * fc
    bottom = arr[np.ix_(r1, c0)] * (1 - fc) + arr[np.ix_(r1, c1)] * fc
    return (top * (1 - fr) + bottom * fr).astype(np.float32)
