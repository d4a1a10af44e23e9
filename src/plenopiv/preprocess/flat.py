"""The flat field: each micro-image's throughput from a white image, divided out of the images.

The throughput is a plane fitted to each micro-image's plateau in a white taken at the
recording's aperture (:func:`flat_field`); an image is divided by it relative to the typical
throughput (:func:`apply_flat`). The rim below :data:`RIM_FRACTION` of the plane, dark
micro-images, pixels outside the array and dead pixels are masked, never amplified. See
docs/methods.md#dark-background-and-flat-field.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from plenopiv.errors import ImageError, PlenopivWarning
from plenopiv.preprocess.microimages import MicroImages, gap_level, per_micro_image
from plenopiv.preprocess.pixels import white_defects

__all__ = ["FlatField", "PLATEAU_FRACTION", "RIM_FRACTION", "apply_flat", "flat_field"]

#: Pixels of the white below this fraction of their micro-image's local peak (the fitted
#: plateau there) are masked; so are micro-images darker than this fraction of the typical.
RIM_FRACTION = 0.2
#: The plateau of a micro-image: its pixels above this fraction of the local peak.
PLATEAU_FRACTION = 0.8
#: The plateau lies this far inside the modelled micro-image radius (pixels): there a pixel's
#: aperture cell (a pixel square, half a diagonal from its centre) is wholly inside the
#: aperture, and the plateau is symmetric about the centre (rim pixels would tilt the plane).
INNER_MARGIN_PX = 1.0
#: The local peak of a micro-image: this percentile of its pixels.
PEAK_PERCENTILE = 90.0
#: A plane needs at least this many plateau pixels; fewer give a constant.
MIN_PLANE_PIXELS = 6
#: A white's gaps lie below this fraction of its plateau (a white has micro-images).
MAX_GAP_RATIO = 0.5
#: At least this share of a white's micro-images lie within a factor 4 of the typical one.
MIN_TYPICAL_SHARE = 0.7
#: Below this share of the modelled micro-image's inner pixels unmasked, the white was taken
#: at a smaller aperture than the recording (a warning).
MIN_COVERED_SHARE = 0.8


@dataclass(frozen=True)
class FlatField:
    """A flat field made from a white image.

    Attributes
    ----------
    gain : (rows, cols) float64
        The throughput relative to the typical micro-image's (1 where masked).
    mask : (rows, cols) bool
        Pixels to leave out: outside the array, the dim rim, dark micro-images, dead pixels.
    reference : float
        P_ref, the typical micro-image's plateau, counts of the white.
    plateau : (N,) float64
        a_k, each micro-image's plateau at its centre, counts (NaN where masked).
    dead : (rows, cols) bool
        Dead pixels found in the white (also in ``mask``).
    stuck : (rows, cols) bool
        Pixels of the white far above their micro-image's plateau (repaired, not masked).
    black_level : float
        The white's own gap level that was taken off before the fit, counts.
    """

    gain: np.ndarray
    mask: np.ndarray
    reference: float
    plateau: np.ndarray
    dead: np.ndarray
    stuck: np.ndarray
    black_level: float

    @property
    def spread(self) -> float:
        """The relative rms of the micro-images' plateaus about the typical one."""
        a = self.plateau[np.isfinite(self.plateau)] / self.reference
        return float(np.sqrt(np.mean((a - 1.0) ** 2))) if a.size else float("nan")

    def to_dict(self) -> dict:
        """Figures of the flat field, JSON-ready."""
        return {"reference_counts": self.reference, "throughput_rms": self.spread,
                "masked_pixels": int(self.mask.sum()), "dead_pixels": int(self.dead.sum()),
                "rim_fraction": RIM_FRACTION, "black_level_counts": self.black_level}


def _plane_fit(values, dr, dc, label, n):
    """Least-squares planes a + b dr + c dc per micro-image; ``(a, b, c, pixels used)``."""
    def s(w):
        return np.bincount(label, weights=w, minlength=n)[:n]

    one = np.ones_like(values)
    m = np.empty((n, 3, 3))
    m[:, 0, 0], m[:, 0, 1], m[:, 0, 2] = s(one), s(dr), s(dc)
    m[:, 1, 1], m[:, 1, 2], m[:, 2, 2] = s(dr * dr), s(dr * dc), s(dc * dc)
    m[:, 1, 0], m[:, 2, 0], m[:, 2, 1] = m[:, 0, 1], m[:, 0, 2], m[:, 1, 2]
    rhs = np.stack([s(values), s(values * dr), s(values * dc)], axis=1)
    used = m[:, 0, 0].astype(np.int64)
    coef = np.zeros((n, 3))
    plane = used >= MIN_PLANE_PIXELS
    if plane.any():
        det = np.linalg.det(m[plane])
        ok = np.abs(det) > 1e-9 * np.maximum(m[plane, 0, 0], 1) ** 3
        idx = np.flatnonzero(plane)[ok]
        coef[idx] = np.linalg.solve(m[idx], rhs[idx][..., None])[..., 0]
        plane[np.flatnonzero(plane)[~ok]] = False
    flat = (used > 0) & ~plane
    coef[flat, 0] = rhs[flat, 0] / used[flat]
    return coef[:, 0], coef[:, 1], coef[:, 2], used


