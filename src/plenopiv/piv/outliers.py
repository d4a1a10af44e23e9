"""Vector validation (normalised median test) and replacement of rejected vectors.

A field here is a ``(3, nz, ny, nx)`` array of displacements in the ``(z, y, x)`` order (any
one unit); the border of the vector grid is completed by linear extrapolation.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from plenopiv.errors import PIVError
from plenopiv.piv.inputs import _check_engine


def _as_field(u, v, w):
    arrays = [np.asarray(a, dtype=np.float64) for a in (u, v, w)]
    if arrays[0].ndim != 3 or any(a.shape != arrays[0].shape for a in arrays):
        raise ValueError(
            f"u, v, w have shapes {[a.shape for a in arrays]}: expected three arrays of one "
            "(nz, ny, nx) shape"
        )
    return np.stack(arrays)

def normalized_median_test(u, v, w, *, threshold=2.0, epsilon=0.1, iterations=1, engine="numba"):
    r"""Flag spurious vectors with the normalised median test in a 3x3x3 neighbourhood.

    Parameters
    ----------
    u, v, w : array_like, shape (nz, ny, nx)
        Displacement components in any one unit (voxels in :func:`correlate_volumes`).
        Non-finite values are outliers.
    threshold : float, keyword-only
        Normalised residual above which a vector is an outlier (dimensionless, > 0).
    epsilon : float, keyword-only
        Acceptable fluctuation level, same unit as ``u, v, w`` (>= 0).
    iterations : int, keyword-only
        Detection rounds (>= 1). Each round recomputes the medians without the vectors
        flagged so far; flags are never lifted.
    engine : {"numba", "numpy"}, keyword-only
        Kernel implementation.

    Returns
    -------
    outlier : ndarray of bool, shape (nz, ny, nx)
        True for vectors that fail the test.
    residual : ndarray, shape (nz, ny, nx)
        Largest normalised residual over the three components (dimensionless) from the last
        round; NaN where a vector has no usable neighbour (it is then never flagged, unless
        it is itself non-finite).

    Notes
    -----
    For each component, with ``u_0`` the tested vector, ``u_m`` the median of its usable
    neighbours ``u_i`` (up to 26, the centre excluded) and ``r_m`` the median of the
    neighbours' residuals ``r_i = |u_i - u_m|``, the normalised residual is (Westerweel &
    Scarano 2005, eq. 2)

    .. math:: r_0^* = \frac{|u_0 - u_m|}{r_m + \varepsilon}

    A vector is an outlier when ``max(r_0^*(u), r_0^*(v), r_0^*(w)) > threshold``.

    On the border of the grid the missing neighbours are supplied by linear extrapolation
    (``f[-1] = 2 f[0] - f[1]``, usable only where both sources are). The plain one-sided
    neighbourhood would flag every border vector of a steep linear flow: there the median of
    the neighbours lies a whole vector spacing times the gradient away from the vector.

    References
    ----------
    J. Westerweel and F. Scarano, "Universal outlier detection for PIV data", Experiments in
    Fluids 39, 1096-1100 (2005). doi:10.1007/s00348-005-0016-6
    """
    field_vox = _as_field(u, v, w)
    if not (threshold > 0):
        raise ValueError(f"threshold = {threshold!r}: expected a number > 0")
    if not (epsilon >= 0):
        raise ValueError(f"epsilon = {epsilon!r}: expected a number >= 0")
    if not isinstance(iterations, (int, np.integer)) or iterations < 1:
        raise ValueError(f"iterations = {iterations!r}: expected an int >= 1")
    kernels = _check_engine(engine)
    return _median_test(field_vox, threshold, epsilon, iterations, kernels)


def _pad_extrapolated(field_vox, usable=None):
    """Pad a ``(3, nz, ny, nx)`` field by one vector per side by linear extrapolation.

    Along every axis holding at least two vectors, ``f[-1] = 2 f[0] - f[1]`` (and likewise at
    the far end); a padded vector is usable only if both vectors it comes from are. Returns
    the padded field, the padded mask (or None) and the pad width per axis.
    """
    f = field_vox
    ok = usable
    pads = []
    for axis in (1, 2, 3):
        if f.shape[axis] < 2:
            pads.append(0)
            continue
        pads.append(1)

        def take(a, i, ax=axis):
            return np.take(a, [i], axis=ax)

        f = np.concatenate(
            [2 * take(f, 0) - take(f, 1), f, 2 * take(f, -1) - take(f, -2)], axis=axis
        )
        if ok is not None:
            ok = np.concatenate(
                [
                    take(ok, 0, axis - 1) & take(ok, 1, axis - 1),
                    ok,
                    take(ok, -1, axis - 1) & take(ok, -2, axis - 1),
                ],
                axis=axis - 1,
            )
    return f, ok, pads


def _crop(padded, pads):
    """Undo :func:`_pad_extrapolated` on a ``(3, ...)`` array."""
    inner = tuple(slice(p, n - p) for p, n in zip(pads, padded.shape[1:], strict=True))
    return padded[(slice(None),) + inner]


def _extrapolated_neighbours(field_vox, usable, kernels):
    """Neighbour median and residual median with the border completed by extrapolation.

    The field is padded by :func:`_pad_extrapolated`, so a linear field has the same
    symmetric neighbourhood at the border as inside, instead of a one-sided one whose median
    is off by a whole vector spacing times the gradient (which would flag every border
    vector of a strong linear flow).
    """
    f, ok, pads = _pad_extrapolated(field_vox, usable)
    median, spread = kernels.neighbour_median(np.ascontiguousarray(f), np.ascontiguousarray(ok))
    return _crop(median, pads), _crop(spread, pads)


def _smooth_predictor(field_vox):
    """Low-pass a predictor with the binomial filter [1, 2, 1]/4 along each axis.

    The border is padded by linear extrapolation, so a linear field passes unchanged; the
    shortest wavelength on the vector grid (two vector spacings) is removed, which keeps the
    iteration of window-deformation passes stable (Schrijer & Scarano 2008).
    """
    f, _, pads = _pad_extrapolated(field_vox)
    for axis, p in zip((1, 2, 3), pads, strict=True):
        if p:
            f = scipy.ndimage.correlate1d(f, [0.25, 0.5, 0.25], axis=axis, mode="nearest")
    return _crop(f, pads)


def _median_test(field_vox, threshold, epsilon, iterations, kernels):
    outlier = ~np.all(np.isfinite(field_vox), axis=0)
    residual = np.full(outlier.shape, np.nan)
    for _ in range(iterations):
        median, spread = _extrapolated_neighbours(field_vox, ~outlier, kernels)
        with np.errstate(invalid="ignore"):
            r = np.abs(field_vox - median) / (spread + epsilon)
        has_neighbours = np.all(np.isfinite(median), axis=0)
        residual = np.where(
            has_neighbours, np.max(np.where(np.isnan(r), np.inf, r), axis=0), np.nan
        )
        new = has_neighbours & ~outlier & (residual > threshold)
        if not new.any():
            break
        outlier |= new
    return outlier, residual


def replace_outliers(u, v, w, outlier, *, engine="numba"):
    """Replace flagged vectors by the median of their unflagged 3x3x3 neighbours.

    Parameters
    ----------
    u, v, w : array_like, shape (nz, ny, nx)
        Displacement components (any one unit).
    outlier : array_like of bool, shape (nz, ny, nx)
        Vectors to replace (e.g. from :func:`normalized_median_test`).
    engine : {"numba", "numpy"}, keyword-only
        Kernel implementation.

    Returns
    -------
    u, v, w : ndarray
        New arrays with the outliers replaced; the inputs are not changed.
    n_replaced : int
        Number of vectors replaced.

    Raises
    ------
    PIVError
        If every vector is flagged (nothing to replace them with).

    Notes
    -----
    Replacement sweeps the field repeatedly: a flagged vector with at least one usable
    neighbour takes the component-wise median of those neighbours (with the border completed
    by linear extrapolation, as in :func:`normalized_median_test`) and becomes usable for the
    next sweep, so that clusters of outliers are filled from their edges inwards.
    """
    field_vox = _as_field(u, v, w)
    flags = np.asarray(outlier, dtype=bool)
    if flags.shape != field_vox.shape[1:]:
        raise ValueError(f"outlier has shape {flags.shape}: expected {field_vox.shape[1:]}")
    kernels = _check_engine(engine)
    filled = _replace(field_vox, flags, kernels)
    return filled[0], filled[1], filled[2], int(flags.sum())


def _replace_mean(field_vox, outlier, kernels):
    """Like :func:`_replace`, with the mean of the usable 3x3x3 neighbours for their median.

    The border is completed by linear extrapolation as well.
    """
    usable = ~outlier & np.all(np.isfinite(field_vox), axis=0)
    if not usable.any():
        return _replace(field_vox, outlier, kernels)  # raises the same error
    filled = field_vox.copy()
    ones = np.ones((1, 3, 3, 3))
    ones[0, 1, 1, 1] = 0.0
    while not usable.all():
        f, ok, pads = _pad_extrapolated(np.where(usable[None], filled, 0.0), usable)
        f = np.where(ok[None], f, 0.0)
        total = scipy.ndimage.correlate(f, ones, mode="constant")
        count = scipy.ndimage.correlate(ok.astype(float)[None], ones, mode="constant")
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = _crop(total / count, pads)
        count = _crop(count, pads)[0]
        fillable = ~usable & (count > 0)
        filled[:, fillable] = mean[:, fillable]
        usable = usable | fillable
    return filled


def _replace(field_vox, outlier, kernels):
    usable = ~outlier & np.all(np.isfinite(field_vox), axis=0)
    if not usable.any():
        raise PIVError(
            f"all {usable.size} vectors are outliers or empty: nothing to replace them with; "
            "check that both volumes hold particles and that the windows are large enough"
        )
    filled = field_vox.copy()
    while not usable.all():
        median, _ = _extrapolated_neighbours(filled, usable, kernels)
        fillable = ~usable & np.all(np.isfinite(median), axis=0)
        filled[:, fillable] = median[:, fillable]
        usable = usable | fillable
    return filled

