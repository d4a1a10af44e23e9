"""Lenslet spot detection and regular-lattice fitting (calibration step 1).

Two stage functions, in the order the data moves:

:func:`detect_spots`
    One sub-pixel centre per lenslet from a focal-point image (small bright spots), an
    alignment image (very small spots) or a full-aperture white image (one bright disc per
    lenslet). Returns a :class:`SpotSet`.
:func:`fit_lattice`
    Gives every spot a grid index ``(row, col)``, classifies the grid (square or hexagonal) and
    fits a regular lattice by linear least squares. Returns a :class:`Lattice`.

Conventions
-----------
Pixels are ``(row, col)``, 0-based, with the centre of the top-left pixel at (0, 0) (see
:mod:`plenopiv.conventions`); every length here is in pixels (px). The lattice is

``centre(i, j) = origin_px + i * basis[0] + j * basis[1] + (i mod 2) * odd_row_shift_px``

with ``basis[0]`` the step from lattice row ``i`` to row ``i + 1`` and ``basis[1]`` the step
from column ``j`` to ``j + 1``, both as ``(d_row, d_col)`` px. On a square grid the odd-row
shift is zero. On a hexagonal grid the lenslet rows run along the image col axis and odd rows
are shifted by half a pitch towards +col, ``odd_row_shift_px = basis[1] / 2`` for a regular
array; the shift is fitted (two more unknowns), so a slightly irregular array is measured
rather than forced. Row index 0 is the first lattice row and column index 0 the first lattice
column that hold a spot; on a rotated grid the position of index (0, 0) itself may lie outside
the image, and on a hexagonal grid an even row may begin at column 1 (row 0 is always even).
The rotation is the angle of ``basis[1]`` (the lattice +col direction) from the image +col
axis, counter-clockwise positive in ``(x = col, y = row)`` coordinates:
``rotation_rad = atan2(basis[1][0], basis[1][1])``. Because ``y = row`` points down the
screen, a positive rotation looks clockwise on a displayed image.

Examples
--------
>>> import numpy as np
>>> rr, cc = np.mgrid[0:120, 0:120]
>>> image = np.zeros((120, 120))
>>> for r in range(10, 120, 20):
...     for c in range(10, 120, 20):
...         image += np.exp(-((rr - r - 0.3) ** 2 + (cc - c + 0.2) ** 2) / 2.0)
>>> spots = detect_spots(image, expected_pitch_px=20.0)
>>> lattice = fit_lattice(spots)
>>> lattice.grid, np.round(lattice.pitch_px, 2).tolist(), np.round(lattice.origin_px, 1).tolist()
('square', [20.0, 20.0], [10.3, 9.8])
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import Delaunay, cKDTree
from scipy.special import ndtri

from plenopiv.calibration import _spot_kernels as _k
from plenopiv.errors import CalibrationError, ImageError

__all__ = [
    "GRIDS",
    "METHODS",
    "BACKGROUNDS",
    "SpotFlag",
    "SpotSet",
    "Lattice",
    "estimate_pitch",
    "detect_spots",
    "fit_lattice",
    "check_lattice",
    "micro_image_diameter",
]

GRIDS = ("square", "hexagonal")
METHODS = ("auto", "window", "centroid", "gaussian")
RESOLVED_METHODS = ("window", "centroid", "gaussian")
BACKGROUNDS = ("local", "none")

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


class SpotFlag(enum.IntFlag):
    """Why a spot is flagged (a bit mask; several reasons can hold at once).

    EDGE
        Its window (radius ``window_radius_px``) is cut by the image edge: a partial lenslet.
        Its centre is biased towards the image; it is indexed but not used in the lattice fit.
    DIM
        Its intensity is below ``dim_fraction`` of the median of its eight nearest
        neighbours (dust, a scratch, strong vignetting). Indexed, not used in the fit.
    SATURATED
        A pixel of its window is at the maximum of the image's integer dtype.
    FIT_FAILED
        The Gaussian fit did not converge; the centroid is kept.
    OUTLIER
        Its lattice residual is larger than ``outlier_threshold_px``; not used in the fit.
    DUPLICATE
        Another spot with a smaller residual holds the same grid index; not used in the fit.
    OFF_LATTICE
        Its centre lies between lattice positions (fractional index off by more than 0.25);
        its grid index is the nearest one, and it is not used in the fit.
    """

    EDGE = 1
    DIM = 2
    SATURATED = 4
    FIT_FAILED = 8
    OUTLIER = 16
    DUPLICATE = 32
    OFF_LATTICE = 64


# Spots with any of these are left out of the lattice least squares.
_NOT_FITTED = (
    SpotFlag.EDGE
    | SpotFlag.DIM
    | SpotFlag.FIT_FAILED
    | SpotFlag.OUTLIER
    | SpotFlag.DUPLICATE
    | SpotFlag.OFF_LATTICE
)


def _reasons(flag):
    """Comma-separated lower-case names of the bits set in ``flag``."""
    return ", ".join(f.name.lower() for f in SpotFlag if int(flag) & int(f))


def _frozen(a, dtype):
    """Return a read-only C-contiguous copy of ``a``."""
    out = np.array(a, dtype=dtype, copy=True, order="C")
    out.setflags(write=False)
    return out


def _check_choice(name, value, choices):
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, choices))}; got {value!r}")


def _check_fraction(name, value, *, low_open=True, high=1.0):
    v = float(value)
    if not (np.isfinite(v) and (v > 0.0 if low_open else v >= 0.0) and v <= high):
        lo = "0 <" if low_open else "0 <="
        raise ValueError(f"{name} must satisfy {lo} {name} <= {high}; got {value!r}")
    return v


# ----------------------------------------------------------------------------------------------
# Result objects
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SpotSet:
    """Sub-pixel spot centres found in one calibration image.

    Attributes
    ----------
    centres_px : ndarray of float64, shape (N, 2)
        Spot centres ``(row, col)``, px, sorted by row then column.
    intensity : ndarray of float64, shape (N,)
        Background-subtracted intensity above the centroid threshold, summed over the window
        (image units x px).
    area_px : ndarray of float64, shape (N,)
        Effective area, px: ``intensity`` divided by the brightest above-threshold pixel.
        1 for a single hot pixel, about ``4 s^2`` for a Gaussian spot of standard deviation
        ``s`` px at the default threshold, about the disc area for a flat disc.
    flags : ndarray of uint8, shape (N,)
        :class:`SpotFlag` bits (0 for a clean spot).
    image_shape : tuple of int
        ``(n_rows, n_cols)`` of the image, px.
    pitch_px : float
        Lenslet pitch (nearest-neighbour distance) used to size the search, px; estimated
        from the image unless given.
    window_radius_px : float
        Radius of the circular window of each centre, px.
    method : str
        The estimator that gave the centres: ``"window"``, ``"centroid"`` or ``"gaussian"``
        (``"auto"`` is resolved to one of them).
    grid : str or None
        The grid type the caller gave (``"square"``, ``"hexagonal"``), or None.
    rejected_px : ndarray of float64, shape (K, 2)
        Centres of candidates rejected because their light sat in less than ``min_area_px``
        (hot pixels), ``(row, col)`` px.
    spot_radius_px : float
        Radius holding 99 % of a spot's light (background-subtracted, all clean spots
        stacked), px; NaN when not measured. At most half the pitch.
    spot_rms_radius_px : float
        Root-mean-square radius of the stacked spot within half a pitch, px; a uniform disc
        of diameter ``D`` has ``D / (2 sqrt(2))``. NaN when not measured.
    moment_radius_px : float
        Window radius of the ``"window"`` method, px (NaN for the other methods).
    annulus_px : tuple of float
        Inner and outer radius of the background annulus of the ``"window"`` method, px
        (``(nan, nan)`` without one).
    """

    centres_px: np.ndarray
    intensity: np.ndarray
    area_px: np.ndarray
    flags: np.ndarray
    image_shape: tuple
    pitch_px: float
    window_radius_px: float
    method: str = "centroid"
    grid: str | None = None
    rejected_px: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    spot_radius_px: float = float("nan")
    spot_rms_radius_px: float = float("nan")
    moment_radius_px: float = float("nan")
    annulus_px: tuple = (float("nan"), float("nan"))

    def __post_init__(self):
        c = _frozen(self.centres_px, np.float64).reshape(-1, 2)
        n = c.shape[0]
        object.__setattr__(self, "centres_px", c)
        for name, dtype in (
            ("intensity", np.float64),
            ("area_px", np.float64),
            ("flags", np.uint8),
        ):
            a = _frozen(getattr(self, name), dtype).reshape(-1)
            if a.shape[0] != n:
                raise ValueError(
                    f"SpotSet.{name} has {a.shape[0]} entries; expected {n} (one per centre)"
                )
            object.__setattr__(self, name, a)
        object.__setattr__(
            self, "rejected_px", _frozen(self.rejected_px, np.float64).reshape(-1, 2)
        )
        object.__setattr__(self, "image_shape", tuple(int(s) for s in self.image_shape))
        _check_choice("SpotSet.method", self.method, RESOLVED_METHODS)
        for name in ("spot_radius_px", "spot_rms_radius_px", "moment_radius_px"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "annulus_px", tuple(float(v) for v in self.annulus_px))
        if self.grid is not None:
            _check_choice("SpotSet.grid", self.grid, GRIDS)
        if not (self.pitch_px > 0 and self.window_radius_px > 0):
            raise ValueError(
                f"SpotSet.pitch_px and window_radius_px must be > 0; got {self.pitch_px}, "
                f"{self.window_radius_px}"
            )

    def __len__(self):
        return int(self.centres_px.shape[0])

    @property
    def complete(self):
        """Boolean mask (N,): spots whose window lies fully inside the image (no EDGE flag)."""
        return (self.flags & SpotFlag.EDGE) == 0


@dataclass(frozen=True)
class Lattice:
    """A regular lenslet lattice fitted to spot centres.

    ``centre(i, j) = origin_px + i * basis[0] + j * basis[1] + (i mod 2) * odd_row_shift_px``;
    the odd-row shift is zero on a square grid and about half a column step (towards +col) on
    a hexagonal one. See the module docstring for the full convention.

    Attributes
    ----------
    grid : str
        ``"square"`` or ``"hexagonal"``.
    origin_px : ndarray, shape (2,)
        Position ``(row, col)`` of grid index (0, 0), px.
    basis : ndarray, shape (2, 2)
        ``basis[0]``: step to the next lattice row; ``basis[1]``: step to the next lattice
        column; each ``(d_row, d_col)`` px.
    centres_px : ndarray, shape (N, 2)
        The measured spot centres the lattice was fitted to, ``(row, col)`` px.
    grid_index : ndarray of int64, shape (N, 2)
        Lattice ``(row, col)`` index of each spot.
    residual_px : ndarray, shape (N, 2)
        Measured minus fitted centre, ``(row, col)`` px, for every spot.
    inlier : ndarray of bool, shape (N,)
        Spots used in the least-squares fit.
    flags : ndarray of uint8, shape (N,)
        :class:`SpotFlag` bits, the detector's and the fit's together.
    rms_residual_px : float
        ``sqrt(mean(|residual|^2))`` over the inliers, px (the 2-D residual length).
    missing_index : ndarray of int64, shape (K, 2)
        Grid indices inside the index range whose complete spot window would lie inside the
        image (or, without an image shape, inside the convex hull of the spots) but that hold
        no spot.
    basis_std_px : ndarray, shape (2, 2)
        Standard error of each component of ``basis`` from the least squares, px.
    origin_std_px : ndarray, shape (2,)
        Standard error of ``origin_px``, px.
    odd_row_shift_px : ndarray, shape (2,)
        Extra displacement ``(d_row, d_col)`` px of the odd lattice rows: zero on a square grid,
        fitted on a hexagonal one (``basis[1] / 2`` for a regular hexagonal array).
    image_shape : tuple of int or None
        ``(n_rows, n_cols)`` of the image, when known.
    phase_bias_px : ndarray, shape (N, 2)
        The fitted periodic bias of each measured centre against its sub-pixel phase
        (``fit_lattice(phase_harmonics=...)``), ``(row, col)`` px; zero when not fitted.
        ``residual_px`` is measured minus fitted minus this bias;
        :attr:`corrected_centres_px` removes it from the measured centres.
    """

    grid: str
    origin_px: np.ndarray
    basis: np.ndarray
    centres_px: np.ndarray
    grid_index: np.ndarray
    residual_px: np.ndarray
    inlier: np.ndarray
    flags: np.ndarray
    rms_residual_px: float
    missing_index: np.ndarray
    basis_std_px: np.ndarray
    origin_std_px: np.ndarray
    odd_row_shift_px: np.ndarray = field(default_factory=lambda: np.zeros(2))
    image_shape: tuple | None = None
    phase_bias_px: np.ndarray | None = None

    def __post_init__(self):
        _check_choice("Lattice.grid", self.grid, GRIDS)
        for name, dtype, shape in (
            ("origin_px", np.float64, (2,)),
            ("basis", np.float64, (2, 2)),
            ("odd_row_shift_px", np.float64, (2,)),
            ("basis_std_px", np.float64, (2, 2)),
            ("origin_std_px", np.float64, (2,)),
        ):
            a = _frozen(getattr(self, name), dtype)
            if a.shape != shape:
                raise ValueError(f"Lattice.{name} has shape {a.shape}; expected {shape}")
            object.__setattr__(self, name, a)
        c = _frozen(self.centres_px, np.float64).reshape(-1, 2)
        n = c.shape[0]
        object.__setattr__(self, "centres_px", c)
        for name, dtype in (("grid_index", np.int64), ("residual_px", np.float64)):
            a = _frozen(getattr(self, name), dtype).reshape(-1, 2)
            if a.shape[0] != n:
                raise ValueError(f"Lattice.{name} has {a.shape[0]} rows; expected {n}")
            object.__setattr__(self, name, a)
        for name, dtype in (("inlier", bool), ("flags", np.uint8)):
            a = _frozen(getattr(self, name), dtype).reshape(-1)
            if a.shape[0] != n:
                raise ValueError(f"Lattice.{name} has {a.shape[0]} entries; expected {n}")
            object.__setattr__(self, name, a)
        bias = np.zeros((n, 2)) if self.phase_bias_px is None else self.phase_bias_px
        bias = _frozen(bias, np.float64).reshape(-1, 2)
        if bias.shape[0] != n:
            raise ValueError(f"Lattice.phase_bias_px has {bias.shape[0]} rows; expected {n}")
        object.__setattr__(self, "phase_bias_px", bias)
        object.__setattr__(
            self, "missing_index", _frozen(self.missing_index, np.int64).reshape(-1, 2)
        )
        object.__setattr__(self, "rms_residual_px", float(self.rms_residual_px))
        if self.image_shape is not None:
            object.__setattr__(self, "image_shape", tuple(int(s) for s in self.image_shape))

    # derived values -----------------------------------------------------------------------
    @property
    def corrected_centres_px(self):
        """Measured centres less their fitted phase bias, ``(row, col)`` px, shape (N, 2)."""
        return self.centres_px - self.phase_bias_px

    @property
    def pitch_px(self):
        """Spacing between adjacent lattice rows and adjacent columns, ``(rows, cols)`` px.

        On a hexagonal grid ``pitch_px[1]`` is the lenslet pitch and ``pitch_px[0]`` the row
        spacing, about ``sqrt(3) / 2`` of it.
        """
        return np.hypot(self.basis[:, 0], self.basis[:, 1])

    @property
    def rotation_rad(self):
        """Angle of the lattice +col axis from the image +col axis, rad (CCW in x=col, y=row)."""
        return float(math.atan2(self.basis[1, 0], self.basis[1, 1]))

    @property
    def rotation_std_rad(self):
        """Standard error of :attr:`rotation_rad` from the least squares, rad."""
        (er, ec), (sr, sc) = self.basis[1], self.basis_std_px[1]
        return float(math.sqrt(ec * ec * sr * sr + er * er * sc * sc) / (er * er + ec * ec))

    @property
    def pitch_std_px(self):
        """Standard error of :attr:`pitch_px`, ``(rows, cols)`` px."""
        b, s = self.basis, self.basis_std_px
        return np.sqrt((b[:, 0] * s[:, 0]) ** 2 + (b[:, 1] * s[:, 1]) ** 2) / self.pitch_px

    @property
    def shear_rad(self):
        """Departure of the row step from perpendicular to the col axis, rad (0 when orthogonal)."""
        r, c = self.basis
        return float(math.asin(np.clip((r @ c) / (np.hypot(*r) * np.hypot(*c)), -1.0, 1.0)))

    @property
    def shape(self):
        """Extent of the grid index, ``(n_rows, n_cols)`` lenslets (max index + 1)."""
        if self.grid_index.shape[0] == 0:
            return (0, 0)
        return tuple(int(v) + 1 for v in self.grid_index.max(axis=0))

    @property
    def n_missing(self):
        """Number of lattice positions inside the image that hold no spot."""
        return int(self.missing_index.shape[0])

    @property
    def missing_fraction(self):
        """``n_missing`` over the number of expected lattice positions (found + missing)."""
        found = int(np.count_nonzero((self.flags & SpotFlag.EDGE) == 0))
        total = found + self.n_missing
        return self.n_missing / total if total else 0.0

    @property
    def quality(self):
        """How well the spots fit a regular lattice, as a JSON-ready dict.

        Keys: ``grid``; ``pitch_px`` (rows, cols); ``rotation_rad``; ``shear_deg`` (the row
        step's departure from perpendicular); ``rms_residual_px`` and ``rms_residual_pitch``
        (the same over the mean pitch); ``n_spots``, ``n_fitted`` (inliers), ``n_edge``,
        ``n_off_lattice``, ``n_outliers``; ``n_missing`` and ``missing_fraction``;
        ``phase_bias_px``, the largest fitted sub-pixel phase bias (0 when none was fitted).
        :func:`check_lattice` refuses a lattice by these figures.
        """
        f = self.flags
        pitch = self.pitch_px
        return {
            "grid": self.grid,
            "pitch_px": [float(v) for v in pitch],
            "rotation_rad": self.rotation_rad,
            "shear_deg": math.degrees(self.shear_rad),
            "rms_residual_px": self.rms_residual_px,
            "rms_residual_pitch": self.rms_residual_px / float(np.mean(pitch)),
            "n_spots": len(self.centres_px),
            "n_fitted": int(np.count_nonzero(self.inlier)),
            "n_edge": int(np.count_nonzero(f & SpotFlag.EDGE)),
            "n_off_lattice": int(np.count_nonzero(f & SpotFlag.OFF_LATTICE)),
            "n_outliers": int(np.count_nonzero(f & SpotFlag.OUTLIER)),
            "n_missing": self.n_missing,
            "missing_fraction": self.missing_fraction,
            "phase_bias_px": float(np.abs(self.phase_bias_px).max()) if len(f) else 0.0,
        }

    @property
    def flagged(self):
        """Every flagged spot: a tuple of ``(spot number, (row index, col index), reasons)``."""
        return tuple(
            (
                int(k),
                (int(self.grid_index[k, 0]), int(self.grid_index[k, 1])),
                _reasons(self.flags[k]),
            )
            for k in np.flatnonzero(self.flags)
        )

    def predict(self, index):
        """Fitted centre of lattice index ``(row, col)``.

        Parameters
        ----------
        index : array_like of int, shape (N, 2) or (2,)
            Grid indices ``(i, j)``.

        Returns
        -------
        ndarray, shape (N, 2)
            Centres ``(row, col)``, px.
        """
        idx = np.asarray(index)
        if idx.ndim == 0 or idx.shape[-1] != 2 or not np.issubdtype(idx.dtype, np.integer):
            raise ValueError(
                f"index must be an integer array of shape (N, 2); got {idx.dtype} {idx.shape}"
            )
        idx = idx.reshape(-1, 2).astype(np.int64)
        return _lattice_positions(idx, self.origin_px, self.basis, self.odd_row_shift_px)


def _lattice_positions(index, origin, basis, shift):
    """``origin + i basis[0] + j basis[1] + (i mod 2) shift`` for integer indices ``(i, j)``."""
    i = index[:, 0].astype(np.float64)[:, None]
    j = index[:, 1].astype(np.float64)[:, None]
    odd = (index[:, 0] % 2).astype(np.float64)[:, None]
    return origin[None, :] + i * basis[0][None, :] + j * basis[1][None, :] + odd * shift[None, :]


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


def detect_spots(
    image,
    *,
    expected_pitch_px=None,
    grid=None,
    threshold=0.1,
    detection_threshold=0.15,
    method="auto",
    window_radius_px=None,
    moment_radius_px=None,
    background="local",
    min_area_px=1.5,
    dim_fraction=0.5,
    max_saturated_fraction=0.02,
):
    """Find one sub-pixel spot centre per lenslet in a calibration image.

    Parameters
    ----------
    image : array_like, shape (R, C)
        Focal-point, alignment or white image, integer or floating point, ``image[row, col]``.
    expected_pitch_px : float, optional
        Lenslet pitch (nearest-neighbour distance) in px. Estimated from the image's
        autocorrelation (:func:`estimate_pitch`) when not given.
    grid : {"square", "hexagonal"} or None
        Grid type if known. Recorded in the result for :func:`fit_lattice`; detection itself
        does not depend on it.
    threshold : float, 0 <= threshold < 1
        Centroid threshold: inside each window, pixels count with weight
        ``max(I - threshold * P, 0)`` where ``P`` is the spot's peak height above background.
    detection_threshold : float, 0 < detection_threshold < 1
        A local maximum of the smoothed image is a candidate spot when its height is at least
        this fraction of the bright spots around it (the 90th percentile of the local maxima
        within about 4 x 4 to 12 x 12 pitches), so that the dim lenslets of a vignetted
        corner are found; it must also stand 8 standard deviations of the smoothed image's
        noise above the gaps between spots, and at least a tenth of this fraction of the
        typical spot of the whole image (the 95th percentile).
    method : {"auto", "window", "centroid", "gaussian"}
        Sub-pixel estimator. ``"window"``: the first moment in a soft-edged circular window
        sized from the measured spot (1.75 times the radius holding 99 % of its light) above
        a plane fitted to an annulus around it, with no threshold (unbiased at any sub-pixel
        phase; see Notes). ``"centroid"``: the iterative thresholded centroid.
        ``"gaussian"``: a least-squares circular 2-D Gaussian plus offset, started from the
        centroid. ``"auto"`` (default): ``"window"`` when the spots are small enough for the
        window and its annulus to fit between neighbours (``2 r99 + 4 <= pitch`` and
        ``r99 <= 0.35 pitch``, r99 the radius holding 99 % of a spot's light: focal-point and
        alignment images), else ``"centroid"`` (white images, micro-images that fill the
        pitch).
    window_radius_px : float, optional
        Radius of the circular window of the first, thresholded centroid, which also decides
        whether a spot is cut by the image edge (``EDGE``), px; default half the pitch.
    moment_radius_px : float, optional
        ``"window"`` method only: radius of its window, px; default measured (above).
    background : {"local", "none"}
        ``"local"``: subtract a smooth background (box minimum over 1.25 pitch, then box
        mean, then the expected noise bias of that minimum); candidate heights are measured
        from the median level of the gaps between spots. ``"none"``: use the image as is.
    min_area_px : float
        Candidates whose light sits in less than this effective area (px) are rejected as hot
        pixels (a single bright pixel has area 1).
    dim_fraction : float, 0 < dim_fraction <= 1
        A spot fainter than this fraction of the median of its eight nearest neighbours is
        flagged ``DIM``.
    max_saturated_fraction : float, 0 <= max_saturated_fraction <= 1
        Largest allowed fraction of pixels at the integer dtype's maximum.

    Returns
    -------
    SpotSet
        Centres ``(row, col)`` px with intensity, effective area and flags.

    Raises
    ------
    ImageError
        The image is not 2-D, not real, holds NaN/inf, is all dark, constant, saturated, or has
        no periodic spot pattern.
    ValueError
        An option is outside its valid set.

    Notes
    -----
    Steps: validate; estimate the pitch if needed; subtract the background; smooth with a
    Gaussian of standard deviation ``pitch / 6`` and take local maxima at least half a pitch
    apart as candidates, each at least ``detection_threshold`` of the spots around it (so the
    dim lenslets of a vignetted corner are found) and clearly above the noise; refine each
    candidate with the iterative thresholded centroid (the
    window is re-centred on the estimate until it moves by less than 1e-4 px, so a
    point-symmetric spot carries no window bias); reject candidates smaller than
    ``min_area_px`` (hot pixels) and merge candidates closer than a quarter pitch; measure
    the spot size from all clean spots stacked; refine with the window centroid or the
    Gaussian fit; flag partial (``EDGE``), dim and saturated spots.

    Why the window centroid for small spots. Subtracting a threshold from every pixel and
    dropping the pixels below it makes the centroid of a pixel-sampled spot depend on where
    the spot sits on the pixel grid: for 1-5 px spots this bias reaches 0.01-0.02 px, and as
    a focal-point image's spots step through every sub-pixel phase across the array (a
    non-integer pitch) it becomes a spurious spot-lattice scale, which the focal-point
    method reads as an S_i error of up to a millimetre at 405 mm (docs/validation/
    calibration_study.md). The first moment of all the spot's light has no such bias when
    the pixel response reproduces linear functions (a bilinear splat, or any optics blur of
    about half a pixel or more on a pixel-integrating sensor): measured on 1-5 px discs with
    0-1 px Gaussian blur at ten sub-pixel phases, it stays within 0.0004 px where the
    thresholded centroid is off by 0.005-0.026 px and a Gaussian fit by up to 0.04 px, and
    under photon noise it is the most precise of the three (within 2-7 % of the Cramer-Rao
    bound; ``benchmarks/bench_spots.py`` prints the table). Sharper spots on a
    pixel-integrating sensor alias (0.005-0.05 px for every estimator); ``fit_lattice``
    removes most of that with its phase terms. Its window is soft-edged (a pixel
    counts by about the fraction of it inside the circle), so the window's own moment follows
    the estimate smoothly, and a plane fitted to the annulus just outside it removes any
    background level and slope, which would otherwise pull the estimate.

    Measured on the PlenoptiCam reference images with exact centres (``b``, ``c``, ``d``:
    720 x 720 px, pitches 66.7, 13.1 and 7.7 px, about 10 % multiplicative pixel noise), rms
    error per axis (row, col) of the spots at least one pitch inside the border:

    ========  ================  ================  ================  ======================
    method    b (hexagonal)     c (hexagonal)     d (square)        white image, lattice
                                                                    rms residual
    ========  ================  ================  ================  ======================
    centroid  0.040, 0.041 px   0.067, 0.058 px   0.049, 0.048 px   0.085 px
    gaussian  0.047, 0.048 px   0.068, 0.064 px   0.074, 0.074 px   0.265 px
    ========  ================  ================  ================  ======================

    (These micro-images fill their pitch: ``"auto"`` takes the centroid on all four.)
    Both keep the mean bias below 0.01 px. The centroid is as good or better on all of these,
    makes no assumption about the spot profile (a white-image disc is not a Gaussian, hence
    the Gaussian's large residual there) and is about twice as fast, so it is the default.
    On truly Gaussian spots in additive noise (the synthetic tests) the Gaussian fit is about
    15 % more precise; choose it for such focal-point images.
    The per-spot error is set by the pixel noise: a least-squares fit of the exact mean spot
    profile (an oracle no detector has) reaches 0.035, 0.06 and 0.10 px rms on ``b``, ``c``,
    ``d``. The lattice fit (:func:`fit_lattice`) averages thousands of spots; its predicted
    centres are within 0.01 px rms of the truth on all three.
    """
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

    raw, sat_level = _validate_image(image, max_saturated_fraction)
    work = raw.astype(np.float32)
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

    if background == "local":
        work = work - _local_background(work, pitch)

    # candidates: local maxima of the smoothed image, at least half a pitch apart
    smooth = ndi.gaussian_filter(work, max(pitch / 6.0, 0.7), mode="constant")
    size = 2 * int(pitch // 2) + 1
    is_max = smooth == ndi.maximum_filter(smooth, size=size, mode="nearest")
    cand = np.argwhere(is_max)
    height = smooth[is_max]
    del is_max
    noise = 0.0
    if background == "local":
        # The box minimum sits a few noise standard deviations below the true background.
        # Candidate heights are measured from the typical level of the smoothed image's local
        # minima (the gaps between spots), so noise bumps on that pedestal do not pass as
        # spots. Of the pedestal, the expected noise bias of the minimum (the expected
        # minimum of n_box normal samples, Blom's approximation, times the pixel noise seen in
        # the gaps) is removed from the image; the rest may be light (overlapping spots).
        is_min = smooth == ndi.minimum_filter(smooth, size=size, mode="nearest")
        gap_level = float(np.median(smooth[is_min]))
        height = height - gap_level
        resid = work[is_min] - smooth[is_min]
        noise = 1.4826 * float(np.median(np.abs(resid - np.median(resid))))
        n_box = (int(math.ceil(1.25 * pitch)) | 1) ** 2
        bias = -noise * float(ndtri((1.0 - 0.375) / (n_box + 0.25)))
        work -= np.float32(min(max(gap_level, 0.0), bias))
        del is_min
    del smooth
    positive = height > 0
    if not np.any(positive):
        raise ImageError(
            "no spot found: the background-subtracted image has no local maximum above its "
            "background"
        )
    cand, height = cand[positive], height[positive]
    # A candidate is a spot when it reaches detection_threshold of the bright spots around it
    # (the local reference, so that the dim lenslets of a vignetted corner are found), stands
    # clearly out of the noise of the smoothed image, and is not negligible against the
    # image's typical spot (1/10 of detection_threshold of it).
    sigma_smooth = noise / (2.0 * math.sqrt(math.pi) * max(pitch / 6.0, 0.7))
    ref = _local_reference(cand, height, work.shape, pitch)
    strong = (
        (height >= detection_threshold * ref)
        & (height >= _NOISE_FLOOR * sigma_smooth)
        & (height >= 0.1 * detection_threshold * np.percentile(height, 95))
    )
    cand = cand[strong].astype(np.float64)

    centres, intensity, area, _peak = _k.centroid_refine_numba(
        work, np.ascontiguousarray(cand), radius, threshold, _CENTROID_MAX_ITER, _CENTROID_TOL_PX
    )
    ok = np.all(np.isfinite(centres), axis=1)
    centres, intensity, area = centres[ok], intensity[ok], area[ok]
    hot = area < min_area_px
    rejected = centres[hot]
    centres, intensity, area = centres[~hot], intensity[~hot], area[~hot]

    # two candidates may converge on one spot (a flat-topped disc): keep the brighter
    if centres.shape[0] > 1:
        order = np.argsort(-intensity, kind="stable")
        centres, intensity, area = centres[order], intensity[order], area[order]
        pairs = cKDTree(centres).query_pairs(0.25 * pitch, output_type="ndarray")
        drop = np.zeros(centres.shape[0], dtype=bool)
        for a_, b_ in pairs[np.argsort(pairs[:, 0], kind="stable")]:
            if not drop[a_]:
                drop[b_] = True
        centres, intensity, area = centres[~drop], intensity[~drop], area[~drop]

    flags = np.zeros(centres.shape[0], dtype=np.uint8)
    n_rows, n_cols = work.shape
    interior = ~_edge_mask(centres, radius, (n_rows, n_cols))
    spot_r, spot_rms = _spot_size(work, centres[interior], pitch)
    if method == "auto":
        method = "window" if _window_fits(spot_r, pitch) else "centroid"
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
    if method == "gaussian" and centres.shape[0]:
        sigma0 = np.clip(np.sqrt(area / 4.0), 0.5, radius / 2.0)
        params = _k.gaussian_fit_numba(
            work, np.ascontiguousarray(centres), sigma0, radius, _GAUSS_MAX_ITER
        )
        good = np.all(np.isfinite(params), axis=1)
        centres[good] = params[good, 1:3]
        flags[~good] |= np.uint8(SpotFlag.FIT_FAILED)

    order = np.lexsort((centres[:, 1], centres[:, 0]))
    centres, intensity, area, flags = centres[order], intensity[order], area[order], flags[order]
    flags[_edge_mask(centres, radius, (n_rows, n_cols))] |= np.uint8(SpotFlag.EDGE)
    if sat_level is not None and centres.shape[0]:
        sat_px = np.argwhere(raw == sat_level)
        near = cKDTree(sat_px).query_ball_point(centres, radius, return_length=True)
        flags[np.asarray(near) > 0] |= np.uint8(SpotFlag.SATURATED)
    flags[_dim_mask(centres, intensity, flags, dim_fraction)] |= np.uint8(SpotFlag.DIM)

    return SpotSet(
        centres_px=centres,
        intensity=intensity,
        area_px=area,
        flags=flags,
        image_shape=(n_rows, n_cols),
        pitch_px=pitch,
        window_radius_px=radius,
        method=method,
        grid=grid,
        rejected_px=rejected,
        spot_radius_px=spot_r,
        spot_rms_radius_px=spot_rms,
        moment_radius_px=moment_r,
        annulus_px=annulus,
    )


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


def _edge_mask(centres, radius, shape):
    """Spots whose circular window of ``radius`` px leaves the image area."""
    n_rows, n_cols = shape
    return (
        (centres[:, 0] - radius < -0.5)
        | (centres[:, 0] + radius > n_rows - 0.5)
        | (centres[:, 1] - radius < -0.5)
        | (centres[:, 1] + radius > n_cols - 0.5)
    )


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


# ----------------------------------------------------------------------------------------------
# Lattice fitting
# ----------------------------------------------------------------------------------------------

# Candidate spots: the local reference is taken over cells of this many pitches, and a spot
# must stand this many standard deviations of the smoothed image's noise above the gaps
_REFERENCE_CELL = 4.0
_NOISE_FLOOR = 8.0
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


def fit_lattice(
    spots,
    *,
    grid="auto",
    expected_pitch_px=None,
    image_shape=None,
    window_radius_px=None,
    max_missing_fraction=None,
    outlier_threshold_px=None,
    min_size=4,
    phase_harmonics=0,
    max_shape_error=0.05,
):
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
        Not needed (the median nearest-neighbour distance is used); when given, a measured
        spacing more than 20 % away raises :class:`CalibrationError`.
    image_shape : tuple of int, optional
        ``(n_rows, n_cols)`` px; taken from the SpotSet when not given. With it, a spot is
        partial (``EDGE``) when the window of radius ``window_radius_px`` around its measured
        or its *fitted* centre leaves the image (a cut spot's measured centre is pulled
        inwards and can look complete), and missing positions are counted inside the image;
        without it, inside the convex hull of the spots.
    window_radius_px : float, optional
        Window radius that decides whether a spot is complete, px; default the SpotSet's, or
        half the spacing.
    max_missing_fraction : float, optional
        Largest accepted fraction of missing lattice positions; None (default) accepts any
        and reports them in ``missing_index``.
    outlier_threshold_px : float, optional
        Residual length above which a spot is an outlier, px. Default: 6 times the robust
        (median-absolute-deviation) residual scale per axis, at least 2 % of the pitch.
    min_size : int
        Smallest accepted lattice, ``min_size x min_size`` lenslets.
    phase_harmonics : int
        Fit, together with the lattice, a periodic bias of each measured coordinate against
        its own sub-pixel phase: ``sum_n a_n sin(2 pi n x) + b_n cos(2 pi n x)``, ``n = 1 ..
        phase_harmonics``, per axis (0, the default: none). This is the pixel-locking of any
        centre estimator on spots too sharp for the pixel grid (a pixel-integrating sensor
        with little optical blur); since the pitch is not a whole number of pixels the spots
        sample every phase, so the bias is measured and removed from the lattice
        (``phase_bias_px``). An axis whose spots bunch at a few phases (resultant length of
        any harmonic above 0.8) gets no correction (its bias is then a constant offset), nor
        one whose fitted terms do not stand out of their own noise by 10 standard errors
        (chi-square 100: irregularly placed lenslets, noise), which they would only add to.
    max_shape_error : float or None
        The fitted lattice must have the shape of its grid type: a square grid's row step
        perpendicular to its column step and as long, a hexagonal grid's row step
        perpendicular, ``sqrt(3) / 2`` of the pitch long, and its odd rows shifted by half a
        pitch. A departure larger than this fraction (default 5 %; an angle counts in
        radians) raises :class:`CalibrationError`: a grid type forced on the other kind of
        array. None skips the check.

    Returns
    -------
    Lattice

    Raises
    ------
    CalibrationError
        Too few spots, no square or hexagonal order, a spacing far from
        ``expected_pitch_px``, or more missing positions than ``max_missing_fraction``.
    ValueError
        An option is outside its valid set.

    Notes
    -----
    1. Neighbours are the spots closer than 1.25 times the median nearest-neighbour
       distance. The 4- and 6-fold orders ``|mean(exp(4 i phi))|``,
       ``|mean(exp(6 i phi))|`` of their directions ``phi`` decide the grid, and the phase of
       the larger one gives the lattice axis nearest the image +col axis. The medians of the
       neighbour vectors along that axis and the next one (at 90 or 60 degrees) are the
       primitive vectors.
    2. Axial indices are assigned from the most central spot outwards: within a radius that
       grows by 1.6 each pass, every spot's fractional index is rounded, spots within 0.25 of
       an integer are kept, and the affine lattice is refitted. Holes and dim spots do not
       break it, because each pass predicts from the fitted lattice, not from neighbours.
    3. The axial indices become ``(row, col)`` indices (odd rows half a step towards +col on
       a hexagonal grid), and ``origin_px``, ``basis`` (and on a hexagonal grid the odd-row
       shift) are fitted by linear least squares on the clean spots,
       ``centre = origin + i basis[0] + j basis[1] + (i mod 2) shift``: the model is linear in
       its six (eight) unknowns, so the fit is exact. Outliers and duplicate indices are
       flagged and the fit is repeated, twice. Standard errors come from the residual
       variance and the normal matrix.
    """
    _check_choice("grid", grid, ("auto",) + GRIDS)
    min_size = int(min_size)
    if min_size < 2:
        raise ValueError(f"min_size must be an integer >= 2; got {min_size!r}")
    if max_missing_fraction is not None:
        max_missing_fraction = _check_fraction(
            "max_missing_fraction", max_missing_fraction, low_open=False
        )

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
    n = pts.shape[0]
    need = min_size * min_size
    if n < need:
        raise CalibrationError(
            f"found {n} spots, expected a lattice of at least {min_size} x {min_size} "
            f"({need} spots)"
        )

    if image_shape is not None:
        image_shape = tuple(int(s) for s in image_shape)
        if window_radius_px is None:
            clean = pts[(flags & _NOT_FITTED) == 0]
            if clean.shape[0] >= 2:
                window_radius_px = 0.5 * float(np.median(cKDTree(clean).query(clean, k=2)[0][:, 1]))
        if window_radius_px is not None:
            flags[_edge_mask(pts, float(window_radius_px), image_shape)] |= np.uint8(SpotFlag.EDGE)
    usable = (flags & _NOT_FITTED) == 0
    if np.count_nonzero(usable) < need:
        raise CalibrationError(
            f"found {np.count_nonzero(usable)} complete, clean spots among {n}; expected a "
            f"lattice of at least {min_size} x {min_size} ({need} spots)"
        )
    vec, d0, n_neighbours = _neighbour_vectors(pts[usable])
    if expected_pitch_px is not None and abs(d0 / float(expected_pitch_px) - 1.0) > 0.2:
        raise CalibrationError(
            f"median spot spacing is {d0:.2f} px; expected about {float(expected_pitch_px):.2f} px "
            "(expected_pitch_px)"
        )
    window_radius_px = 0.5 * d0 if window_radius_px is None else float(window_radius_px)

    grid, theta = _classify(vec, grid)
    a1, a2 = _initial_basis(vec, grid, theta)
    full = n_neighbours == (6 if grid == "hexagonal" else 4)
    o_ax, p_ax = _grow_indices(pts[usable], a1, a2, d0, full)

    # axial indices of every spot from the grown lattice
    q = _fractional_index(pts, o_ax, p_ax)
    mn = np.rint(q).astype(np.int64)
    frac = np.max(np.abs(q - mn), axis=1)
    flags[(frac >= _INDEX_TOL) & ((flags & SpotFlag.EDGE) == 0)] |= np.uint8(SpotFlag.OFF_LATTICE)
    index = _grid_index(mn, grid, flags)
    coef, res, _, _ = _offset_fit(index, pts, grid, (flags & _NOT_FITTED) == 0)
    if image_shape is not None:
        # a lenslet is also partial when the window around its fitted position leaves the
        # image: a cut spot's measured centre is pulled inwards and can look complete
        pred = _lattice_positions(index, coef[0], coef[1:3], _shift(coef, grid))
        flags[_edge_mask(pred, window_radius_px, image_shape)] |= np.uint8(SpotFlag.EDGE)
    index, flags = _place_edge_spots(index, pts, flags, coef, grid, d0)
    index = _normalise_index(index, grid, flags)

    # least squares with outlier rejection; duplicates resolved by residual
    phase_harmonics = int(phase_harmonics)
    if phase_harmonics < 0:
        raise ValueError(f"phase_harmonics must be an integer >= 0; got {phase_harmonics!r}")
    fitted = (flags & _NOT_FITTED) == 0
    coef, res, cov_scale, bias = _offset_fit(index, pts, grid, fitted, phase_harmonics)
    for _ in range(2):
        fitted, flags = _reject(index, res, flags, fitted, d0, outlier_threshold_px)
        if np.count_nonzero(fitted) < need:
            raise CalibrationError(
                f"only {np.count_nonzero(fitted)} of {n} spots fit a regular lattice; expected "
                f"at least {need} ({min_size} x {min_size})"
            )
        coef, res, cov_scale, bias = _offset_fit(index, pts, grid, fitted, phase_harmonics)
    origin, basis, shift = coef[0], np.stack([coef[1], coef[2]]), _shift(coef, grid)
    if max_shape_error is not None:
        _check_shape(grid, basis, shift, float(max_shape_error))
    is_edge = (flags & SpotFlag.EDGE) != 0

    extent = index[fitted].max(axis=0) - index[fitted].min(axis=0) + 1
    if min(extent) < min_size:
        raise CalibrationError(
            f"the indexed spots span a lattice of {extent[0]} x {extent[1]} lenslets; expected at "
            f"least {min_size} x {min_size}"
        )

    missing = _missing(
        index, flags, origin, basis, shift, image_shape, window_radius_px, pts[fitted]
    )
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

    n_par = coef.shape[0] + np.array([2 * phase_harmonics * bool(np.any(bias[:, a]))
                                      for a in (0, 1)])
    dof = np.maximum(int(np.count_nonzero(fitted)) - n_par, 1)
    s2 = np.sum(res[fitted] ** 2, axis=0) / dof  # per axis (row, col), px^2
    # rows: origin, e_row, e_col[, shift]; columns: axis (row, col)
    std = np.sqrt(np.column_stack([np.diag(cov_scale[a]) * s2[a] for a in (0, 1)]))
    rms = float(np.sqrt(np.mean(np.sum(res[fitted] ** 2, axis=1))))
    return Lattice(
        grid=grid,
        origin_px=origin,
        basis=basis,
        centres_px=pts,
        grid_index=index,
        residual_px=res,
        inlier=fitted,
        flags=flags,
        rms_residual_px=rms,
        missing_index=missing,
        basis_std_px=np.stack([std[1], std[2]]),
        origin_std_px=std[0],
        odd_row_shift_px=shift,
        image_shape=image_shape,
        phase_bias_px=bias,
    )


def _check_shape(grid, basis, shift, tol):
    """Raise CalibrationError when the fitted lattice does not have its grid type's shape."""
    e_row, e_col = basis
    p_col = float(np.hypot(*e_col))
    p_row = float(np.hypot(*e_row))
    shear = abs(math.asin(np.clip((e_row @ e_col) / (p_row * p_col), -1.0, 1.0)))
    other = "hexagonal" if grid == "square" else "square"
    ratio_expected = 1.0 if grid == "square" else math.sqrt(3.0) / 2.0
    checks = [
        ("the angle between its row and column steps departs from 90 degrees by "
         f"{math.degrees(shear):.1f} degrees", shear, f"{math.degrees(tol):.1f} degrees"),
        (f"its row spacing is {p_row / p_col:.3f} of its pitch, expected {ratio_expected:.3f}",
         abs(p_row / (ratio_expected * p_col) - 1.0), f"{100 * tol:g} %"),
    ]
    if grid == "hexagonal":
        dev = float(np.hypot(*(shift - 0.5 * e_col))) / p_col
        checks.append(
            (f"its odd rows are shifted by ({shift[0]:.2f}, {shift[1]:.2f}) px, expected half "
             f"a pitch along its rows ({0.5 * e_col[0]:.2f}, {0.5 * e_col[1]:.2f}) px", dev,
             f"{100 * tol:g} % of the pitch")
        )
    for text, value, limit in checks:
        if value > tol:
            raise CalibrationError(
                f"the spots do not form a {grid} lattice: {text} (at most {limit}, "
                f"max_shape_error = {tol:g}); is the grid type wrong (a {other} array)?"
            )


def micro_image_diameter(image, centres_px, pitch_px):
    """Mean diameter (px) of the bright micro-images of a white (full-aperture) image.

    Each is ``2 sqrt(A / pi)``, ``A`` the number of pixels within half a pitch of its centre
    that are brighter than half its plateau (the median within 0.15 pitch of the centre,
    at least 1.5 px); only micro-images wholly inside the image count.

    Parameters
    ----------
    image : array_like, shape (R, C)
        Background-subtracted white image.
    centres_px : array_like, shape (N, 2)
        Micro-image centres ``(row, col)``, px.
    pitch_px : float
        Micro-image pitch, px.

    Raises
    ------
    CalibrationError
        No micro-image lies wholly inside the image.
    """
    w = np.asarray(image, float)
    h = int(math.ceil(pitch_px / 2)) + 1
    rr, cc = np.mgrid[-h : h + 1, -h : h + 1]
    core = max(0.15 * pitch_px, 1.5)
    out = []
    for r, c in np.asarray(centres_px, float):
        r0, c0 = int(round(r)), int(round(c))
        if r0 - h < 0 or c0 - h < 0 or r0 + h >= w.shape[0] or c0 + h >= w.shape[1]:
            continue
        patch = w[r0 - h : r0 + h + 1, c0 - h : c0 + h + 1]
        d = np.hypot(rr + r0 - r, cc + c0 - c)
        plateau = np.median(patch[d < core])
        area = np.count_nonzero((patch > 0.5 * plateau) & (d < pitch_px / 2))
        out.append(2.0 * math.sqrt(area / math.pi))
    if not out:
        raise CalibrationError("no complete micro-image to measure its diameter")
    return float(np.mean(out))


MAX_RMS_RESIDUAL_PITCH = 0.015
MAX_MISSING_FRACTION = 0.05


def check_lattice(lattice, *, what="the image", max_rms_residual_pitch=MAX_RMS_RESIDUAL_PITCH,
                  max_missing_fraction=MAX_MISSING_FRACTION):
    """Refuse a lattice that says its image is not a calibration image of this camera.

    Parameters
    ----------
    lattice : Lattice
    what : str
        How the error names the image (e.g. ``"the focal-point image"``).
    max_rms_residual_pitch : float or None
        Largest rms lattice residual as a fraction of the pitch (default 1.5 %: 0.25 px at a
        17 px pitch; focal-point and white images reach 0.001-0.01 of the pitch, a scene or
        ruler image 0.02 and more). None skips the check.
    max_missing_fraction : float or None
        Largest fraction of the lattice positions inside the image that hold no spot
        (default 5 %). None skips the check.

    Returns
    -------
    dict
        ``lattice.quality``.

    Raises
    ------
    CalibrationError
        Naming the figure, its value and the threshold.
    """
    q = lattice.quality
    hint = ("is it a focal-point, alignment or white image of this camera, not a scene or a "
            "ruler?")
    if max_rms_residual_pitch is not None and q["rms_residual_pitch"] > max_rms_residual_pitch:
        raise CalibrationError(
            f"{what}: the spots fit a regular {q['grid']} lattice only to "
            f"{q['rms_residual_px']:.3f} px rms, {100 * q['rms_residual_pitch']:.2f} % of its "
            f"pitch {float(np.mean(q['pitch_px'])):.2f} px (at most "
            f"{100 * max_rms_residual_pitch:g} %, max_rms_residual_pitch); {hint}"
        )
    if max_missing_fraction is not None and q["missing_fraction"] > max_missing_fraction:
        shown = ", ".join(f"({i}, {j})" for i, j in lattice.missing_index[:6])
        more = " ..." if lattice.n_missing > 6 else ""
        raise CalibrationError(
            f"{what}: {q['n_missing']} lattice positions inside the image hold no spot, "
            f"{100 * q['missing_fraction']:.1f} % of them (at most "
            f"{100 * max_missing_fraction:g} %, max_missing_fraction); grid indices "
            f"{shown}{more}; {hint} (dark corners outside the lens's image circle: raise "
            "max_missing_fraction)"
        )
    return q


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