def flat_field(white, micro: MicroImages, *, bad=None, name: str = "white") -> FlatField:
    """The flat field of a dark-subtracted white image (counts) on the micro-images ``micro``.

    Parameters
    ----------
    white : (rows, cols) array_like
        The white (a mean of frames), its dark subtracted when a dark is known; its own gap
        level (:func:`~plenopiv.preprocess.microimages.gap_level`) is taken off here.
    micro : MicroImages
        The calibration's micro-images.
    bad : (rows, cols) bool, optional
        Pixels known to be bad (hot pixels of the dark): left out of the fit.
    name : str
        Names the white in messages (e.g. ``"[preprocess] white 'white.tif'"``).

    Raises
    ------
    ImageError
        When the white is not the sensor's shape, or is no white: no lit micro-images, gaps
        as bright as the micro-images (no micro-image structure), or micro-images whose
        brightness scatters as a particle image's does.

    Warns
    -----
    PlenopivWarning
        When the white's micro-images are smaller than the modelled ones at the recording's
        aperture (taken stopped down?).
    """
    w = np.asarray(white, dtype=np.float64)
    if w.shape != micro.shape:
        raise ImageError(f"{name} is {' × '.join(str(s) for s in w.shape)} pixels: expected "
                         f"the sensor's {micro.shape[0]} × {micro.shape[1]} (rows × cols)")
    if not np.isfinite(w).all():
        raise ImageError(f"{name} holds NaN or infinite values: expected finite counts")
    n = micro.n_micro_images
    label = micro.label
    bad = np.zeros(w.shape, bool) if bad is None else np.asarray(bad, dtype=bool)
    black = gap_level(w, micro)
    w = w - black
    inside = (label >= 0) & ~bad
    peak = per_micro_image(w[inside], label[inside], n, PEAK_PERCENTILE)
    found = np.isfinite(peak)
    typical = float(np.median(peak[found])) if found.any() else float("nan")
    gap = micro.gap & ~bad
    noise = _gap_noise(w, gap)
    if black > 0 and not black < MAX_GAP_RATIO * (typical + black):
        raise ImageError(f"{name} shows no micro-image structure: the gaps between the "
                         f"micro-images are at {black:.4g} counts, "
                         f"{black / (typical + black):.0%} of the micro-images' plateau "
                         f"(expected below {MAX_GAP_RATIO:.0%}): expected a white image through "
                         "this camera's lenslets, not a uniform frame")
    if not (np.isfinite(typical) and typical > max(10.0 * noise, 0.0)):
        raise ImageError(f"{name} shows no lit micro-images: the typical micro-image's peak is "
                         f"{typical:.4g} counts above the gaps (noise {noise:.3g}): expected a "
                         "white image (a diffuser or a white sheet) at the recording's aperture")
    share = float(np.mean((peak[found] > 0.25 * typical) & (peak[found] < 4.0 * typical)))
    if share < MIN_TYPICAL_SHARE:
        raise ImageError(f"{name} is not a white: only {share:.0%} of its micro-images are "
                         f"within a factor 4 of the typical one (expected at least "
                         f"{MIN_TYPICAL_SHARE:.0%}); a white lights every micro-image alike")
    lab = np.maximum(label, 0)
    peak_px = np.where(label >= 0, np.nan_to_num(peak, nan=np.inf)[lab], np.inf)
    dr, dc = micro.offsets()
    interior = inside & found[lab] & (micro.distance_px <= micro.radius_px - INNER_MARGIN_PX)
    plateau_px = interior & (w >= PLATEAU_FRACTION * peak_px)
    judge = interior
    stuck, dead = white_defects(w, label, judge)
    plateau_px &= ~stuck
    a, b, c, used = _plane_fit(w[plateau_px], dr[plateau_px], dc[plateau_px],
                               label[plateau_px], n)
    reference = float(np.median(a[used > 0]))
    valid = (used > 0) & (a >= RIM_FRACTION * reference)
    level = np.where(label >= 0, a[lab] + b[lab] * dr + c[lab] * dc, 0.0)
    ok = (label >= 0) & valid[lab] & (level > 0)
    mask = ~ok | (w < RIM_FRACTION * np.where(ok, level, np.inf)) | dead
    gain = np.where(mask, 1.0, level / reference)
    inner = (label >= 0) & valid[lab] & (micro.distance_px <= micro.radius_px - INNER_MARGIN_PX)
    if inner.any():
        covered = float(np.mean(~mask[inner]))
        if covered < MIN_COVERED_SHARE:
            warnings.warn(f"{name}: only {covered:.0%} of the pixels inside the modelled "
                          f"micro-images ({2 * micro.radius_px:.1f} px across) are lit above "
                          f"{RIM_FRACTION:.0%} of their plateau: was the white taken at a "
                          "smaller aperture than the recording? Those pixels are masked",
                          PlenopivWarning, stacklevel=2)
    plateau = np.where(valid, a, np.nan)
    return FlatField(gain, mask, reference, plateau, dead, stuck, float(black))


def _gap_noise(w: np.ndarray, gap: np.ndarray) -> float:
    """The noise of the gap pixels, counts: from the differences of neighbours along a row.

    1.4826 × the median absolute departure of ``w[r, c + 1] - w[r, c]`` over neighbouring gap
    pixels, over √2. A real white may hold a light floor between its micro-images (the rims'
    tails, stray light; 17 to 60 counts under a 190-count plateau on the plenoptomos letters
    camera): smooth, it leaves the differences alone, where the spread of the gap pixels
    themselves would count it as noise. 0 without neighbouring gap pixels.
    """
    both = gap[:, 1:] & gap[:, :-1]
    if not both.any():
        return 0.0
    d = (w[:, 1:] - w[:, :-1])[both]
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def apply_flat(image, flat: FlatField) -> np.ndarray:
    """``image / gain`` where the flat is unmasked, 0 where it is masked (float64 counts)."""
    img = np.asarray(image, dtype=np.float64)
    if img.shape != flat.gain.shape:
        raise ImageError(f"image is {img.shape} pixels but the flat field "
                         f"{flat.gain.shape}: expected frames of one sensor")
    return np.where(flat.mask, 0.0, img / flat.gain)
