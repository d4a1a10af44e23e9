"""Calibration step 1a: one sub-pixel spot centre per lenslet (:func:`detect_spots`).

Candidates are the local maxima of the smoothed, background-subtracted image, refined by the
iterative thresholded centroid and then by the window centroid (the default for focal and
alignment spots: the first moment of all of a spot's light, free of the pixel-phase bias of a
thresholded centroid) or a Gaussian fit; partial, dim and saturated spots are flagged.
:func:`estimate_pitch` finds the lenslet pitch when it is not given.

See docs/methods.md#focal-spots for the steps, the choice of estimator and its accuracy.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree
from scipy.special import ndtri

from plenopiv.calibration import _spot_kernels as _k
from plenopiv.calibration.defects import (
    HOT_SHAPE_MIN_RMS_PX,
    fixed_pattern,
    isolated_pixels,
    patch_pixels,
)
from plenopiv.calibration.spot_shape import fit_radius, shape_refine, shape_uncertainty
from plenopiv.calibration.spot_types import (
    BACKGROUNDS,
    GRIDS,
    METHODS,
    SpotFlag,
    SpotSet,
    _check_choice,
    _check_fraction,
    _edge_mask,
)
from plenopiv.errors import ImageError

# The iteration limits of the sub-pixel estimators; all converge in a few passes.
_CENTROID_MAX_ITER = 20
_CENTROID_TOL_PX = 1e-4
_GAUSS_MAX_ITER = 50
_WINDOW_MAX_ITER = 50
_WINDOW_TOL_PX = 1e-7
# The window method: window radius = _WINDOW_SCALE times the radius holding 99 % of a spot's
# light plus 0.5 px (5.8 standard deviations of a Gaussian spot: its truncated tail moves the
# first moment by < 1e-5 px at any phase), less where the annulus would reach the
# neighbours, never less than that radius plus _WINDOW_MARGIN_PX; the background annulus is
# _ANNULUS_PX wide, just outside the window.
_ENERGY_FRACTION = 0.99
_WINDOW_SCALE = 1.75
_WINDOW_MARGIN_PX = 1.0
_ANNULUS_PX = 2.0
# ----------------------------------------------------------------------------------------------

# Micro-images whose stacked diameter at half height reaches this fraction of the pitch fill
# their cells: their centres come from their mean shape, not a thresholded centroid
_FILL_FOR_SHAPE = 0.85
# Candidate spots: the local reference is taken over cells of this many pitches, and a spot
# must stand this many standard deviations of the smoothed image's noise above the gaps
_REFERENCE_CELL = 4.0
_NOISE_FLOOR = 8.0


# ----------------------------------------------------------------------------------------------
# Image checks
# ----------------------------------------------------------------------------------------------


def _validate_image(image, max_saturated_fraction):
    """Check a calibration image; return it as an ndarray and its saturation level (or None)."""
    a = np.asarray(image)
    if a.ndim != 2:
        hint = (
            " (a colour image? convert it to grey first)"
            if a.ndim == 3 and a.shape[-1] in (3, 4)
            else ""
        )
        raise ImageError(f"image must be 2-D (rows, cols); got an array of shape {a.shape}{hint}")
    if a.dtype == bool or not (
        np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)
    ):
        raise ImageError(
            f"image dtype {a.dtype} is not supported; expected an integer or floating-point image"
        )
    if min(a.shape) < 8:
        raise ImageError(f"image of shape {a.shape} is too small; expected at least 8 x 8 pixels")
    if np.issubdtype(a.dtype, np.floating):
        bad = ~np.isfinite(a)
        n_bad = int(np.count_nonzero(bad))
        if n_bad:
            r, c = np.unravel_index(int(np.argmax(bad)), a.shape)
            raise ImageError(
                f"image has {n_bad} non-finite pixels (NaN or inf); the first at (row {r}, "
                f"col {c}); expected finite values (replace dead pixels, e.g. by the median of "
                "their neighbours)"
            )
    lo, hi = a.min(), a.max()
    if hi <= 0:
        raise ImageError(f"image is all dark (maximum {hi}); expected bright lenslet spots")
    if lo == hi:
        raise ImageError(
            f"image is constant (every pixel = {hi}); expected bright spots on a darker background"
        )
    sat_level = None
    if np.issubdtype(a.dtype, np.integer):
        sat_level = np.iinfo(a.dtype).max
        n_sat = int(np.count_nonzero(a == sat_level))
        frac = n_sat / a.size
        if frac > max_saturated_fraction:
            raise ImageError(
                f"{100 * frac:.1f} % of the pixels ({n_sat}) are saturated at {sat_level} (the "
                f"{a.dtype} maximum); expected at most {100 * max_saturated_fraction:g} % "
                "(max_saturated_fraction); reduce the exposure"
            )
        if n_sat == 0:
            sat_level = None
    return a, sat_level


# ----------------------------------------------------------------------------------------------
# Pitch from the image autocorrelation
# ----------------------------------------------------------------------------------------------

_PITCH_CROP_PX = 1024


def estimate_pitch(image):
    """Lenslet pitch (nearest-neighbour spacing) of a periodic spot image, px.

    Parameters
    ----------
    image : array_like, shape (R, C)
        Calibration image (any real dtype, finite).

    Returns
    -------
    float
        Distance from the origin to the nearest strong peak of the image autocorrelation, px
        (the lenslet pitch on a square and on a hexagonal grid).

    Raises
    ------
    ImageError
        When the autocorrelation shows no periodic pattern.

    Notes
    -----
    The central crop (at most 1024 x 1024 px) is high-pass filtered (its box mean over 1/8 of
    the crop removed, which takes out vignetting), zero-padded and correlated with itself
    through the FFT. Its local maxima other than the origin are the lattice
    vectors; the nearest one whose height is at least half the highest one is the pitch,
    refined to sub-pixel by a parabola through its neighbours in each axis. The result only
    sizes the search windows; the lattice fit measures the pitch exactly.
    """
    a = np.asarray(image, dtype=np.float64)
    n_rows, n_cols = a.shape
    h = min(n_rows, _PITCH_CROP_PX)
    w = min(n_cols, _PITCH_CROP_PX)
    r0 = (n_rows - h) // 2
    c0 = (n_cols - w) // 2
    crop = a[r0 : r0 + h, c0 : c0 + w]
    crop = crop - ndi.uniform_filter(crop, max(min(h, w) // 8, 3), mode="reflect")
    crop = crop - crop.mean()
    spec = np.fft.rfft2(crop, s=(2 * h, 2 * w))
    ac = np.fft.irfft2(spec * np.conj(spec), s=(2 * h, 2 * w))
    ac = np.fft.fftshift(ac)
    # lags up to a third of the crop: at least three periods must fit for a trustworthy peak
    lr, lc = h // 3, w // 3
    ac = ac[h - lr : h + lr + 1, w - lc : w + lc + 1]
    if ac[lr, lc] <= 0:
        raise ImageError(
            "image has no contrast after removing its smooth background; expected a spot pattern"
        )
    ac = ac / ac[lr, lc]
    peaks = (ac == ndi.maximum_filter(ac, size=5, mode="constant", cval=np.inf)) & (ac > 0.0)
    pr, pc = np.nonzero(peaks)
    dr = pr - lr
    dc = pc - lc
    dist = np.hypot(dr, dc)
    off_centre = dist > 2.0
    pr, pc, dr, dc, dist = (
        pr[off_centre],
        pc[off_centre],
        dr[off_centre],
        dc[off_centre],
        dist[off_centre],
    )
    if dist.size == 0:
        raise ImageError(
            "no periodic lenslet pattern found in the image autocorrelation (no peak besides the "
            "origin within a third of the image); pass expected_pitch_px"
        )
    height = ac[pr, pc]
    strong = height >= 0.5 * height.max()
    k = np.flatnonzero(strong)[np.argmin(dist[strong])]
    r, c = pr[k], pc[k]
    sub = []
    for axis_vals in (
        (ac[r - 1, c], ac[r, c], ac[r + 1, c]),
        (ac[r, c - 1], ac[r, c], ac[r, c + 1]),
    ):
        m1, m0, p1 = axis_vals
        den = m1 - 2.0 * m0 + p1
        sub.append(0.5 * (m1 - p1) / den if den < 0 else 0.0)
    pitch = float(np.hypot(dr[k] + sub[0], dc[k] + sub[1]))
    if pitch < 3.0:
        raise ImageError(
            f"estimated lenslet pitch {pitch:.2f} px is below 3 px; pass expected_pitch_px"
        )
    return pitch


# ----------------------------------------------------------------------------------------------
# Spot detection
# ----------------------------------------------------------------------------------------------


def _local_background(work, pitch):
    """Smooth background: the minimum over a 1.25-pitch box, then its box mean (px units)."""
    size = int(math.ceil(1.25 * pitch)) | 1
    return ndi.uniform_filter(
        ndi.minimum_filter(work, size=size, mode="nearest"), size=size, mode="nearest"
    )


def detect_spots(image, *, expected_pitch_px=None, grid=None, threshold=0.1,
                 detection_threshold=0.15, method="auto", window_radius_px=None,
                 moment_radius_px=None, background="local", min_area_px=1.5, dim_fraction=0.5,
                 max_saturated_fraction=0.02, bad_pixels=None, hot_pixel_shapes=True):
    """Find one sub-pixel spot centre per lenslet in a calibration image.

    Parameters
    ----------
    image : array_like, shape (R, C)
        Focal-point, alignment or white image, integer or floating point, ``image[row, col]``.
    expected_pitch_px : float, optional
        Lenslet pitch, px (default :func:`estimate_pitch`).
    grid : {"square", "hexagonal"} or None
        Grid type if known (recorded for ``fit_lattice``).
    threshold : float, 0 <= threshold < 1
        Centroid weights ``max(I - threshold * P, 0)``, P the spot's peak over background.
    detection_threshold : float, 0 < detection_threshold < 1
        A local maximum is a candidate when it reaches this fraction of the bright spots
        around it, stands 8 noise levels above the gaps, and a tenth of it of the image's
        typical spot (docs/methods.md#focal-spots).
    method : {"auto", "window", "shape", "centroid", "gaussian"}
        Sub-pixel estimator: ``"window"`` (first moment in a soft window above an annulus
        plane), ``"shape"`` (the spots' mean shape fitted to each, for micro-images that
        fill their cells), ``"centroid"`` (iterative thresholded), ``"gaussian"``; ``"auto"``
        takes ``"window"`` where the window fits between neighbours, else ``"centroid"`` or,
        where the micro-images fill their cells, ``"shape"`` (docs/methods.md#focal-spots).
    window_radius_px : float, optional
        Radius of the centroid's window, which decides ``EDGE``, px (default pitch / 2).
    moment_radius_px : float, optional
        ``"window"`` only: its window's radius, px (default measured from the spots).
    background : {"local", "none"}
        ``"local"``: subtract the black level's fixed pattern per column and row measured on
        the gaps (:func:`~plenopiv.calibration.defects.fixed_pattern`) and a smooth
        background; ``"none"``: the image as is.
    min_area_px : float
        Candidates of a smaller effective area (px) are hot pixels (one pixel: area 1).
    dim_fraction : float, 0 < dim_fraction <= 1
        A spot below this fraction of its eight nearest neighbours' median is ``DIM``.
    max_saturated_fraction : float, 0 <= max_saturated_fraction <= 1
        Largest fraction of pixels at the integer dtype's maximum.
    bad_pixels : array_like of bool, shape (R, C), optional
        Pixels to ignore (a dark frame's hot pixels), replaced by their good neighbours'
        median first.
    hot_pixel_shapes : bool
        Where spots are broader than a pixel (rms ``HOT_SHAPE_MIN_RMS_PX``), find hot pixels
        by their shape (:func:`~plenopiv.calibration.defects.isolated_pixels`), replace them
        and detect again; False never (an alignment spot may be one pixel, halo or not).

    Returns
    -------
    SpotSet
        Centres ``(row, col)`` px, intensity, effective area, flags.

    Raises
    ------
    ImageError
        Not 2-D, not real, NaN/inf, dark, constant, saturated, or no periodic spots.
    ValueError
        An option is outside its valid set. The steps, the choice of estimator and its
        accuracy: docs/methods.md#focal-spots.
    """
    opts = _checked_options(method, background, grid, threshold, detection_threshold,
                            min_area_px, dim_fraction, max_saturated_fraction)
    raw, sat_level = _validate_image(image, opts["max_saturated_fraction"])
    work = raw.astype(np.float32)
    work = work if bad_pixels is None else patch_pixels(work, bad_pixels)
    pitch, radius = _pitch_and_radius(work, expected_pitch_px, window_radius_px)
    if background == "local":
        work = work - fixed_pattern(work, pitch)
        work = work - _local_background(work, pitch)
    cand, work, noise = _candidates(work, pitch, background, opts["detection_threshold"])
    centres, intensity, area, rejected = _first_centroids(work, cand, radius, pitch, opts)
    interior = ~_edge_mask(centres, radius, work.shape)
    spot_r, spot_rms = _spot_size(work, centres[interior], pitch)
    broad = hot_pixel_shapes and spot_rms >= HOT_SHAPE_MIN_RMS_PX
    hot = isolated_pixels(work, noise) if broad else None
    if hot is not None and hot.any():
        work = patch_pixels(work, hot)
        cand, work, _ = _candidates(work, pitch, background, opts["detection_threshold"])
        centres, intensity, area, rejected = _first_centroids(work, cand, radius, pitch, opts)
        rejected = np.concatenate([rejected, np.argwhere(hot).astype(np.float64)])
        interior = ~_edge_mask(centres, radius, work.shape)
        spot_r, spot_rms = _spot_size(work, centres[interior], pitch)
    if method == "auto":
        method = "window" if _window_fits(spot_r, pitch) else "disc"
    centres, flags, moment_r, annulus = _refine(work, centres, area, method, pitch, radius,
                                                spot_r, moment_radius_px)
    if method == "disc":
        centres, method = _better_disc_centres(work, centres, pitch, radius, spot_r)
    std = _centre_std(work, centres, flags, intensity, method,
                      (pitch, radius, moment_r, spot_r), noise, spot_rms)
    order = np.lexsort((centres[:, 1], centres[:, 0]))
    centres, intensity, area, flags, std = (a[order] for a in (centres, intensity, area, flags,
                                                                std))
    flags |= _image_flags(raw, sat_level, centres, intensity, flags, radius, opts)
    return SpotSet(centres_px=centres, intensity=intensity, area_px=area, flags=flags,
                   image_shape=work.shape, pitch_px=pitch, window_radius_px=radius,
                   method=method, grid=grid, rejected_px=rejected, spot_radius_px=spot_r,
                   spot_rms_radius_px=spot_rms, moment_radius_px=moment_r,
                   annulus_px=annulus, centre_std_px=std)


def _checked_options(method, background, grid, threshold, detection_threshold, min_area_px,
                     dim_fraction, max_saturated_fraction):
    """Check the options of :func:`detect_spots`; return the numeric ones as floats (a dict)."""
    _check_choice("method", method, METHODS)
    _check_choice("background", background, BACKGROUNDS)
    if grid is not None:
        _check_choice("grid", grid, GRIDS)
    threshold = float(threshold)
    if not (0.0 <= threshold < 1.0):
        raise ValueError(f"threshold must satisfy 0 <= threshold < 1; got {threshold!r}")
    detection_threshold = float(detection_threshold)
    if not (0.0 < detection_threshold < 1.0):
        raise ValueError(
            "detection_threshold must satisfy 0 < detection_threshold < 1; "
            f"got {detection_threshold!r}"
        )
    dim_fraction = _check_fraction("dim_fraction", dim_fraction)
    max_saturated_fraction = _check_fraction(
        "max_saturated_fraction", max_saturated_fraction, low_open=False
    )
    min_area_px = float(min_area_px)
    if not (np.isfinite(min_area_px) and min_area_px >= 0.0):
        raise ValueError(f"min_area_px must be a finite number >= 0; got {min_area_px!r}")
    return {"threshold": threshold, "detection_threshold": detection_threshold,
            "min_area_px": min_area_px, "dim_fraction": dim_fraction,
            "max_saturated_fraction": max_saturated_fraction}


def _pitch_and_radius(work, expected_pitch_px, window_radius_px):
    """The lenslet pitch (given or estimated) and the centroid window radius, px; checked."""
    if expected_pitch_px is None:
        pitch = estimate_pitch(work)
    else:
        pitch = float(expected_pitch_px)
        if not (np.isfinite(pitch) and pitch >= 3.0):
            raise ValueError(
                f"expected_pitch_px must be a finite number >= 3 px; got {expected_pitch_px!r}"
            )
    if min(work.shape) < 2 * pitch:
        raise ImageError(
            f"image of shape {work.shape} holds less than two lenslets of pitch {pitch:.1f} px "
            "in one direction; expected a lattice of at least 4 x 4"
        )
    radius = 0.5 * pitch if window_radius_px is None else float(window_radius_px)
    if not (np.isfinite(radius) and 1.0 <= radius <= pitch):
        raise ValueError(
            "window_radius_px must satisfy 1 <= window_radius_px <= pitch "
            f"({pitch:.2f} px); got {radius!r}"
        )
    return pitch, radius


def _candidates(work, pitch, background, detection_threshold):
    """Candidate spot positions ``(row, col)`` px, the image less its pedestal, the gaps' noise.

    The noise is a standard deviation in image units (0 without a local background).
    Candidates are the local maxima of the smoothed image at least half a pitch apart. With a local
    background, candidate heights are measured from the typical level of the smoothed
    image's local minima (the gaps between spots), so noise bumps on that pedestal do not
    pass as spots; of the pedestal, the expected noise bias of the box minimum (the expected
    minimum of ``n_box`` normal samples, Blom's approximation, times the pixel noise seen in
    the gaps) is removed from the image; the rest may be light (overlapping spots).
    A candidate is kept when it reaches ``detection_threshold`` of the bright spots around it
    (:func:`_local_reference`, so the dim lenslets of a vignetted corner are found), stands
    ``_NOISE_FLOOR`` noise standard deviations of the smoothed image out, and reaches a
    tenth of ``detection_threshold`` of the image's typical spot (95th percentile).
    """
    smooth = ndi.gaussian_filter(work, max(pitch / 6.0, 0.7), mode="constant")
    size = 2 * int(pitch // 2) + 1
    is_max = smooth == ndi.maximum_filter(smooth, size=size, mode="nearest")
    cand = _holes_filled(np.argwhere(is_max), smooth, pitch)
    height = smooth[cand[:, 0], cand[:, 1]]
    noise = 0.0
    if background == "local":
        is_min = smooth == ndi.minimum_filter(smooth, size=size, mode="nearest")
        gap_level = float(np.median(smooth[is_min]))
        height = height - gap_level
        resid = work[is_min] - smooth[is_min]
        noise = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
        n_box = (int(math.ceil(1.25 * pitch)) | 1) ** 2
        bias = -noise * float(ndtri((1.0 - 0.375) / (n_box + 0.25)))
        work = work - np.float32(min(max(gap_level, 0.0), bias))
    positive = height > 0
    if not np.any(positive):
        raise ImageError(
            "no spot found: the background-subtracted image has no local maximum above its "
            "background"
        )
    cand, height = cand[positive], height[positive]
    sigma_smooth = noise / (2.0 * math.sqrt(math.pi) * max(pitch / 6.0, 0.7))
    ref = _local_reference(cand, height, work.shape, pitch)
    strong = (
        (height >= detection_threshold * ref)
        & (height >= _NOISE_FLOOR * sigma_smooth)
        & (height >= 0.1 * detection_threshold * np.percentile(height, 95))
    )
    return cand[strong].astype(np.float64), work, noise


def _holes_filled(cand, smooth, pitch):
    """The maxima ``cand`` of a pitch-wide filter, and a half-pitch filter's in their holes.

    The half-pitch filter's maxima count when farther than 0.6 pitch from all of ``cand``,
    taken by height, each 0.6 pitch from the others. A micro-image that fills its cell has a
    flat top whose maximum wanders with the noise; its neighbour's brighter shoulder, within
    the pitch-wide filter, can then hide it. The half-pitch filter finds it again, and a
    focal spot's gaps (0.71 pitch from the spots at the cell corners) give only noise
    candidates, which the heights then refuse.
    """
    small = smooth == ndi.maximum_filter(smooth, size=2 * int(pitch // 4) + 1, mode="nearest")
    extra = np.argwhere(small)
    if not len(cand) or not len(extra):
        return cand
    dist, _ = cKDTree(cand).query(extra, distance_upper_bound=0.6 * pitch)
    extra = extra[~np.isfinite(dist)]
    if not len(extra):
        return cand
    extra = extra[np.argsort(-smooth[extra[:, 0], extra[:, 1]], kind="stable")]
    keep = np.ones(len(extra), dtype=bool)
    for a_, b_ in sorted(cKDTree(extra).query_pairs(0.6 * pitch)):
        if keep[a_]:
            keep[b_] = False
    return np.concatenate([cand, extra[keep]])


def _first_centroids(work, cand, radius, pitch, opts):
    """Thresholded centroids of the candidates, hot pixels rejected and duplicates merged.

    Returns the centres ``(row, col)`` px, their intensity and effective area (px), and the
    centres rejected as hot pixels (area below ``min_area_px``). Two candidates that
    converge within a quarter pitch (a flat-topped disc) keep the brighter.
    """
    centres, intensity, area, _peak = _k.centroid_refine_numba(
        work, np.ascontiguousarray(cand), radius, opts["threshold"], _CENTROID_MAX_ITER,
        _CENTROID_TOL_PX
    )
    ok = np.all(np.isfinite(centres), axis=1)
    centres, intensity, area = centres[ok], intensity[ok], area[ok]
    hot = area < opts["min_area_px"]
    rejected = centres[hot]
    centres, intensity, area = centres[~hot], intensity[~hot], area[~hot]
    if centres.shape[0] > 1:
        order = np.argsort(-intensity, kind="stable")
        centres, intensity, area = centres[order], intensity[order], area[order]
        pairs = cKDTree(centres).query_pairs(0.25 * pitch, output_type="ndarray")
        drop = np.zeros(centres.shape[0], dtype=bool)
        for a_, b_ in pairs[np.argsort(pairs[:, 0], kind="stable")]:
            if not drop[a_]:
                drop[b_] = True
        centres, intensity, area = centres[~drop], intensity[~drop], area[~drop]
    return centres, intensity, area, rejected


def _refine(work, centres, area, method, pitch, radius, spot_r, moment_radius_px):
    """Refine the centres with the chosen estimator; ``FIT_FAILED`` where it fails.

    Returns the centres ``(row, col)`` px, the flags, and the window radius and background
    annulus ``(inner, outer)`` of the ``"window"`` method, px (NaN for the others).
    """
    centres = centres.copy()
    flags = np.zeros(centres.shape[0], dtype=np.uint8)
    moment_r, annulus = float("nan"), (float("nan"), float("nan"))
    if method == "window" and centres.shape[0]:
        moment_r, annulus = _window_geometry(spot_r, pitch, moment_radius_px)
        a_in, a_out = (0.0, 0.0) if not np.isfinite(annulus[0]) else annulus
        refined, _flux, _bg = _k.window_centroid_numba(
            work, np.ascontiguousarray(centres), moment_r, a_in, a_out, _WINDOW_MAX_ITER,
            _WINDOW_TOL_PX
        )
        good = np.all(np.isfinite(refined), axis=1)
        good[good] = np.hypot(*(refined[good] - centres[good]).T) < 0.25 * pitch
        centres[good] = refined[good]
        flags[~good] |= np.uint8(SpotFlag.FIT_FAILED)
    if method == "shape" and centres.shape[0]:
        use = ~_edge_mask(centres, radius, work.shape)
        refined, _std = shape_refine(work, centres, pitch, fit_radius(pitch, spot_r), use=use)
        centres = refined
    if method == "gaussian" and centres.shape[0]:
        sigma0 = np.clip(np.sqrt(area / 4.0), 0.5, radius / 2.0)
        params = _k.gaussian_fit_numba(
            work, np.ascontiguousarray(centres), sigma0, radius, _GAUSS_MAX_ITER
        )
        good = np.all(np.isfinite(params), axis=1)
        centres[good] = params[good, 1:3]
        flags[~good] |= np.uint8(SpotFlag.FIT_FAILED)
    return centres, flags, moment_r, annulus


def _better_disc_centres(work, centres, pitch, radius, spot_r):
    """The centres of micro-images too large for the window: centroid or mean-shape fit.

    ``centres`` are the thresholded centroids. A micro-image separated from its neighbours
    by a dark gap has its centroid exact (its whole edge lies inside the window); one that
    fills its cell does not (a window inside a uniform plateau has its centroid at its own
    centre wherever that is), and the fit of the spots' mean shape
    (:func:`~plenopiv.calibration.spot_shape.shape_refine`) takes over: when the stacked
    micro-image's diameter at half its height is at least :data:`_FILL_FOR_SHAPE` of the
    pitch (:func:`_fill_factor`). Returns the centres and the method's name.
    """
    if centres.shape[0] < 3 or _fill_factor(work, centres, pitch, radius) < _FILL_FOR_SHAPE:
        return centres, "centroid"
    use = ~_edge_mask(centres, radius, work.shape)
    shaped, _ = shape_refine(work, centres, pitch, fit_radius(pitch, spot_r), use=use)
    return shaped, "shape"


def _fill_factor(work, centres, pitch, radius):
    """The stacked micro-image's diameter at half its height over the pitch.

    Half height above its darkest ring within 0.75 pitch: about 0.6-0.7 for discs with dark
    gaps between them, 0.9-1 for cells they fill.
    """
    inner = centres[~_edge_mask(centres, 0.75 * pitch, work.shape)]
    if inner.shape[0] == 0:
        inner = centres
    energy, count = _k.radial_energy_numba(work, np.ascontiguousarray(inner, np.float64),
                                           0.75 * pitch, 0.25)
    have = count > 0
    if not have.any():
        return 0.0
    prof = np.where(have, energy / np.maximum(count, 1.0), np.nan)
    r = (np.arange(prof.size) + 0.5) * 0.25
    plateau = float(np.nanmedian(prof[have & (r < 0.2 * pitch)])) if np.any(
        have & (r < 0.2 * pitch)) else float(np.nanmax(prof))
    low = float(np.nanmin(prof))
    below = have & (prof < low + 0.5 * (plateau - low))
    return float(2.0 * r[np.argmax(below)] / pitch) if below.any() else 1.5


def _centre_std(work, centres, flags, intensity, method, geometry, gap_noise, spot_rms):
    """Standard error of each refined centre per axis, px, shape (N, 2).

    The fit of the spots' mean shape at the centres
    (:func:`~plenopiv.calibration.spot_shape.shape_uncertainty`, the complete spots building
    the shape) gives the standard error of a shape fit (``"shape"``, ``"gaussian"``). A first
    moment over a disc of radius R (the window, or the thresholded centroid's; ``"window"``,
    ``"centroid"``) moves with the noise by

        var = s^2 pi R^4 / (4 F^2) + g sigma^2 / F

    per axis: s the noise of the gaps (``gap_noise``), F the spot's light, sigma^2 its
    variance per axis (``spot_rms``^2 / 2), g the image units per photon, from how much
    more the shape fits' residual is than the gaps' noise (the median over the spots).
    """
    pitch, radius, moment_r, spot_r = geometry
    if centres.shape[0] == 0:
        return np.zeros((0, 2))
    use = ~_edge_mask(centres, radius, work.shape) & (flags == 0)
    if not use.any():
        use = np.ones(centres.shape[0], dtype=bool)
    fit_r = fit_radius(pitch, spot_r)
    std, noise = shape_uncertainty(work, centres, pitch, fit_r, use=use)
    if method not in ("window", "centroid"):
        return std
    r = moment_r if method == "window" else radius
    light = np.abs(np.asarray(intensity, dtype=np.float64))
    with np.errstate(invalid="ignore", divide="ignore"):
        per_photon = (noise ** 2 - gap_noise ** 2) * math.pi * fit_r ** 2 / light
        g = float(np.nanmedian(np.clip(per_photon[use], 0.0, None))) if use.any() else 0.0
        sigma2 = (spot_rms ** 2 / 2.0) if np.isfinite(spot_rms) else 0.0
        var = gap_noise ** 2 * math.pi * r ** 4 / (4.0 * light ** 2) + g * sigma2 / light
    one = np.sqrt(var)
    return np.column_stack([one, one])


def _image_flags(raw, sat_level, centres, intensity, flags, radius, opts):
    """``EDGE``, ``SATURATED`` and ``DIM`` flags of the sorted spots (uint8, shape (N,))."""
    new = np.zeros(centres.shape[0], dtype=np.uint8)
    new[_edge_mask(centres, radius, raw.shape)] |= np.uint8(SpotFlag.EDGE)
    if sat_level is not None and centres.shape[0]:
        sat_px = np.argwhere(raw == sat_level)
        near = cKDTree(sat_px).query_ball_point(centres, radius, return_length=True)
        new[np.asarray(near) > 0] |= np.uint8(SpotFlag.SATURATED)
    new[_dim_mask(centres, intensity, flags | new, opts["dim_fraction"])] |= np.uint8(SpotFlag.DIM)
    return new


def _local_reference(cand, height, shape, pitch):
    """Typical height of the bright spots around each candidate.

    Candidates are binned into cells of ``_REFERENCE_CELL`` pitches; a cell's level is the
    90th percentile of its candidates' heights, and a candidate's reference the highest level
    among its cell and the eight around it (so a dim lenslet is not its own reference).
    """
    cell = _REFERENCE_CELL * pitch
    n_r = max(int(math.ceil(shape[0] / cell)), 1)
    n_c = max(int(math.ceil(shape[1] / cell)), 1)
    ir = np.minimum((cand[:, 0] / cell).astype(np.int64), n_r - 1)
    ic = np.minimum((cand[:, 1] / cell).astype(np.int64), n_c - 1)
    key = ir * n_c + ic
    order = np.argsort(key, kind="stable")
    k_sorted, h_sorted = key[order], height[order]
    level = np.zeros(n_r * n_c)
    starts = np.flatnonzero(np.r_[True, k_sorted[1:] != k_sorted[:-1]])
    for a, b in zip(starts, np.r_[starts[1:], k_sorted.size], strict=True):
        level[k_sorted[a]] = np.percentile(h_sorted[a:b], 90)
    level = ndi.maximum_filter(level.reshape(n_r, n_c), size=3, mode="nearest")
    return level[ir, ic]


def _spot_size(work, centres, pitch):
    """Radius holding 99 % of a spot's light and its rms radius, px, from the stacked spots.

    The light of every given spot within half a pitch is summed in rings of 0.1 px about its
    centre. The darkest ring beyond 0.3 pitch is taken as the remaining background per pixel
    and removed; the radii follow from the cumulative sum. NaN when there are no spots or no
    light.
    """
    if centres.shape[0] == 0:
        return float("nan"), float("nan")
    r_max = 0.5 * pitch
    bin_px = 0.1
    energy, count = _k.radial_energy_numba(
        work, np.ascontiguousarray(centres, dtype=np.float64), r_max, bin_px
    )
    r = (np.arange(energy.size) + 0.5) * bin_px
    have = count > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        per_px = np.where(have, energy / np.where(have, count, 1.0), np.nan)
    outer = have & (r >= 0.3 * pitch)
    pedestal = float(np.nanmin(per_px[outer])) if np.any(outer) else 0.0
    e = np.where(have, energy - pedestal * count, 0.0)
    total = e.sum()
    if not total > 0:
        return float("nan"), float("nan")
    cum = np.cumsum(e)
    k = int(np.argmax(cum >= _ENERGY_FRACTION * total))
    r99 = min((k + 1) * bin_px, r_max)
    rms = math.sqrt(max(float(np.sum(e * r * r) / total), 0.0))
    return float(r99), float(rms)


def _window_fits(spot_r, pitch):
    """Whether spots of 99 % radius ``spot_r`` leave room for the window method (``"auto"``).

    The window (``spot_r + 1``) and its 2 px annulus must fit between neighbours
    (``2 spot_r + 4 <= pitch``), and the spot must be clearly smaller than its cell
    (``spot_r <= 0.35 pitch``); micro-images that fill the cell (white images, whose 99 %
    radius is near half the pitch) keep the thresholded centroid.
    """
    return bool(np.isfinite(spot_r) and 2.0 * spot_r + 4.0 <= pitch and spot_r <= 0.35 * pitch)


def window_radius_from_rms(spot_rms_px: float) -> float:
    """The window radius of a Gaussian spot of measured rms radius ``spot_rms_px``, px.

    A Gaussian holds 99 % of its light within ``sqrt(ln 100)`` = 2.15 times its rms radius;
    the window reaches 1.75 times that plus 0.5 px (:func:`_window_geometry`). The rms radius,
    weighted by the light, reads the spot's size where the 99 % radius, a threshold on the
    stacked profile's tail, is carried outwards by a background left in the gaps.
    """
    r99 = math.sqrt(math.log(1.0 / (1.0 - _ENERGY_FRACTION))) * float(spot_rms_px)
    return max(_WINDOW_SCALE * r99 + 0.5, r99 + _WINDOW_MARGIN_PX, 1.5)


def _window_geometry(spot_r, pitch, moment_radius_px):
    """Window radius and background annulus ``(inner, outer)`` of the window method, px.

    The window reaches 1.75 times the spot's 99 % radius (+ 0.5 px), where room allows, and at
    least that radius plus 1 px; the annulus lies just outside it,
    ``_ANNULUS_PX`` wide, and must stay clear of the neighbours' light (their 99 % radius
    one pitch away); ``(nan, nan)`` when less than a pixel of it fits (then the image's
    local background stands alone).
    """
    if not np.isfinite(spot_r):
        spot_r = 0.25 * pitch
    if moment_radius_px is None:
        rad = max(min(_WINDOW_SCALE * spot_r + 0.5, pitch - spot_r - 0.5 - _ANNULUS_PX - 0.5),
                  spot_r + _WINDOW_MARGIN_PX)
    else:
        rad = float(moment_radius_px)
        if not (np.isfinite(rad) and 1.0 <= rad <= pitch):
            raise ValueError(
                f"moment_radius_px must satisfy 1 <= moment_radius_px <= pitch ({pitch:.2f} px); "
                f"got {moment_radius_px!r}"
            )
    rad = float(min(max(rad, 1.5), 0.5 * pitch)) if moment_radius_px is None else rad
    inner = rad + 0.5
    outer = min(inner + _ANNULUS_PX, pitch - spot_r - 0.5)
    if outer - inner < 1.0:
        return rad, (float("nan"), float("nan"))
    return rad, (float(inner), float(outer))





def _dim_mask(centres, intensity, flags, dim_fraction, k=8):
    """Spots fainter than ``dim_fraction`` of the median of their ``k`` nearest complete spots."""
    ref = (flags & SpotFlag.EDGE) == 0
    if np.count_nonzero(ref) < 2:
        return np.zeros(centres.shape[0], dtype=bool)
    kk = min(k + 1, int(np.count_nonzero(ref)))
    _, idx = cKDTree(centres[ref]).query(centres, k=kk)
    neigh = intensity[ref][idx]
    # a spot is among its own neighbours when it is a reference spot; leave it out
    self_hit = np.flatnonzero(ref)[idx] == np.arange(centres.shape[0])[:, None]
    neigh = np.where(self_hit, np.nan, neigh)
    med = np.nanmedian(neigh, axis=1)
    return intensity < dim_fraction * med
