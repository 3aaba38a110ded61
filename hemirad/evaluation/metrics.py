"""Image error metrics against a reference: pure functions on numpy arrays, no rendering.

All images are (H, W, 3) linear RGB in the same units (``reference.radiance_view`` puts a
solution in the reference's). Errors are taken over *surface pixels* only (``surface_mask``):
pixels fully covered by geometry and away from emitters. Emitters are excluded because a
display saturates them and their value is the input, not the answer; partly covered
silhouette pixels against the background are excluded because they measure antialiasing,
not light transport.

* ``relative_mse``: sum (x - r)^2 / sum r^2 over surface pixels and channels: the squared
  error as a fraction of the reference's energy (a normalised MSE; dark pixels cannot blow
  it up).
* ``mean_relative_error``: mean over surface pixels and channels of |x - r| / (r + eps_c),
  eps_c = 1% of the channel's mean reference value (so a near-black channel, like green on
  the Cornell box's red wall, does not dominate).
* ``ssim``: scikit-image's structural similarity of the tone-mapped images (``tone_map``:
  both with the same fixed exposure taken from the reference, then sRGB), averaged over the
  surface pixels.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.metrics import structural_similarity

from hemirad.core.colour import REC709_LUMINANCE
from hemirad.output.display import MIDDLE_GREY, srgb_encode

#: eps_c of ``mean_relative_error`` as a fraction of the channel's mean reference value.
RELATIVE_ERROR_FLOOR = 0.01


def surface_mask(geometry: np.ndarray, emitter: np.ndarray, margin: int = 1) -> np.ndarray:
    """(H, W) bool: pixels fully on geometry and at least ``margin`` pixels from any emitter.

    Args:
        geometry, emitter: (H, W) covered fractions, as ``reference.coverage`` gives them.
        margin: the emitter pixels are grown by this many pixels (8-connected) first, so
            that emitter edges, where the two images' sampling of a saturated step differ,
            are left out.
    """
    covered = np.asarray(geometry) >= 1.0 - 1e-6
    lit = np.asarray(emitter) > 0.0
    if margin > 0:
        lit = ndimage.binary_dilation(lit, structure=np.ones((3, 3), bool), iterations=margin)
    return covered & ~lit


def luminance(image: np.ndarray) -> np.ndarray:
    """(..., 3) linear RGB -> (...) Rec. 709 relative luminance."""
    return np.asarray(image, dtype=np.float64) @ np.asarray(REC709_LUMINANCE)


def reference_exposure(reference: np.ndarray, mask: np.ndarray) -> float:
    """Display value per unit of the reference: its mean surface luminance to middle grey
    (the same rule as ``display.auto_exposure``, but fixed by the reference, so that both
    images get the same one and a darker solution looks darker)."""
    mean = float(luminance(reference)[mask].mean())
    if not (np.isfinite(mean) and mean > 0):
        raise ValueError("the reference has no lit surface pixel")
    return MIDDLE_GREY / mean


def tone_map(image: np.ndarray, exposure: float) -> np.ndarray:
    """(H, W, 3) linear -> float64 sRGB in [0, 1]: scale, clip, sRGB transfer function."""
    scaled = np.clip(np.nan_to_num(np.asarray(image, dtype=np.float64) * exposure), 0.0, 1.0)
    return srgb_encode(scaled)


def ssim(reference: np.ndarray, image: np.ndarray, mask: np.ndarray, exposure: float | None = None) -> float:
    """Mean SSIM over the surface pixels of the two tone-mapped images.

    Args:
        reference, image: (H, W, 3) linear RGB.
        mask: (H, W) bool, the pixels to average the SSIM map over.
        exposure: of both tone mappings; default ``reference_exposure(reference, mask)``.

    Returns:
        SSIM in [-1, 1]; 1 for identical images. scikit-image's defaults (7 x 7 uniform
        window, K1 = 0.01, K2 = 0.03), data range 1, per channel then averaged.
    """
    if exposure is None:
        exposure = reference_exposure(reference, mask)
    _, full = structural_similarity(tone_map(reference, exposure), tone_map(image, exposure),
                                    channel_axis=-1, data_range=1.0, full=True)
    return float(full.mean(axis=-1)[mask].mean())


def relative_mse(reference: np.ndarray, image: np.ndarray, mask: np.ndarray) -> float:
    """sum (x - r)^2 / sum r^2 over the masked pixels and all channels (linear values)."""
    r = np.asarray(reference, dtype=np.float64)[mask]
    x = np.asarray(image, dtype=np.float64)[mask]
    return float(((x - r) ** 2).sum() / (r ** 2).sum())


def mean_relative_error(reference: np.ndarray, image: np.ndarray, mask: np.ndarray) -> float:
    """Mean over masked pixels and channels of |x - r| / (r + eps_c), eps_c = 1% of the
    channel's mean reference value over the mask."""
    r = np.asarray(reference, dtype=np.float64)[mask]  # (N, 3)
    x = np.asarray(image, dtype=np.float64)[mask]
    eps = RELATIVE_ERROR_FLOOR * r.mean(axis=0)
    return float((np.abs(x - r) / (np.abs(r) + eps)).mean())


def mean_bias(reference: np.ndarray, image: np.ndarray, mask: np.ndarray) -> float:
    """Signed relative error of the mean luminance over the mask: (mean Y(x) - mean Y(r)) /
    mean Y(r); negative when the image is too dark overall (e.g. light still unshot)."""
    yr, yx = luminance(reference)[mask].mean(), luminance(image)[mask].mean()
    return float((yx - yr) / yr)


def compare(reference: np.ndarray, image: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """All of the above at once: ``ssim``, ``relative_mse``, ``mean_relative_error``, ``bias``."""
    return {"ssim": ssim(reference, image, mask),
            "relative_mse": relative_mse(reference, image, mask),
            "mean_relative_error": mean_relative_error(reference, image, mask),
            "bias": mean_bias(reference, image, mask)}
