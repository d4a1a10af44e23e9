"""Calibration step 1b: index the spots on a regular lattice and fit it (:func:`fit_lattice`).

The grid type and primitive vectors come from the neighbours' directions, the indices are
assigned outwards from the central spot, and origin, basis (and a hexagonal grid's odd-row
shift) are fitted by linear least squares, optionally with each coordinate's periodic bias
against its sub-pixel phase (``phase_harmonics``). Every length is in pixels (px).

See docs/methods.md#lattice-fit for the steps and the lattice convention.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import Delaunay, cKDTree

from plenopiv.calibration.lattice_quality import (
    MIN_ON_LATTICE_FRACTION,
    check_lattice_shape,
    not_a_lattice,
)
from plenopiv.calibration.spot_types import (
    _NOT_FITTED,
    GRIDS,
    ON_LATTICE_RADIUS,
    Lattice,
    SpotFlag,
    SpotSet,
    _check_choice,
    _check_fraction,
    _edge_mask,
    _lattice_positions,
)
from plenopiv.errors import CalibrationError

# The phase-bias terms of a lattice fit are kept when their chi-square against their own
# standard errors exceeds this (a "10 sigma" amplitude)
_PHASE_CHI2 = 100.0
_NEIGHBOUR_FACTOR = 1.25  # neighbours: closer than this times the median nearest distance
_INDEX_TOL = 0.25  # largest fractional-index error of a lattice spot


def _neighbour_vectors(pts):
    """Vectors ``(d_row, d_col)`` to the neighbours, the median spacing, neighbours per point."""
    k = min(7, pts.shape[0])
    dist, idx = cKDTree(pts).query(pts, k=k)
    d0 = float(np.median(dist[:, 1]))
    near = (dist[:, 1:] < _NEIGHBOUR_FACTOR * d0) & (dist[:, 1:] > 0)
    vec = pts[idx[:, 1:]] - pts[:, None, :]
    count = near.sum(axis=1)
    return vec[near], d0, count


def _classify(vec, grid):
    """Grid type and the angle of the lattice axis nearest the image +col axis, rad."""
    phi = np.arctan2(vec[:, 0], vec[:, 1])  # CCW in (x = col, y = row)
    z4 = np.mean(np.exp(4j * phi))
    z6 = np.mean(np.exp(6j * phi))
    r4, r6 = abs(z4), abs(z6)
    if grid == "auto":
        if max(r4, r6) < 0.5:
            raise CalibrationError(
                "the spot neighbours do not form a square or hexagonal lattice: the 4-fold order "
                f"of their directions is {r4:.2f} and the 6-fold order {r6:.2f}; expected one of "
                "them near 1 (check the spot detection, or pass grid=)"
            )
        grid = "hexagonal" if r6 > r4 else "square"
    theta = float(np.angle(z6) / 6.0) if grid == "hexagonal" else float(np.angle(z4) / 4.0)
    return grid, theta


def _initial_basis(vec, grid, theta):
    """Primitive vectors ``a1`` (lattice +col) and ``a2`` (next row), ``(d_row, d_col)`` px."""
    phi = np.arctan2(vec[:, 0], vec[:, 1])
    alpha = np.angle(np.exp(1j * (phi - theta)))
    step = math.pi / 2 if grid == "square" else math.pi / 3
    cls = np.rint(alpha / step).astype(int)
    n_cls = 4 if grid == "square" else 6
    cls %= n_cls
    half = n_cls // 2

    def median_of(k):
        v = np.concatenate([vec[cls == k], -vec[cls == (k + half) % n_cls]])
        if v.shape[0] == 0:
            raise CalibrationError(
                f"no spot neighbours along lattice direction {k * step:.2f} rad; expected a "
                "2-D lattice"
            )
        return np.median(v, axis=0)

    return median_of(0), median_of(1)


def _affine_fit(mn, pts):
    """Fit ``pts = o + m a1 + n a2`` by least squares; return ``o`` and ``P = [a1, a2]``."""
    x = np.column_stack([np.ones(mn.shape[0]), mn.astype(np.float64)])
    coef, *_ = np.linalg.lstsq(x, pts, rcond=None)
    return coef[0], coef[1:].T


def _fractional_index(pts, o, p):
    return np.linalg.solve(p, (pts - o).T).T


def _grow_indices(pts, a1, a2, d0, seeds):
    """Fit the axial lattice ``o + m a1 + n a2``, growing outwards from the most central seed.

    ``seeds`` marks the points that may start it (those with a full set of neighbours).
    """
    centre = np.median(pts, axis=0)
    dist2 = np.sum((pts - centre) ** 2, axis=1)
    seed = (
        int(np.argmin(np.where(seeds, dist2, np.inf))) if np.any(seeds) else int(np.argmin(dist2))
    )
    o = pts[seed].copy()
    p = np.column_stack([a1, a2])
    dist = np.hypot(*(pts - o).T)
    radius = 4.0 * d0
    while True:
        sel = dist <= radius
        q = _fractional_index(pts[sel], o, p)
        mn = np.rint(q)
        good = np.max(np.abs(q - mn), axis=1) < _INDEX_TOL
        if np.count_nonzero(good) >= 3:
            o, p = _affine_fit(mn[good], pts[sel][good])
        if radius > dist.max():
            break
        radius *= 1.6
    return o, p


def fit_lattice(spots, *, grid="auto", expected_pitch_px=None, image_shape=None,
                window_radius_px=None, max_missing_fraction=None, outlier_threshold_px=None,
                min_size=4, phase_harmonics=0, max_shape_error=0.05, what="the spots"):
    """Index the spots on a regular lattice and fit it by linear least squares.

    Parameters
    ----------
    spots : SpotSet or array_like, shape (N, 2)
        Spot centres ``(row, col)`` px. A :class:`SpotSet` also brings its flags, image shape,
        window radius and grid hint.
    grid : {"auto", "square", "hexagonal"}
        Grid type; ``"auto"`` (default) classifies it from the directions between neighbouring
        spots (90 degree vs 60 degree symmetry), unless the SpotSet names one.
    expected_pitch_px : float, optional
        When given, a measured spacing more than 20 % away raises CalibrationError.
    image_shape : tuple of int, optional
        ``(n_rows, n_cols)`` px; taken from the SpotSet when not given. With it, a spot is
        partial (``EDGE``) when the window of radius ``window_radius_px`` around its measured
        or its *fitted* centre leaves the image (a cut spot's measured centre is pulled
        inwards and can look complete), and missing positions are counted inside the image;
        without it, inside the convex hull of the spots.
    window_radius_px : float, optional
        Radius deciding whether a spot is complete, px (the SpotSet's, or half the spacing).
    max_missing_fraction : float, optional
        Largest accepted fraction of missing lattice positions; None (default) accepts any
        and reports them in ``missing_index``.
    outlier_threshold_px : float, optional
        Residual length above which a spot is an outlier, px. Default: 6 times the robust
        (median-absolute-deviation) residual scale per axis, at least 2 % of the pitch.
    min_size : int
        Smallest accepted lattice, ``min_size`` lenslets a side.
    phase_harmonics : int
        Harmonics ``n = 1 .. phase_harmonics`` of the periodic bias of each coordinate
        against its own sub-pixel phase, fitted with the lattice and removed from it
        (``phase_bias_px``; module docstring, step 4); 0 (default): none.
    max_shape_error : float or None
        Largest departure from the grid type's shape (default 5 %, angles in radians;
        ``lattice_quality.check_lattice_shape``), else CalibrationError; None: no check.
    what : str
        How errors name the image (``"the focal-point image"``; default ``"the spots"``).

    Returns
    -------
    Lattice

    Raises
    ------
    CalibrationError
        Too few spots, no lattice, a spacing far from ``expected_pitch_px``, or more missing
        positions than ``max_missing_fraction``.
    ValueError
        An option is outside its valid set. (The steps: docs/methods.md#lattice-fit.)

    Examples
    --------
    >>> import numpy as np
    >>> from plenopiv.calibration.spots import detect_spots, fit_lattice
    >>> rr, cc = np.mgrid[0:120, 0:120] % 20 - np.array([10.3, 9.8])[:, None, None]
    >>> lattice = fit_lattice(detect_spots(np.exp(-(rr**2 + cc**2) / 2), expected_pitch_px=20.0))
    >>> lattice.grid, lattice.pitch_px.round(2).tolist(), lattice.origin_px.round(1).tolist()
    ('square', [20.0, 20.0], [10.3, 9.8])
    """
    min_size, max_missing_fraction, phase_harmonics = _checked_options(
        grid, min_size, max_missing_fraction, phase_harmonics)
    pts, flags, image_shape, window_radius_px, grid = _spot_input(
        spots, grid, image_shape, window_radius_px, min_size)
    centre_std = spots.centre_std_px if isinstance(spots, SpotSet) else None
    intensity = spots.intensity if isinstance(spots, SpotSet) else None
    flags, window_radius_px = _flag_cut_spots(pts, flags, image_shape, window_radius_px)
    usable = _enough_clean_spots(flags, min_size)
    vec, d0, n_neighbours = _neighbour_vectors(pts[usable])
    _check_spacing(d0, expected_pitch_px)
    window_radius_px = 0.5 * d0 if window_radius_px is None else float(window_radius_px)
    grid, theta = _classify(vec, grid)
    a1, a2 = _initial_basis(vec, grid, theta)
    full = n_neighbours == (6 if grid == "hexagonal" else 4)
    o_ax, p_ax = _grow_indices(pts[usable], a1, a2, d0, full)
    index, flags = _lattice_index(pts, flags, o_ax, p_ax, grid, d0, image_shape,
                                  window_radius_px)
    fit, fitted, flags = _robust_fit(index, pts, grid, flags, d0, outlier_threshold_px,
                                     phase_harmonics, min_size)
    coef, res, cov_scale, bias = fit
    origin, basis, shift = coef[0], np.stack([coef[1], coef[2]]), _shift(coef, grid)
    if max_shape_error is not None:
        _check_shape(grid, basis, shift, float(max_shape_error), res, flags, what)
    _check_extent(index[fitted], min_size)
    missing = _missing(
        index, flags, origin, basis, shift, image_shape, window_radius_px, pts[fitted]
    )
    _check_missing(missing, flags, max_missing_fraction)
    std = _standard_errors(coef, res, cov_scale, bias, fitted, phase_harmonics)
    return Lattice(
        grid=grid, origin_px=origin, basis=basis, centres_px=pts, grid_index=index,
        residual_px=res, inlier=fitted, flags=flags,
        rms_residual_px=float(np.sqrt(np.mean(np.sum(res[fitted] ** 2, axis=1)))),
        missing_index=missing, basis_std_px=np.stack([std[1], std[2]]), origin_std_px=std[0],
        odd_row_shift_px=shift, image_shape=image_shape, phase_bias_px=bias,
        centre_std_px=centre_std, intensity=intensity,
    )


def _checked_options(grid, min_size, max_missing_fraction, phase_harmonics):
    """Check the options of :func:`fit_lattice`; return ``min_size``, the fraction, harmonics."""
    _check_choice("grid", grid, ("auto",) + GRIDS)
    min_size = int(min_size)
    if min_size < 2:
        raise ValueError(f"min_size must be an integer >= 2; got {min_size!r}")
    if max_missing_fraction is not None:
        max_missing_fraction = _check_fraction(
            "max_missing_fraction", max_missing_fraction, low_open=False
        )
    phase_harmonics = int(phase_harmonics)
    if phase_harmonics < 0:
        raise ValueError(f"phase_harmonics must be an integer >= 0; got {phase_harmonics!r}")
    return min_size, max_missing_fraction, phase_harmonics


def _spot_input(spots, grid, image_shape, window_radius_px, min_size):
    """Centres (N, 2) px, flags, image shape, window radius and grid of the fit's input.

    A :class:`SpotSet` brings its flags, image shape, window radius and grid hint (each
    unless given); an array brings centres alone. Raises when there are fewer than
    ``min_size ** 2`` spots.
    """
    if isinstance(spots, SpotSet):
        pts = spots.centres_px.astype(np.float64)
        flags = spots.flags.astype(np.uint8).copy()
        if image_shape is None:
            image_shape = spots.image_shape
        if window_radius_px is None:
            window_radius_px = spots.window_radius_px
        if grid == "auto" and spots.grid is not None:
            grid = spots.grid
    else:
        pts = np.asarray(spots, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(
                f"spots must be a SpotSet or an array of shape (N, 2); got shape {pts.shape}"
            )
        if not np.all(np.isfinite(pts)):
            raise ValueError("spot centres must be finite")
        flags = np.zeros(pts.shape[0], dtype=np.uint8)
    n, need = pts.shape[0], min_size * min_size
    if n < need:
        raise CalibrationError(
            f"found {n} spots, expected a lattice of at least {min_size} x {min_size} "
            f"({need} spots)"
        )
    if image_shape is not None:
        image_shape = tuple(int(s) for s in image_shape)
    return pts, flags, image_shape, window_radius_px, grid


def _flag_cut_spots(pts, flags, image_shape, window_radius_px):
    """Flag ``EDGE`` the spots whose measured window leaves the image; new flags and radius.

    Without a window radius, it is half the median nearest-neighbour distance of the clean
    spots. Nothing is flagged without an image shape.
    """
    flags = flags.copy()
    if image_shape is None:
        return flags, window_radius_px
    if window_radius_px is None:
        clean = pts[(flags & _NOT_FITTED) == 0]
        if clean.shape[0] >= 2:
            window_radius_px = 0.5 * float(np.median(cKDTree(clean).query(clean, k=2)[0][:, 1]))
    if window_radius_px is not None:
        flags[_edge_mask(pts, float(window_radius_px), image_shape)] |= np.uint8(SpotFlag.EDGE)
    return flags, window_radius_px


def _enough_clean_spots(flags, min_size):
    """The spots that may enter the fit; raises when fewer than ``min_size ** 2``."""
    usable = (flags & _NOT_FITTED) == 0
    need = min_size * min_size
    if np.count_nonzero(usable) < need:
        raise CalibrationError(
            f"found {np.count_nonzero(usable)} complete, clean spots among {flags.shape[0]}; "
            f"expected a lattice of at least {min_size} x {min_size} ({need} spots)"
        )
    return usable


def _check_spacing(d0, expected_pitch_px):
    """Raise when the median spot spacing ``d0`` is more than 20 % from the expected pitch."""
    if expected_pitch_px is not None and abs(d0 / float(expected_pitch_px) - 1.0) > 0.2:
        raise CalibrationError(
            f"median spot spacing is {d0:.2f} px; expected about {float(expected_pitch_px):.2f} px "
            "(expected_pitch_px)"
        )


def _lattice_index(pts, flags, o_ax, p_ax, grid, d0, image_shape, window_radius_px):
    """Grid index ``(row, col)`` of every spot from the grown axial lattice; new flags.

    Spots off the lattice by a quarter index or more are ``OFF_LATTICE``; with an image
    shape, a spot whose window around its *fitted* position leaves the image is ``EDGE``
    (a cut spot's measured centre is pulled inwards and can look complete); partial spots
    take the nearest free position, and the index starts at 0.
    """
    flags = flags.copy()
    q = _fractional_index(pts, o_ax, p_ax)
    mn = np.rint(q).astype(np.int64)
    frac = np.max(np.abs(q - mn), axis=1)
    flags[(frac >= _INDEX_TOL) & ((flags & SpotFlag.EDGE) == 0)] |= np.uint8(SpotFlag.OFF_LATTICE)
    index = _grid_index(mn, grid, flags)
    coef, _res, _, _ = _offset_fit(index, pts, grid, (flags & _NOT_FITTED) == 0)
    if image_shape is not None:
        pred = _lattice_positions(index, coef[0], coef[1:3], _shift(coef, grid))
        flags[_edge_mask(pred, window_radius_px, image_shape)] |= np.uint8(SpotFlag.EDGE)
    index, flags = _place_edge_spots(index, pts, flags, coef, grid, d0)
    return _normalise_index(index, grid, flags), flags


def _robust_fit(index, pts, grid, flags, d0, outlier_threshold_px, phase_harmonics, min_size):
    """Least squares with outlier rejection, twice; duplicates resolved by residual.

    Returns the last :func:`_offset_fit` result, the mask of the spots it used and the flags.
    """
    need = min_size * min_size
    fitted = (flags & _NOT_FITTED) == 0
    fit = _offset_fit(index, pts, grid, fitted, phase_harmonics)
    for _ in range(2):
        fitted, flags = _reject(index, fit[1], flags, fitted, d0, outlier_threshold_px)
        if np.count_nonzero(fitted) < need:
            raise CalibrationError(
                f"only {np.count_nonzero(fitted)} of {pts.shape[0]} spots fit a regular lattice; "
                f"expected at least {need} ({min_size} x {min_size})"
            )
        fit = _offset_fit(index, pts, grid, fitted, phase_harmonics)
    return fit, fitted, flags


def _check_shape(grid, basis, shift, tol, res, flags, what="the spots"):
    """:func:`check_lattice_shape`, its error following what the spots show.

    The shape of the other grid type (a row spacing of sqrt(3)/2 of the pitch forced on a
    square grid, or of 1 on a hexagonal one): the grid type is wrong, and the error says so.
    Otherwise, when fewer than :data:`MIN_ON_LATTICE_FRACTION` of the complete spots lie near
    a node, the image holds no lattice at all (a scene, a particle image): the error says
    that, naming the image ``what``, and blames no grid type.
    """
    try:
        check_lattice_shape(grid, basis, shift, tol)
    except CalibrationError as err:
        p_row, p_col = np.hypot(basis[:, 0], basis[:, 1])
        other_ratio = math.sqrt(3.0) / 2.0 if grid == "square" else 1.0
        if abs(p_row / (other_ratio * p_col) - 1.0) <= tol:
            raise
        complete = (flags & SpotFlag.EDGE) == 0
        pitch = float(np.mean(np.hypot(basis[:, 0], basis[:, 1])))
        r = np.hypot(*res[complete].T)
        fraction = float(np.mean(r <= ON_LATTICE_RADIUS * pitch)) if r.size else 1.0
        if fraction < MIN_ON_LATTICE_FRACTION:
            rms = float(np.sqrt(np.mean(r * r))) if r.size else 0.0
            raise not_a_lattice(what, fraction, r.size, grid, pitch, rms) from err
        raise


def _check_extent(index, min_size):
    """Raise when the fitted spots span fewer than ``min_size`` rows or columns."""
    extent = index.max(axis=0) - index.min(axis=0) + 1
    if min(extent) < min_size:
        raise CalibrationError(
            f"the indexed spots span a lattice of {extent[0]} x {extent[1]} lenslets; expected at "
            f"least {min_size} x {min_size}"
        )


def _check_missing(missing, flags, max_missing_fraction):
    """Raise when more than ``max_missing_fraction`` of the expected positions are empty."""
    is_edge = (flags & SpotFlag.EDGE) != 0
    on_lattice = (flags & SpotFlag.OFF_LATTICE) == 0
    n_expected = int(np.count_nonzero(~is_edge & on_lattice)) + missing.shape[0]
    if (
        max_missing_fraction is not None
        and n_expected
        and missing.shape[0] / n_expected > max_missing_fraction
    ):
        shown = ", ".join(f"({i}, {j})" for i, j in missing[:8]) + (
            " ..." if missing.shape[0] > 8 else ""
        )
        raise CalibrationError(
            f"{missing.shape[0]} of {n_expected} lattice positions inside the image hold no spot "
            f"({100 * missing.shape[0] / n_expected:.1f} %), more than max_missing_fraction = "
            f"{100 * max_missing_fraction:g} %; missing grid indices {shown}"
        )


def _standard_errors(coef, res, cov_scale, bias, fitted, phase_harmonics):
    """Standard errors of the lattice coefficients, px: rows origin, e_row, e_col[, shift].

    Columns are the axes (row, col); the residual variance per axis counts the phase terms
    that were kept among the fitted parameters.
    """
    n_par = coef.shape[0] + np.array([2 * phase_harmonics * bool(np.any(bias[:, a]))
                                      for a in (0, 1)])
    dof = np.maximum(int(np.count_nonzero(fitted)) - n_par, 1)
    s2 = np.sum(res[fitted] ** 2, axis=0) / dof  # per axis (row, col), px^2
    return np.sqrt(np.column_stack([np.diag(cov_scale[a]) * s2[a] for a in (0, 1)]))


def _grid_index(mn, grid, flags):
    """``(row, col)`` grid indices from axial ``(m, n)``, the first row and column at 0.

    ``n`` counts lattice rows and ``a2`` steps one row, so on a hexagonal grid the position
    along ``a1`` is ``u = m + n / 2``. Row ``i = n - n_min`` (row 0 is even); in even rows
    ``u`` has the fractional part ``f = (n_min / 2) mod 1`` and in odd rows ``f + 1/2``, so
    ``j = u - f - (i mod 2) / 2`` is a whole number and odd rows sit half a step towards +col.
    Off-lattice spots do not decide where the index starts.
    """
    m, n = mn[:, 0], mn[:, 1]
    on = (flags & SpotFlag.OFF_LATTICE) == 0
    if not np.any(on):
        on = np.ones(mn.shape[0], dtype=bool)
    i = n - n[on].min()
    if grid == "square":
        j = m
    else:
        f = (n[on].min() / 2.0) % 1.0
        j = np.rint(m + n / 2.0 - f - (i % 2) / 2.0).astype(np.int64)
    j = j - j[on].min()
    return np.column_stack([i, j]).astype(np.int64)


def _shift(coef, grid):
    """Return the odd-row shift from the fit coefficients (zero on a square grid)."""
    return coef[3] if grid == "hexagonal" else np.zeros(2)


def _place_edge_spots(index, pts, flags, coef, grid, d0):
    """Give each partial spot the nearest lattice position that no complete spot holds.

    A cut spot's centroid is pulled towards the image, up to half a pitch, so rounding can
    hand it a neighbour's index. Candidates are the 3 x 3 indices around the rounded one;
    a spot farther than 0.75 of the spacing from every free candidate is OFF_LATTICE.
    """
    index = index.copy()
    flags = flags.copy()
    edge = np.flatnonzero((flags & SpotFlag.EDGE) != 0)
    if edge.size == 0:
        return index, flags
    held = (flags & (SpotFlag.EDGE | SpotFlag.OFF_LATTICE)) == 0
    taken = {(int(i), int(j)) for i, j in index[held]}
    offsets = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)])
    shift = _shift(coef, grid)
    for k in edge:
        cand = index[k] + offsets
        dist = np.hypot(*(_lattice_positions(cand, coef[0], coef[1:3], shift) - pts[k]).T)
        free = np.array([(int(i), int(j)) not in taken for i, j in cand])
        if not free.any() or dist[free].min() > 0.75 * d0:
            flags[k] |= np.uint8(SpotFlag.OFF_LATTICE)
            continue
        best = np.flatnonzero(free)[np.argmin(dist[free])]
        index[k] = cand[best]
        taken.add((int(cand[best, 0]), int(cand[best, 1])))
    return index, flags


def _normalise_index(index, grid, flags):
    """Shift indices so the first row and column holding an on-lattice spot are 0.

    On a hexagonal grid, a shift by an odd number of rows swaps which rows are odd; the
    model ``origin + i e_row + j e_col + (i mod 2) shift`` keeps its form (with the new shift
    ``e_col - shift``) when odd rows of the new labelling also take ``j - 1``.
    """
    on = (flags & SpotFlag.OFF_LATTICE) == 0
    if not np.any(on):
        on = np.ones(index.shape[0], dtype=bool)
    new = index.copy()
    di = int(new[on, 0].min())
    new[:, 0] -= di
    if grid == "hexagonal" and di % 2:
        new[:, 1] -= new[:, 0] % 2
    new[:, 1] -= int(new[on, 1].min())
    return new


def _design(index, grid):
    """Design matrix of the lattice model: columns 1, i, j and (hexagonal) i mod 2."""
    cols = [np.ones(index.shape[0]), index[:, 0].astype(np.float64), index[:, 1].astype(np.float64)]
    if grid == "hexagonal":
        cols.append((index[:, 0] % 2).astype(np.float64))
    return np.column_stack(cols)


def _phase_design(x, harmonics):
    """Columns ``sin(2 pi n x), cos(2 pi n x)``, ``n = 1 .. harmonics``, of coordinates x."""
    cols = []
    for k in range(1, harmonics + 1):
        cols += [np.sin(2.0 * math.pi * k * x), np.cos(2.0 * math.pi * k * x)]
    return np.column_stack(cols) if cols else np.zeros((x.shape[0], 0))


def _phases_spread(x, harmonics):
    """Whether coordinates ``x`` sample every sub-pixel phase (no harmonic bunches them)."""
    return all(
        abs(np.mean(np.exp(2j * math.pi * k * x))) <= 0.8 for k in range(1, harmonics + 1)
    )


def _offset_fit(index, pts, grid, fitted, harmonics=0):
    """Fit ``pts = origin + i e_row + j e_col (+ (i mod 2) shift) (+ phase bias)``.

    Returns the coefficient rows (origin, e_row, e_col[, odd-row shift]), the residuals of every
    spot (less its phase bias), ``(X^T X)^-1`` of each axis for the standard errors (the
    lattice block, shape (2, k, k)) and the fitted phase bias of every spot (N, 2; zero
    without harmonics, or on an axis whose phases bunch).
    """
    x = _design(index, grid)
    k = x.shape[1]
    coef = np.zeros((k, 2))
    cov_scale = np.zeros((2, k, k))
    bias = np.zeros(pts.shape)
    n_fit = int(np.count_nonzero(fitted))
    for a in (0, 1):
        xa = x
        if harmonics and n_fit >= 10 * (k + 2 * harmonics) \
                and _phases_spread(pts[fitted, a], harmonics):
            xa = np.column_stack([x, _phase_design(pts[:, a], harmonics)])
            ca, *_ = np.linalg.lstsq(xa[fitted], pts[fitted, a], rcond=None)
            inv = np.linalg.inv(xa[fitted].T @ xa[fitted])
            r = pts[fitted, a] - xa[fitted] @ ca
            s2 = float(r @ r) / max(n_fit - xa.shape[1], 1)
            c = ca[k:]
            # keep the phase terms only when they stand far out of their own noise (a lattice
            # whose lenslets are irregularly placed would otherwise pass its scatter on)
            chi2 = float(c @ np.linalg.solve(inv[k:, k:], c)) / s2 if s2 > 0 else np.inf
            if not chi2 > _PHASE_CHI2:
                xa = x
        ca, *_ = np.linalg.lstsq(xa[fitted], pts[fitted, a], rcond=None)
        coef[:, a] = ca[:k]
        bias[:, a] = xa[:, k:] @ ca[k:]
        cov_scale[a] = np.linalg.inv(xa[fitted].T @ xa[fitted])[:k, :k]
    res = pts - x @ coef - bias
    return coef, res, cov_scale, bias


def _reject(index, res, flags, fitted, d0, outlier_threshold_px):
    """Flag outliers and duplicate indices from the last fit; return the new fit mask and flags.

    The outlier limit comes from the residuals of the spots of the last fit (``fitted``).
    Among spots sharing an index, a clean spot beats an outlier, a complete one beats a
    partial one, then the smaller residual wins; the others are DUPLICATE.
    """
    flags = flags & ~np.uint8(SpotFlag.OUTLIER | SpotFlag.DUPLICATE)
    r = res[fitted]
    if outlier_threshold_px is None:
        scale = 1.4826 * np.median(np.abs(r - np.median(r, axis=0)), axis=0)
        limit = max(6.0 * float(np.hypot(*scale)), 0.02 * d0)
    else:
        limit = float(outlier_threshold_px)
    length = np.hypot(res[:, 0], res[:, 1])
    clean = (flags & _NOT_FITTED) == 0
    flags[clean & (length > limit)] |= np.uint8(SpotFlag.OUTLIER)
    live = np.flatnonzero((flags & SpotFlag.OFF_LATTICE) == 0)
    outlier = (flags[live] & SpotFlag.OUTLIER) != 0
    edge = (flags[live] & SpotFlag.EDGE) != 0
    order = live[np.lexsort((length[live], edge, outlier))]
    # the first spot of each index in that order keeps it
    _, first = np.unique(index[order], axis=0, return_index=True)
    dup = np.ones(order.size, dtype=bool)
    dup[first] = False
    flags[order[dup]] |= np.uint8(SpotFlag.DUPLICATE)
    return (flags & _NOT_FITTED) == 0, flags


def _missing(index, flags, origin, basis, shift, image_shape, radius, hull_pts):
    """Grid indices inside the index range that should hold a complete spot but hold none."""
    on = (flags & SpotFlag.OFF_LATTICE) == 0
    imax, jmax = index[on].max(axis=0)
    ii, jj = np.meshgrid(np.arange(imax + 1), np.arange(jmax + 1), indexing="ij")
    cand = np.column_stack([ii.ravel(), jj.ravel()])
    pos = _lattice_positions(cand, origin, basis, shift)
    if image_shape is not None:
        expected = ~_edge_mask(pos, radius, image_shape)
    else:
        if hull_pts.shape[0] < 3:
            return np.zeros((0, 2), dtype=np.int64)
        expected = Delaunay(hull_pts).find_simplex(pos, tol=1e-9) >= 0
    taken = np.zeros((imax + 1, jmax + 1), dtype=bool)
    taken[index[on, 0], index[on, 1]] = True
    missing = expected & ~taken.ravel()
    return cand[missing]
