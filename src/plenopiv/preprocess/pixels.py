"""Hot and dead pixels: found in dark and white frames and in the images, repaired in place.

A defective pixel is repaired from the median of its good neighbours in its own micro-image,
never across a micro-image's border (:func:`repair_pixels`). It is found in the master dark
(:func:`dark_defects`), in the white (:func:`white_defects`), and in an image or a batch's
minimum as a pixel far above its same-micro-image neighbours whose neighbours carry none of
the spill a light spot would put there (:func:`isolated_pixels`). See
docs/methods.md#hot-and-dead-pixels.
"""

from __future__ import annotations

import numpy as np

from plenopiv._threads import run_slices
from plenopiv.errors import ImageError
from plenopiv.preprocess import _kernels

__all__ = ["DEAD_FRACTION", "DEFECT_SIGMA", "HOT_MIN_FRACTION", "ISOLATION", "SPILL_SIGMA",
           "SPOT_SPILL",
           "dark_defects",
           "isolated_pixels", "neighbour_stats", "repair_pixels", "robust_sigma",
           "white_defects"]

#: A defect departs from its neighbours by more than this many robust noise levels (a
#: Gaussian pixel does so once in 10^15).
DEFECT_SIGMA = 8.0
#: A hot pixel of an image rises above its neighbours' median by at least this fraction of
#: the image's bright level (its 99.9th percentile): a pixel the reconstruction would count
#: as lit (the default ``[reconstruction] pixel_threshold`` is 0.003 of the maximum).
HOT_MIN_FRACTION = 0.01
#: A hot pixel's brightest same-micro-image neighbour rises less than this fraction of the
#: pixel's own excess above their median (plus :data:`SPILL_SIGMA` noise levels); a light
#: spot, spread over at least two pixels by the point spread and by where it lands, puts
#: more than that on a neighbour.
ISOLATION = 0.05
#: What noise alone may lift the brightest of eight neighbours by, in noise levels (its
#: 99.9th percentile is 3.7).
SPILL_SIGMA = 4.0
#: The least share of a light spot's excess its brightest neighbour carries (measured on
#: ray-traced particle images without point spread: 0.12 to 0.16).
SPOT_SPILL = 0.12
#: A pixel of a white's lit micro-image below this fraction of its neighbours' median is dead.
DEAD_FRACTION = 0.5
#: Repairs look for good neighbours up to this many pixels away.
MAX_REPAIR_RADIUS = 3
#: The noise floor of an integer-valued frame with no measurable spread, counts.
NOISE_FLOOR_COUNTS = 0.5


def robust_sigma(values) -> float:
    """The standard deviation of Gaussian noise from the median absolute deviation (1.4826 MAD).

    0 for no values.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


def _labels(labels, shape) -> np.ndarray:
    if labels is None:
        return np.zeros(shape, np.int32)
    lab = np.ascontiguousarray(labels, dtype=np.int32)
    if lab.shape != tuple(shape):
        raise ImageError(f"micro-image labels have shape {lab.shape}: expected the image's "
                         f"{tuple(shape)}")
    return lab


def _image(image, name: str = "image") -> np.ndarray:
    img = np.ascontiguousarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ImageError(f"{name} has shape {img.shape}: expected a 2-D (rows, cols) image")
    if not np.isfinite(img).all():
        raise ImageError(f"{name} holds NaN or infinite values: expected finite counts")
    return img


def neighbour_stats(image, labels=None, *, use=None, which=None, radius: int = 1,
                    engine: str = "numba") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(maximum, median, count)`` of each pixel's neighbours in its own micro-image.

    Parameters
    ----------
    image : (rows, cols) array_like
        Counts.
    labels : (rows, cols) int array, optional
        Micro-image of each pixel (:attr:`MicroImages.label`); None: one region.
    use : (rows, cols) bool, optional
        Pixels that may serve as neighbours (default all).
    which : (rows, cols) bool, optional
        Pixels to summarise (default all); the others get NaN and 0.
    radius : int
        Half-width of the square neighbourhood, pixels (1: the 8 neighbours).
    engine : {"numba", "numpy"}
        The kernel or its NumPy twin.

    Returns
    -------
    maximum, median : (rows, cols) float64
        Of the neighbours (the pixel itself left out); NaN where there are none.
    count : (rows, cols) int32
        How many there are.
    """
    img = _image(image)
    lab = _labels(labels, img.shape)
    use = np.ones(img.shape, bool) if use is None else np.ascontiguousarray(use, dtype=bool)
    which = (np.ones(img.shape, bool) if which is None
             else np.ascontiguousarray(which, dtype=bool))
    for name, a in (("use", use), ("which", which)):
        if a.shape != img.shape:
            raise ImageError(f"{name} has shape {a.shape}: expected the image's {img.shape}")
    if int(radius) < 1:
        raise ValueError(f"radius = {radius!r}: expected an integer >= 1")
    if engine not in ("numba", "numpy"):
        raise ValueError(f"engine = {engine!r}: expected 'numba' or 'numpy'")
    maximum = np.full(img.shape, np.nan)
    median = np.full(img.shape, np.nan)
    count = np.zeros(img.shape, np.int32)
    if engine == "numba":
        run_slices(_kernels.neighbour_stats, img.shape[0], img, lab, use, which, int(radius),
                   maximum, median, count)
    else:
        _kernels.neighbour_stats_numpy(img, lab, use, which, int(radius), maximum, median,
                                       count, 0, img.shape[0])
    return maximum, median, count


