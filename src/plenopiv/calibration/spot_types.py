"""The results of calibration step 1: spot flags, spot sets and fitted lenslet lattices.

:class:`SpotSet` holds what :func:`~plenopiv.calibration.spot_detection.detect_spots` finds,
:class:`Lattice` what :func:`~plenopiv.calibration.lattice_fit.fit_lattice` fits; the lattice
convention is stated in docs/methods.md#lattice-fit. Every length is in pixels (px).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

GRIDS = ("square", "hexagonal")
# a spot is on its lattice when within this fraction of the pitch of its node
ON_LATTICE_RADIUS = 0.15
METHODS = ("auto", "window", "shape", "centroid", "gaussian")
RESOLVED_METHODS = ("window", "shape", "centroid", "gaussian")
BACKGROUNDS = ("local", "none")


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
        The estimator that gave the centres: ``"window"``, ``"shape"``, ``"centroid"`` or
        ``"gaussian"`` (``"auto"`` is resolved to one of them).
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
    centre_std_px : ndarray of float64, shape (N, 2)
        Standard error of each centre per axis ``(row, col)``, px: the residual of a fit of
        the spots' mean shape to the spot
        (:func:`~plenopiv.calibration.spot_shape.shape_uncertainty`); NaN when not measured.
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
    centre_std_px: np.ndarray | None = None

    def __post_init__(self):
        c = _frozen(self.centres_px, np.float64).reshape(-1, 2)
        n = c.shape[0]
        object.__setattr__(self, "centres_px", c)
        std = np.full((n, 2), np.nan) if self.centre_std_px is None else self.centre_std_px
        std = _frozen(std, np.float64).reshape(-1, 2)
        if std.shape[0] != n:
            raise ValueError(f"SpotSet.centre_std_px has {std.shape[0]} rows; expected {n}")
        object.__setattr__(self, "centre_std_px", std)
        light = np.full(n, np.nan) if self.intensity is None else self.intensity
        light = _frozen(light, np.float64).reshape(-1)
        if light.shape[0] != n:
            raise ValueError(f"Lattice.intensity has {light.shape[0]} entries; expected {n}")
        object.__setattr__(self, "intensity", light)
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
    centre_std_px : ndarray, shape (N, 2)
        Standard error of each measured centre per axis, px (the spot set's; NaN when not
        known). With it the lattice tells how far its lenslets scatter about their nodes
        (:attr:`scatter_px`) and keeps each lenslet's own centre where that is the better
        estimate (:attr:`best_centres_px`).
    intensity : ndarray, shape (N,)
        Each spot's light (the spot set's; NaN when not known), for
        :attr:`lenslet_contrast`.
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
    centre_std_px: np.ndarray | None = None
    intensity: np.ndarray | None = None

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
        std = np.full((n, 2), np.nan) if self.centre_std_px is None else self.centre_std_px
        std = _frozen(std, np.float64).reshape(-1, 2)
        if std.shape[0] != n:
            raise ValueError(f"Lattice.centre_std_px has {std.shape[0]} rows; expected {n}")
        object.__setattr__(self, "centre_std_px", std)
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
    def scatter_px(self):
        """How far the lenslets scatter about their lattice nodes, per axis ``(row, col)``, px.

        The robust variance of the inliers' residuals (1.4826 MAD, squared) less their
        centres' own mean squared standard error (:attr:`centre_std_px`), at least 0: the
        real array's irregularity, what the measurement noise does not explain. Where the
        standard errors are unknown, the residuals' whole spread.
        """
        res = self.residual_px[self.inlier]
        if res.shape[0] < 2:
            return np.zeros(2)
        mad = 1.4826 * np.median(np.abs(res - np.median(res, axis=0)), axis=0)
        std = self.centre_std_px[self.inlier]
        noise = np.nanmean(std * std, axis=0) if np.isfinite(std).any() else np.zeros(2)
        return np.sqrt(np.maximum(mad * mad - np.nan_to_num(noise), 0.0))

    @property
    def best_centres_px(self):
        """Each lenslet's best centre, ``(row, col)`` px, shape (N, 2).

        Its measured centre where that is better than the lattice, its node where not, a
        weighted mean between. The node stands for the lenslet to within the array's scatter tau
        (:attr:`scatter_px`), the measured centre (less its phase bias) to within its standard
        error sigma (:attr:`centre_std_px`); their inverse-variance mean, the weight of the
        measurement tau^2 / (tau^2 + sigma^2), is the best linear estimate. So a regular
        array (tau ~ 0) keeps its nodes, a scattered one (tau >> sigma) its measured centres,
        per axis. Spots left out of the fit (partial, outliers, duplicates, off the lattice)
        and spots of unknown error take their node.
        """
        node = self.predict(self.grid_index)
        w = self._measurement_weight()
        return node + w * (self.corrected_centres_px - node)

    @property
    def best_centres_std_px(self):
        """Standard error of :attr:`best_centres_px` per axis, px, shape (N, 2)."""
        tau2 = self.scatter_px[None, :] ** 2
        w = self._measurement_weight()
        return np.sqrt((1.0 - w) * tau2)

    def _measurement_weight(self):
        """tau^2 / (tau^2 + sigma^2) per spot and axis (0 where not fitted or unknown)."""
        tau2 = self.scatter_px[None, :] ** 2
        sigma2 = self.centre_std_px ** 2
        with np.errstate(invalid="ignore", divide="ignore"):
            w = np.where(tau2 + sigma2 > 0, tau2 / (tau2 + sigma2), 0.0)
        w = np.where(np.isfinite(w), w, 0.0)
        return np.where(self.inlier[:, None], w, 0.0)

    @property
    def on_lattice_fraction(self):
        """Fraction of the complete spots within :data:`ON_LATTICE_RADIUS` pitch of their node.

        A lenslet array puts all of them there, even one whose lenslets scatter by 5 % of its
        pitch per axis (98.9 %); spots of a scene, a particle image or of noise, with no
        lattice, fall there by the area alone, pi 0.15^2 = 7 % of a cell. 1.0 when no spot is
        complete.
        """
        complete = (self.flags & SpotFlag.EDGE) == 0
        if not complete.any():
            return 1.0
        r = np.hypot(*self.residual_px[complete].T)
        return float(np.mean(r <= ON_LATTICE_RADIUS * self.lenslet_pitch_px))

    @property
    def lenslet_contrast(self):
        """How unevenly the lenslets are lit, a fraction.

        The 90th percentile over the complete spots on the lattice (dim ones and outliers
        included) of ``|I / I_n - 1|``, I a spot's light and I_n the median of its 4 nearest
        such spots'. A calibration image lights its
        lenslets alike but for a smooth vignetting and a spread of their throughput (±10 %
        gives 0.11-0.13, a corner vignetted down to 4 % 0.04); a scene modulates them (a
        ruler 0.35-0.45, the plenoptomos letters 0.24). 0 with fewer than 5 such spots or
        without intensities.
        """
        skip = SpotFlag.EDGE | SpotFlag.OFF_LATTICE | SpotFlag.DUPLICATE
        use = ((self.flags & skip) == 0) & np.isfinite(self.intensity)
        if np.count_nonzero(use) < 5:
            return 0.0
        pts, light = self.centres_px[use], self.intensity[use]
        _, nb = cKDTree(pts).query(pts, k=5)
        ref = np.median(light[nb[:, 1:]], axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            rel = np.abs(light / ref - 1.0)
        rel = rel[np.isfinite(rel)]
        return float(np.percentile(rel, 90)) if rel.size else 0.0

    @property
    def pitch_px(self):
        """Spacing between adjacent lattice rows and adjacent columns, ``(rows, cols)`` px.

        On a hexagonal grid ``pitch_px[1]`` is the lenslet pitch and ``pitch_px[0]`` the row
        spacing, about ``sqrt(3) / 2`` of it.
        """
        return np.hypot(self.basis[:, 0], self.basis[:, 1])

    @property
    def lenslet_pitch_px(self) -> float:
        """The distance between neighbouring lenslets, px.

        The mean of :attr:`pitch_px` on a square grid; on a hexagonal one the mean of the
        column pitch and the row spacing over sqrt(3)/2 (both the lenslet pitch), not the
        mean of the two spacings, which is 7 % short of it.
        """
        p = self.pitch_px
        if self.grid == "hexagonal":
            return float(0.5 * (p[1] + p[0] * 2.0 / math.sqrt(3.0)))
        return float(np.mean(p))

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
        (the same over the lenslet pitch, ``lenslet_pitch_px``: :attr:`lenslet_pitch_px`);
        ``n_spots``, ``n_fitted`` (inliers), ``n_edge``,
        ``n_off_lattice``, ``n_outliers``; ``n_missing`` and ``missing_fraction``;
        ``phase_bias_px``, the largest fitted sub-pixel phase bias (0 when none was fitted);
        ``on_lattice_fraction`` (:attr:`on_lattice_fraction`), ``scatter_px``, the lenslets'
        scatter about their nodes (:attr:`scatter_px`, both axes together), and
        ``lenslet_contrast`` (:attr:`lenslet_contrast`).
        :func:`~plenopiv.calibration.lattice_quality.check_lattice` refuses a lattice by these
        figures.
        """
        f = self.flags
        pitch = self.pitch_px
        return {
            "grid": self.grid,
            "pitch_px": [float(v) for v in pitch],
            "lenslet_pitch_px": self.lenslet_pitch_px,
            "rotation_rad": self.rotation_rad,
            "shear_deg": math.degrees(self.shear_rad),
            "rms_residual_px": self.rms_residual_px,
            "rms_residual_pitch": self.rms_residual_px / self.lenslet_pitch_px,
            "n_spots": len(self.centres_px),
            "n_fitted": int(np.count_nonzero(self.inlier)),
            "n_edge": int(np.count_nonzero(f & SpotFlag.EDGE)),
            "n_off_lattice": int(np.count_nonzero(f & SpotFlag.OFF_LATTICE)),
            "n_outliers": int(np.count_nonzero(f & SpotFlag.OUTLIER)),
            "n_missing": self.n_missing,
            "missing_fraction": self.missing_fraction,
            "phase_bias_px": float(np.abs(self.phase_bias_px).max()) if len(f) else 0.0,
            "on_lattice_fraction": self.on_lattice_fraction,
            "scatter_px": float(np.hypot(*self.scatter_px)),
            "lenslet_contrast": self.lenslet_contrast,
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


def _edge_mask(centres, radius, shape):
    """Spots whose circular window of ``radius`` px leaves the image area."""
    n_rows, n_cols = shape
    return (
        (centres[:, 0] - radius < -0.5)
        | (centres[:, 0] + radius > n_rows - 0.5)
        | (centres[:, 1] - radius < -0.5)
        | (centres[:, 1] + radius > n_cols - 0.5)
    )
