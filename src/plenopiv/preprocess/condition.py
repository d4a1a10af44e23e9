"""The condition of an image as it comes: its black level, saturation and hot pixels.

An image straight from a camera sits on a black level (hundreds of counts on many sensors),
may hold saturated and hot pixels, and wants a dark and a white frame. :func:`image_condition`
measures what the reconstruction cares about (:mod:`plenopiv.preprocess.intensity`), and
:func:`advice` says, once per image, which figure is off and which ``[preprocess]`` key to set.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plenopiv.preprocess.microimages import MicroImages, gap_level
from plenopiv.preprocess.pixels import isolated_pixels, robust_sigma

__all__ = ["DEFAULT_DARK_FRACTION", "HOT_REPORT", "ImageCondition", "advice",
           "image_condition"]

#: The reconstruction's default dark threshold, a fraction of the brightest pixel
#: (``[reconstruction] pixel_threshold``).
DEFAULT_DARK_FRACTION = 0.003
#: A saturated share above this is reported (the image check warns from the same share).
SATURATED_REPORT = 1e-3
#: Hot pixels are reported above this share of the pixels (a sensor has 1e-4 to 1e-3 of
#: them; a few single-pixel spots of a sparse ray-traced render are not reported).
HOT_REPORT = 1e-5


@dataclass(frozen=True)
class ImageCondition:
    """Figures of one image.

    Attributes
    ----------
    black_level : float
        The median of its darkest micro-image gaps, counts
        (:func:`~plenopiv.preprocess.microimages.gap_level`).
    peak : float
        Its brightest pixel, counts.
    saturated_fraction : float
        The share of its pixels at the recording's ceiling.
    hot_pixels : int or None
        Its hot pixels (:func:`~plenopiv.preprocess.pixels.isolated_pixels`) left unrepaired;
        None where they were not counted.
    noise : float
        The robust spread of its gap pixels, counts.
    n_pixels : int
        Its size.
    """

    black_level: float
    peak: float
    saturated_fraction: float
    hot_pixels: int | None
    noise: float
    n_pixels: int = 1

    def to_dict(self) -> dict:
        """The figures, JSON-ready (``hot_pixels`` only where they were counted)."""
        out = {"black_level_counts": self.black_level, "peak_counts": self.peak,
               "saturated_fraction": self.saturated_fraction, "noise_counts": self.noise}
        if self.hot_pixels is not None:
            out["hot_pixels"] = self.hot_pixels
        return out


def image_condition(image, micro: MicroImages, *, saturated_fraction: float = 0.0,
                    count_hot: bool = True, exclude=None) -> ImageCondition:
    """Measure an image (counts): black level, peak, hot pixels (``count_hot``), noise.

    ``saturated_fraction`` comes from the recording (its dtype's ceiling,
    :func:`plenopiv.products.images.saturation`); ``exclude`` marks pixels already handled.
    """
    img = np.asarray(image, dtype=np.float64)
    level = gap_level(img, micro)
    gap = micro.gap
    noise = robust_sigma(img[gap]) if gap.any() else 0.0
    hot = None
    if count_hot:
        hot = int(isolated_pixels(img, micro.label, noise=noise, exclude=exclude).sum())
    return ImageCondition(float(level), float(img.max()), float(saturated_fraction), hot,
                          float(noise), int(img.size))


def advice(condition: ImageCondition, *, dark_fraction: float = DEFAULT_DARK_FRACTION,
           applied: bool = False, dark: bool = False, hot_pixels: str = "none"
           ) -> str | None:
    """What is off with an image and which ``[preprocess]`` key to set; None when all is well.

    Parameters
    ----------
    condition : ImageCondition
        Of the image as the reconstruction will see it (after what was applied).
    dark_fraction : float
        The reconstruction's dark threshold, a fraction of the brightest pixel.
    applied : bool
        Whether a ``[preprocess]`` table was given.
    dark : bool
        Whether a dark was subtracted.
    hot_pixels : str
        ``"auto"`` or ``"none"``: whether hot pixels were repaired.

    Notes
    -----
    Off: a black level above ``dark_fraction`` of the brightest pixel (no pixel would be
    dark), hot pixels left unrepaired on more than :data:`HOT_REPORT` of the pixels, or more
    than 0.1 % of the pixels saturated.
    """
    c = condition
    level_off = c.black_level > 0 and c.black_level > dark_fraction * c.peak
    hot_off = bool(c.hot_pixels) and c.hot_pixels > HOT_REPORT * c.n_pixels
    sat_off = c.saturated_fraction > SATURATED_REPORT
    if not (level_off or hot_off or sat_off):
        return None
    share = c.black_level / c.peak if c.peak > 0 else float("nan")
    figures = (f"black level {c.black_level:.4g} counts (median of the darkest micro-image "
               f"gaps; {share:.2%} of the brightest pixel, the reconstruction's dark threshold "
               f"is {dark_fraction:.2%}), {c.saturated_fraction:.2%} of the pixels saturated, "
               f"{c.hot_pixels or 0} hot pixels")
    keys = []
    if level_off:
        keys.append('[preprocess] background = "BACKGROUND.tif" (or "minimum" over a batch): '
                    "the dark leaves a level" if dark else
                    '[preprocess] dark = "DARK.tif" (a dark frame or stack at the images\' '
                    "exposure)")
    if hot_off:
        keys.append('[preprocess] hot_pixels = "auto"' if not applied or hot_pixels == "none"
                    else '[preprocess] dark = "DARK.tif" (its hot pixels are repaired)')
    if sat_off:
        keys.append("a shorter exposure or a weaker pulse (saturated pixels are clipped)")
    return f"{figures}: set {'; '.join(keys)}"