def repair_pixels(image, bad, labels=None, *, max_radius: int = MAX_REPAIR_RADIUS,
                  engine: str = "numba") -> tuple[np.ndarray, np.ndarray]:
    """Replace the ``bad`` pixels by the median of their good neighbours in their micro-image.

    The neighbourhood grows from 3 × 3 up to ``2 max_radius + 1`` square until it holds a
    good pixel of the same micro-image (``labels``; None: one region).

    Returns
    -------
    repaired : (rows, cols) float64
        A copy of ``image`` with the bad pixels replaced.
    unrepaired : (rows, cols) bool
        Bad pixels with no good neighbour of their micro-image within ``max_radius`` (left as
        they were; leave them out of what follows, e.g. by an image mask).
    """
    img = _image(image)
    bad = np.asarray(bad, dtype=bool)
    if bad.shape != img.shape:
        raise ImageError(f"bad-pixel mask has shape {bad.shape}: expected the image's "
                         f"{img.shape}")
    out = img.copy()
    remaining = bad.copy()
    good = ~bad
    for radius in range(1, int(max_radius) + 1):
        if not remaining.any():
            break
        _, median, count = neighbour_stats(img, labels, use=good, which=remaining,
                                           radius=radius, engine=engine)
        fixed = remaining & (count > 0)
        out[fixed] = median[fixed]
        remaining &= ~fixed
    return out, remaining


def dark_defects(dark) -> tuple[np.ndarray, np.ndarray]:
    """``(hot, cold)`` pixels of a master dark (bool images).

    A pixel is hot (cold) when it lies more than :data:`DEFECT_SIGMA` robust noise levels
    above (below) the median of its 3 × 3 neighbourhood; the noise level is the robust spread
    of those departures over the frame (so a fixed pattern of the black level, or a glow,
    does not count), at least :data:`NOISE_FLOOR_COUNTS`.
    """
    from scipy import ndimage

    d = _image(dark, "dark")
    residual = d - ndimage.median_filter(d, size=3, mode="nearest")
    sigma = max(robust_sigma(residual), NOISE_FLOOR_COUNTS)
    return residual > DEFECT_SIGMA * sigma, residual < -DEFECT_SIGMA * sigma


def white_defects(white, labels, judge) -> tuple[np.ndarray, np.ndarray]:
    """``(stuck high, dead)`` pixels of a (dark-subtracted) white inside its lit micro-images.

    Parameters
    ----------
    white : (rows, cols) array_like
        The white frame, counts.
    labels : (rows, cols) int
        Micro-image of each pixel.
    judge : (rows, cols) bool
        Pixels inside a micro-image's plateau (their aperture cell wholly inside the
        aperture): only there is a pixel expected to read like its neighbours.

    Notes
    -----
    Against the median of its same-micro-image neighbours m, a pixel is dead below
    :data:`DEAD_FRACTION` × m, and stuck high above 1.5 m when also :data:`DEFECT_SIGMA`
    robust noise levels above it.
    """
    w = _image(white, "white")
    judge = np.asarray(judge, dtype=bool)
    _, median, count = neighbour_stats(w, labels, which=judge)
    ok = judge & (count >= 3) & (median > 0)
    dead = ok & (w < DEAD_FRACTION * median)
    departure = np.where(ok, w - median, 0.0)
    sigma = max(robust_sigma(departure[ok]), NOISE_FLOOR_COUNTS)
    high = ok & (departure > DEFECT_SIGMA * sigma) & (w > 1.5 * median)
    return high, dead


def isolated_pixels(image, labels=None, *, noise: float = 0.0, exclude=None,
                    engine: str = "numba") -> np.ndarray:
    """Hot pixels of an image: bright single pixels no light spot can explain (bool image).

    Parameters
    ----------
    image : (rows, cols) array_like
        Counts (an image, or the per-pixel minimum of a batch).
    labels : (rows, cols) int, optional
        Micro-image of each pixel (None: one region).
    noise : float
        Standard deviation of the image's noise, counts (0 when unknown).
    exclude : (rows, cols) bool, optional
        Pixels known to be bad: not used as neighbours, not reported again.

    Notes
    -----
    A pixel is hot when, against the neighbours in its own micro-image (3 × 3, the pixel
    left out), its excess e = v − median exceeds the median itself,
    :data:`SPILL_SIGMA` / (:data:`SPOT_SPILL` − :data:`ISOLATION`) × ``noise`` and
    :data:`HOT_MIN_FRACTION` of the image's bright level (its 99.9th percentile), and its
    brightest neighbour (in any micro-image: light crosses a cell's border, a neighbour's
    rim reaches into the gap) rises less than :data:`ISOLATION` × e + :data:`SPILL_SIGMA` ×
    ``noise`` above the median. See the module's notes for why a light spot never does that.
    """
    img = _image(image)
    use = np.ones(img.shape, bool) if exclude is None else ~np.asarray(exclude, dtype=bool)
    bright = float(np.percentile(img, 99.9))
    floor = max(SPILL_SIGMA / (SPOT_SPILL - ISOLATION) * float(noise),
                HOT_MIN_FRACTION * max(bright, 0.0))
    base = float(np.median(img))
    which = use & (img > base + floor)
    if not which.any():
        return np.zeros(img.shape, bool)
    _, median, count = neighbour_stats(img, labels, use=use, which=which, engine=engine)
    # light crosses a micro-image's border (a neighbour's rim spills into the gap): the
    # spill is looked for in every neighbour, the level in the pixel's own micro-image
    maximum, _, _ = neighbour_stats(img, None, use=use, which=which, engine=engine)
    ok = which & (count >= 2)
    excess = np.where(ok, img - median, 0.0)
    spill = np.where(ok, maximum - median, np.inf)
    return (ok & (excess > floor) & (excess > median)
            & (spill < ISOLATION * excess + SPILL_SIGMA * float(noise)))
