"""The two exposures of a pair on one intensity scale, for MART.

The reconstruction counts a pixel at or below ``[reconstruction] pixel_threshold`` times the
image's brightest pixel as dark, and dark pixels empty and cap the voxels they see; so the
exposures of a pair must count the same pixels as dark for the same particles.
:func:`normalise_pair` scales exposure B onto A's level (:func:`exposure_level`) and clips both
at their common saturation ceiling. See docs/methods.md#intensities-for-mart.
"""

from __future__ import annotations

import numpy as np

from plenopiv.errors import ImageError

__all__ = ["LEVEL_PERCENTILE", "LIT_FRACTION", "exposure_level", "normalise_pair"]

#: Lit pixels: above this fraction of the image's 99.9th percentile.
LIT_FRACTION = 0.05
#: The exposure's level: this percentile of its lit pixels (robust to 5 % of them clipped).
LEVEL_PERCENTILE = 95.0


def exposure_level(image, mask=None) -> float:
    """The level of an exposure, counts: the :data:`LEVEL_PERCENTILE` of its lit pixels.

    Lit pixels are those above :data:`LIT_FRACTION` of the 99.9th percentile of the unmasked
    pixels. Scaling the image scales the level; NaN for an image with no lit pixel.
    """
    img = np.asarray(image, dtype=np.float64)
    values = img[~np.asarray(mask, bool)] if mask is not None else img.ravel()
    if values.size == 0:
        return float("nan")
    top = float(np.percentile(values, 99.9))
    if not top > 0:
        return float("nan")
    lit = values[values > LIT_FRACTION * top]
    return float(np.percentile(lit, LEVEL_PERCENTILE)) if lit.size else float("nan")


def normalise_pair(image_a, image_b, *, mask=None, saturated=(None, None)
                   ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Exposure B scaled onto A's level, both clipped at their common saturation ceiling.

    Parameters
    ----------
    image_a, image_b : (rows, cols) array_like
        The preprocessed exposures, counts (background near 0).
    mask : (rows, cols) bool, optional
        Pixels left out of the reconstruction (not used for the levels).
    saturated : pair of (rows, cols) bool or None
        Each exposure's pixels that were at the recording's ceiling.

    Returns
    -------
    a, b : (rows, cols) float64
        The exposures on A's scale.
    figures : dict
        ``level_a``, ``level_b`` (counts), ``scale_b`` (B's factor), ``ceiling`` (counts on
        A's scale, None without saturation).

    Notes
    -----
    With a ceiling c (the median, on A's scale, of each exposure's saturated pixels, the
    smaller of the two), both exposures are clipped at c: a pixel that clipped in the
    brighter exposure clips in the other, whose brightest pixel then also sits at c, and the
    reconstruction's threshold (a fraction of the brightest pixel) falls on the same pixels.
    """
    a = np.asarray(image_a, dtype=np.float64)
    b = np.asarray(image_b, dtype=np.float64)
    if a.shape != b.shape:
        raise ImageError(f"the two exposures have shapes {a.shape} and {b.shape}: expected "
                         "images of one sensor")
    level_a, level_b = exposure_level(a, mask), exposure_level(b, mask)
    scale = level_a / level_b if (np.isfinite(level_a) and np.isfinite(level_b)
                                  and level_b > 0) else 1.0
    b = b * scale
    ceilings = []
    for img, sat in zip((a, b), saturated, strict=True):
        if sat is None:
            continue
        s = np.asarray(sat, bool)
        if mask is not None:
            s = s & ~np.asarray(mask, bool)
        if s.any():
            ceilings.append(float(np.median(img[s])))
    ceiling = min(ceilings) if ceilings else None
    if ceiling is not None and ceiling > 0:
        a = np.minimum(a, ceiling)
        b = np.minimum(b, ceiling)
    return a, b, {"level_a": level_a, "level_b": level_b, "scale_b": float(scale),
                  "ceiling": ceiling}
