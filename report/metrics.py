"""Image metrics against the reference: MSE, FLIP, SSIM, mean and highlight brightness, bias versus noise.

Every method's image goes through the same tone mapping (:func:`tonemap`, its exposure fixed by the
reference) before FLIP and SSIM; MSE and the brightness ratio are on linear RGB.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from neumip.core import contract as C

MIDDLE_GREY = 0.25
"""Linear value the reference's mean luminance is mapped to before the sRGB curve."""


def luminance(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear RGB -> (H, W) luminance (Rec. 709)."""
    r, g, b = C.LUMINANCE
    return img[..., 0] * r + img[..., 1] * g + img[..., 2] * b


def exposure_for(reference: np.ndarray) -> float:
    """Exposure that maps the reference's mean luminance to :data:`MIDDLE_GREY`."""
    return MIDDLE_GREY / max(float(luminance(reference).mean()), 1e-8)


def tonemap(img: np.ndarray, exposure: float) -> np.ndarray:
    """(H, W, 3) linear -> (H, W, 3) float32 display values in [0, 1]: exposure, clip, sRGB curve."""
    x = np.clip(img[..., :3] * exposure, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def mse(a: np.ndarray, b: np.ndarray) -> float:
    """Linear-RGB mean squared error."""
    d = a[..., :3].astype(np.float64) - b[..., :3]
    return float(np.mean(d * d))


def flip_map(reference_ldr: np.ndarray, test_ldr: np.ndarray) -> tuple[np.ndarray, float]:
    """LDR-FLIP of two tone-mapped (H, W, 3) images: ((H, W) error map in [0, 1], mean error).

    The map is FLIP's error itself (``applyMagma=False``; by default `flip.evaluate` returns it
    already coloured by magma, whose channels are not the error); the mean error is its mean."""
    import flip_evaluator as flip

    error_map, mean, _ = flip.evaluate(
        np.ascontiguousarray(reference_ldr, np.float32), np.ascontiguousarray(test_ldr, np.float32), "LDR",
        applyMagma=False,
    )
    error_map = np.asarray(error_map, np.float32).reshape(reference_ldr.shape[:2])
    return error_map, float(mean)


def ssim(reference_ldr: np.ndarray, test_ldr: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    win = min(7, *reference_ldr.shape[:2])
    win -= 1 - win % 2  # odd
    return float(structural_similarity(reference_ldr, test_ldr, channel_axis=2, data_range=1.0, win_size=win))


@dataclass
class Scores:
    """A method's image against the reference."""

    mse: float
    """Linear-RGB MSE."""
    flip: float
    """Mean LDR-FLIP after the shared tone mapping."""
    ssim: float
    """SSIM after the shared tone mapping."""
    mean_ratio: float
    """Mean luminance of the image / the reference's."""
    p99_ratio: float
    """99th-percentile luminance of the image / the reference's (do the highlights survive?)."""

    def to_dict(self) -> dict:
        return asdict(self)


def score(reference: np.ndarray, image: np.ndarray, exposure: float) -> tuple[Scores, np.ndarray]:
    """Scores of ``image`` against ``reference`` and the FLIP error map."""
    ref_ldr, img_ldr = tonemap(reference, exposure), tonemap(image, exposure)
    fmap, fmean = flip_map(ref_ldr, img_ldr)
    lum, ref_lum = luminance(image), luminance(reference)
    ratio = float(lum.mean() / max(ref_lum.mean(), 1e-12))
    p99 = float(np.percentile(lum, 99) / max(np.percentile(ref_lum, 99), 1e-12))
    return Scores(mse(reference, image), fmean, ssim(ref_ldr, img_ldr), ratio, p99), fmap


def noise_mse(a: np.ndarray, b: np.ndarray) -> float:
    """Noise (MSE) of one image, from two renders with different seeds: MSE(a, b) / 2."""
    return mse(a, b) / 2


def bias_noise(error: float, noise: float, reference_noise: float) -> dict:
    """Split an error against the reference into the method's noise, the reference's noise and the
    rest (bias squared): ``error = bias + noise + reference_noise`` for independent renders."""
    return {"noise": noise, "reference_noise": reference_noise, "bias": max(error - noise - reference_noise, 0.0)}
