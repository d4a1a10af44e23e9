"""Multi-pass 3-D cross-correlation of two reconstructed particle volumes (volumetric PIV).

The stage turns two volumes of the same grid, recorded a time ``dt`` apart, into a field of
displacement vectors: one per interrogation window. It implements the iterative multigrid
window-deformation scheme WIDIM (Scarano 2002) with a normalised median test between passes
(Westerweel & Scarano 2005).

Conventions (see :mod:`plenopiv.conventions`): volumes are indexed ``[z, y, x]``; the grid's
``origin`` is the ``(x, y, z)`` position of voxel ``[0, 0, 0]`` and its ``voxel_size`` the edge
``(dx, dy, dz)``, both in metres. The returned :class:`VectorField` holds window-centre
coordinates ``x, y, z`` (1-D, metres) and the displacement components ``u`` (along x), ``v``
(along y), ``w`` (along z) as arrays of shape ``(nz, ny, nx)`` in metres. Inside this module
index-space quantities carry the suffix ``_vox`` and are ordered ``(z, y, x)``.

A displacement ``d`` means that the pattern of ``volume_a`` at position ``p`` is found in
``volume_b`` at ``p + d``.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numba
import numpy as np
import scipy.fft
import scipy.ndimage

from plenopiv._piv_kernels import ENGINES
from plenopiv.conventions import voxel_to_world
from plenopiv.errors import PIVError

__all__ = [
    "FLAG_EMPTY",
    "FLAG_MASKED",
    "FLAG_OUTLIER",
    "PIVSettings",
    "VectorField",
    "correlate_volumes",
    "normalized_median_test",
    "replace_outliers",
]

SUBPIXEL_METHODS = ("gaussian", "parabolic")
"""Valid values of :attr:`PIVSettings.subpixel`."""

REPLACEMENT_METHODS = ("median", "mean", "none")
"""Valid values of :attr:`PIVSettings.replacement`."""

FLAG_OUTLIER = 1
"""Bit of :attr:`VectorField.flag`: the vector failed the normalised median test."""
FLAG_EMPTY = 2
"""Bit of :attr:`VectorField.flag`: the window had no intensity variation (no particles)."""
FLAG_MASKED = 4

#: Below this many window voxels (windows × voxels per window) of the last pass, the
#: correlation statistics use the plain-NumPy twin of their kernel even with
#: ``engine="numba"``: on a small field compiling the numba kernel (2-4 s of CPU on the first
#: run) costs more than it saves, and the twin's arrays (about ten float64 arrays of this
#: many values) stay under 200 MB. The two give the same statistics (tests).
NUMPY_STATISTICS_MAX_VOXELS = 2**21
"""Bit of :attr:`VectorField.flag`: the window centre lies in the volume mask."""

DEFORMATION_ORDERS = (1, 2, 3, 4, 5)
"""Valid values of :attr:`PIVSettings.deformation_order` (1: trilinear, >1: B-spline)."""

MIN_WINDOW_VOX = 4
"""Smallest interrogation window edge, voxels: the 3-point peak fit needs distinct neighbours."""

_CHUNK_BYTES = 4 * 2**20
"""Float32 window bytes correlated at once (small enough to stay in cache)."""

_SLAB_BYTES = 64 * 2**20
"""Bytes of partial (x, y) spectra held per volume while a slab of window rows is transformed."""

_MIN_ENERGY_FRACTION = 1e-6
"""A window whose energy about its mean is below this fraction of its total energy is empty."""

_SPLINE_PAD = 12
"""Zero voxels added around a volume before its B-spline prefilter (as scipy.ndimage does)."""

_DEFORM_CHUNK_VOXELS = 2**20
"""Voxels resampled per call of ``scipy.ndimage.map_coordinates`` (bounds its coordinate array)."""


# --------------------------------------------------------------------------------------------
# parameter and result objects
# --------------------------------------------------------------------------------------------


def _as_window(value, name):
    """Return one window as a ``(wz, wy, wx)`` tuple of int, or raise ValueError."""
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        value = (int(value),) * 3
    try:
        window = tuple(value)
    except TypeError:
        raise ValueError(
            f"{name} = {value!r}: expected an int or a (wz, wy, wx) tuple of int voxels"
        ) from None
    if len(window) != 3 or not all(
        isinstance(w, (int, np.integer)) and not isinstance(w, bool) for w in window
    ):
        raise ValueError(
            f"{name} = {value!r}: expected an int or a (wz, wy, wx) tuple of int voxels"
        )
    window = tuple(int(w) for w in window)
    if min(window) < MIN_WINDOW_VOX:
        raise ValueError(
            f"{name} = {window}: every window edge must be at least {MIN_WINDOW_VOX} voxels"
        )
    return window


@dataclass(frozen=True)
class PIVSettings:
    """Validated settings of a multi-pass volumetric cross-correlation.

    Parameters
    ----------
    windows : int, (wz, wy, wx) or sequence of (wz, wy, wx)
        Interrogation window edge in voxels, per pass and per axis in the volume's index order
        ``(z, y, x)``. A single int or triple means one window size for every pass. Windows
        may differ per axis: plenoptic particles are elongated in Z, so a taller window in z
        (e.g. ``((32, 32, 32), (24, 16, 16))``) keeps enough particle pairs per window.
        Every edge is at least 4 voxels. Stored as a tuple of triples.
    overlap : float
        Fraction of a window shared with its neighbour, ``0 <= overlap < 1``. The window step
        is ``max(1, round(w * (1 - overlap)))`` voxels per axis.
    passes : int or None
        Number of passes, at least ``len(windows)``; the passes after the last listed window
        repeat it (WIDIM iterations at the final resolution). ``None`` means ``len(windows)``.
    deformation : bool
        True: deform both volumes by the predictor field (WIDIM, Scarano 2002). False: shift
        each window pair by the predictor rounded to whole voxels (discrete window offset).
    deformation_order : int
        Interpolation order used to deform the volumes, one of ``DEFORMATION_ORDERS``:
        1 is trilinear and 3 a cubic B-spline (numba kernels); 2, 4 and 5 are B-splines
        evaluated by ``scipy.ndimage.map_coordinates`` (slower). Trilinear deformation
        leaves a bias of about 0.03 voxel on images of 1-voxel standard deviation.
    median_threshold : float
        Threshold of the normalised median test (dimensionless, > 0); 2.0 is the value
        recommended by Westerweel & Scarano (2005).
    median_epsilon_vox : float
        Noise level added to the median residual, voxels (>= 0); 0.1 voxel after
        Westerweel & Scarano (2005).
    median_iterations : int
        Detection rounds of the median test (>= 1); each round ignores the vectors flagged
        before it, so that clustered outliers do not hide each other.
    smooth_predictor : bool
        Low-pass the predictor of every pass after the first with a [1, 2, 1]/4 filter per
        axis before deforming (the returned field is not smoothed). This keeps repeated
        deformation passes stable (Schrijer & Scarano 2008); a linear flow is not changed.
    subpixel : str
        Sub-voxel peak estimator, one of ``SUBPIXEL_METHODS``: ``"gaussian"`` (3-point
        Gaussian fit per axis, parabolic where a value is not positive) or ``"parabolic"``.
    replacement : str
        What becomes of the vectors rejected after the last pass (failed median test, empty
        window), one of ``REPLACEMENT_METHODS``: ``"median"`` (component-wise median of the
        usable 3x3x3 neighbours, the default), ``"mean"`` (their mean) or ``"none"`` (left
        NaN). Between passes rejected vectors are always filled by the local median, since
        window deformation needs a complete predictor.

    Raises
    ------
    ValueError
        If a value is outside its valid range; the message names the parameter.

    Examples
    --------
    >>> s = PIVSettings(windows=((32, 32, 32), (24, 16, 16)), passes=3)
    >>> s.window_vox(2)
    (24, 16, 16)
    """

    windows: tuple[tuple[int, int, int], ...] | tuple[int, int, int] | int = (
        (32, 32, 32),
        (24, 24, 24),
    )
    overlap: float = 0.5
    passes: int | None = 3
    deformation: bool = True
    deformation_order: int = 3
    median_threshold: float = 2.0
    median_epsilon_vox: float = 0.1
    median_iterations: int = 2
    smooth_predictor: bool = True
    subpixel: str = "gaussian"
    replacement: str = "median"

    def __post_init__(self):
        w = self.windows
        is_int = lambda e: isinstance(e, (int, np.integer)) and not isinstance(e, bool)  # noqa: E731
        if is_int(w) or (
            isinstance(w, Sequence) and not isinstance(w, str) and all(map(is_int, w))
        ):
            windows = (_as_window(w, "windows"),)
        elif isinstance(w, Sequence) and not isinstance(w, str) and len(w) > 0:
            windows = tuple(_as_window(e, f"windows[{i}]") for i, e in enumerate(w))
        else:
            raise ValueError(
                f"windows = {w!r}: expected an int, a (wz, wy, wx) triple or a non-empty "
                "sequence of triples (voxels, one per pass)"
            )
        object.__setattr__(self, "windows", windows)

        passes = len(windows) if self.passes is None else self.passes
        if (
            not isinstance(passes, (int, np.integer))
            or isinstance(passes, bool)
            or passes < len(windows)
        ):
            raise ValueError(
                f"passes = {self.passes!r}: expected an int >= len(windows) = {len(windows)} "
                "(or None for exactly one pass per window)"
            )
        object.__setattr__(self, "passes", int(passes))

        if not (isinstance(self.overlap, (int, float)) and 0.0 <= self.overlap < 1.0):
            raise ValueError(
                f"overlap = {self.overlap!r}: expected a fraction with 0 <= overlap < 1"
            )
        for name in ("deformation", "smooth_predictor"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} = {getattr(self, name)!r}: expected True or False")
        if self.deformation_order not in DEFORMATION_ORDERS or isinstance(
            self.deformation_order, bool
        ):
            raise ValueError(
                f"deformation_order = {self.deformation_order!r}: "
                f"expected one of {DEFORMATION_ORDERS}"
            )
        if not (isinstance(self.median_threshold, (int, float)) and self.median_threshold > 0):
            raise ValueError(
                f"median_threshold = {self.median_threshold!r}: expected a number > 0 "
                "(2.0 is the usual value)"
            )
        eps = self.median_epsilon_vox
        if not (isinstance(eps, (int, float)) and math.isfinite(eps) and eps >= 0):
            raise ValueError(
                f"median_epsilon_vox = {eps!r}: expected a finite number of voxels >= 0 (e.g. 0.1)"
            )
        it = self.median_iterations
        if not isinstance(it, (int, np.integer)) or isinstance(it, bool) or it < 1:
            raise ValueError(f"median_iterations = {it!r}: expected an int >= 1")
        if self.subpixel not in SUBPIXEL_METHODS:
            raise ValueError(f"subpixel = {self.subpixel!r}: expected one of {SUBPIXEL_METHODS}")
        if self.replacement not in REPLACEMENT_METHODS:
            raise ValueError(
                f"replacement = {self.replacement!r}: expected one of {REPLACEMENT_METHODS}"
            )

    def window_vox(self, pass_index):
        """Window edge ``(wz, wy, wx)`` in voxels of pass ``pass_index`` (0-based)."""
        if not 0 <= pass_index < self.passes:
            raise ValueError(f"pass_index = {pass_index}: expected 0 <= pass_index < {self.passes}")
        return self.windows[min(pass_index, len(self.windows) - 1)]


def _readonly(array, dtype):
    a = np.array(array, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class VectorField:
    """A 3-D displacement field on the window-centre grid of the last PIV pass.

    Attributes
    ----------
    x, y, z : ndarray, shape (nx,), (ny,), (nz,)
        Window-centre coordinates in metres (volume coordinates X, Y, Z).
    u, v, w : ndarray, shape (nz, ny, nx)
        Displacement along x, y and z in metres (the volumes' ``[z, y, x]`` order is kept for
        the array axes; ``u`` is the x component).
    valid : ndarray of bool, shape (nz, ny, nx)
        False where the vector was rejected: it failed the normalised median test, its
        window had no particles, or its window centre is masked (``flag`` says which).
    snr : ndarray, shape (nz, ny, nx)
        Primary-to-secondary correlation peak ratio (dimensionless, >= 1; inf where no
        positive secondary peak exists); also available as :attr:`peak_ratio`.
    correlation : ndarray, shape (nz, ny, nx)
        Height of the correlation peak as a correlation coefficient (dimensionless, <= 1);
        0 for a window without particles. ``snr`` and ``correlation`` describe each window's
        own correlation in the last pass, also where its vector was replaced.
    n_replaced : int
        Number of vectors replaced after the last pass (``replaced.sum()``).
    settings : PIVSettings
        The settings that produced the field.
    replaced : ndarray of bool, shape (nz, ny, nx)
        True where a rejected vector was filled from its neighbours (``settings.replacement``
        ``"median"`` or ``"mean"``); rejected vectors that are not replaced are NaN. Default:
        ``~valid`` where ``u`` is finite.
    flag : ndarray of uint8, shape (nz, ny, nx)
        Why a vector was rejected, a sum of the bits ``FLAG_OUTLIER`` (1, normalised median
        test), ``FLAG_EMPTY`` (2, no intensity variation in the window) and ``FLAG_MASKED``
        (4, window centre in the volume mask); 0 for a valid vector. Default: ``FLAG_OUTLIER``
        where not ``valid``.
    u_uncertainty, v_uncertainty, w_uncertainty : ndarray, shape (nz, ny, nx)
        Standard uncertainty of ``u``, ``v``, ``w`` in metres (see :func:`correlate_volumes`,
        *Uncertainty*); NaN where no vector is given. Default: NaN (not estimated).
    uncertainty_parts : dict
        The terms of the uncertainty, each ``(3, nz, ny, nx)`` metres in ``(u, v, w)`` order:
        ``"correlation"`` (correlation statistics) and ``"last_correction"`` (the last pass's
        change of the estimate), for diagnostics; None if not estimated.

    All arrays are read-only.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    u: np.ndarray
    v: np.ndarray
    w: np.ndarray
    valid: np.ndarray
    snr: np.ndarray
    correlation: np.ndarray
    n_replaced: int = 0
    settings: PIVSettings = field(default_factory=PIVSettings)
    replaced: np.ndarray | None = None
    flag: np.ndarray | None = None
    u_uncertainty: np.ndarray | None = None
    v_uncertainty: np.ndarray | None = None
    w_uncertainty: np.ndarray | None = None
    uncertainty_parts: dict | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        for name in ("x", "y", "z"):
            object.__setattr__(self, name, _readonly(getattr(self, name), np.float64))
            if getattr(self, name).ndim != 1:
                raise ValueError(f"{name} has shape {getattr(self, name).shape}: expected 1-D")
        shape = (self.z.size, self.y.size, self.x.size)
        valid = np.asarray(self.valid, dtype=bool)
        if self.replaced is None:
            object.__setattr__(self, "replaced", ~valid & np.isfinite(np.asarray(self.u, float)))
        if self.flag is None:
            object.__setattr__(self, "flag", np.where(valid, 0, FLAG_OUTLIER))
        for name in ("u_uncertainty", "v_uncertainty", "w_uncertainty"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(shape, np.nan))
        for name, dtype in (
            ("u", np.float64),
            ("v", np.float64),
            ("w", np.float64),
            ("valid", bool),
            ("snr", np.float64),
            ("correlation", np.float64),
            ("replaced", bool),
            ("flag", np.uint8),
            ("u_uncertainty", np.float64),
            ("v_uncertainty", np.float64),
            ("w_uncertainty", np.float64),
        ):
            object.__setattr__(self, name, _readonly(getattr(self, name), dtype))
            if getattr(self, name).shape != shape:
                raise ValueError(
                    f"{name} has shape {getattr(self, name).shape}: expected (nz, ny, nx) = {shape}"
                )

    @property
    def shape(self):
        """Number of vectors per axis ``(nz, ny, nx)``."""
        return self.u.shape

    @property
    def peak_ratio(self):
        """Primary-to-secondary correlation peak ratio (the same array as ``snr``)."""
        return self.snr

    @property
    def masked(self):
        """True where the window centre lies in the volume mask (bool, (nz, ny, nx))."""
        return (self.flag & FLAG_MASKED) != 0

    def velocity(self, dt):
        """Velocity components ``(u, v, w) / dt`` in m/s.

        Parameters
        ----------
        dt : float
            Time between the two volumes, seconds (> 0).

        Returns
        -------
        tuple of ndarray
            ``(vx, vy, vz)``, each of shape ``(nz, ny, nx)``, in m/s.
        """
        if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt = {dt!r}: expected a finite time between the volumes > 0 s")
        return self.u / dt, self.v / dt, self.w / dt


# --------------------------------------------------------------------------------------------
# input checks
# --------------------------------------------------------------------------------------------


def _check_volumes(volume_a, volume_b):
    arrays = []
    for name, vol in (("volume_a", volume_a), ("volume_b", volume_b)):
        a = np.asarray(vol)
        if a.ndim != 3:
            raise PIVError(
                f"{name} has {a.ndim} dimensions (shape {a.shape}): expected a [z, y, x] volume"
            )
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise PIVError(f"{name} has dtype {a.dtype}: expected real numbers (float32 preferred)")
        a = np.ascontiguousarray(a, dtype=np.float32)
        bad = ~np.isfinite(a)
        if bad.any():
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            raise PIVError(
                f"{name} holds {int(bad.sum())} non-finite voxels (first at [z, y, x] = {first}): "
                "expected finite intensities"
            )
        arrays.append(a)
    if arrays[0].shape != arrays[1].shape:
        raise PIVError(
            f"volume_a has shape {arrays[0].shape} and volume_b {arrays[1].shape}: "
            "expected two volumes of the same [z, y, x] grid"
        )
    return arrays


def _grid_geometry(grid, shape):
    """Return ``origin (x, y, z)`` and ``voxel (dx, dy, dz)`` in metres from ``grid``.

    ``grid`` is a :class:`plenopiv.volume.VolumeGrid` (attributes ``origin``, ``voxel``,
    ``shape``) or any object with ``origin`` and ``voxel_size`` (and optionally ``shape``).
    """
    name = "voxel_size" if hasattr(grid, "voxel_size") else "voxel"
    if not (hasattr(grid, "origin") and hasattr(grid, name)):
        raise PIVError(
            f"grid = {grid!r}: expected a VolumeGrid, or an object with attributes origin "
            "(x, y, z) and voxel_size (dx, dy, dz), in metres"
        )
    edge = getattr(grid, name)
    try:
        origin = np.asarray(grid.origin, dtype=float)
        voxel = np.broadcast_to(np.asarray(edge, dtype=float), (3,)).copy()
    except (TypeError, ValueError):
        origin = voxel = np.full(3, np.nan)
        if np.shape(grid.origin) != (3,):
            origin = np.zeros(0)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise PIVError(f"grid.origin = {grid.origin!r}: expected three finite metres (x, y, z)")
    if not (np.all(np.isfinite(voxel)) and np.all(voxel > 0)):
        raise PIVError(f"grid.{name} = {edge!r}: expected (dx, dy, dz) > 0 metres")
    grid_shape = getattr(grid, "shape", None)
    if grid_shape is not None and tuple(int(s) for s in grid_shape) != tuple(shape):
        raise PIVError(
            f"grid.shape = {tuple(grid_shape)} but the volumes have shape {tuple(shape)}: "
            "expected the grid the volumes were reconstructed on"
        )
    return origin, voxel


def _check_windows(settings, shape):
    for k, window in enumerate(settings.windows):
        too_big = [
            f"{axis}: {w} > {n}" for axis, w, n in zip("zyx", window, shape, strict=True) if w > n
        ]
        if too_big:
            raise PIVError(
                f"settings.windows[{k}] = {window} voxels is larger than the volume "
                f"{tuple(shape)} ({', '.join(too_big)}): expected windows that fit the volume"
            )


def _resolve_workers(workers):
    if workers is None:
        return os.cpu_count() or 1
    if not isinstance(workers, (int, np.integer)) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers = {workers!r}: expected None (all cores) or an int >= 1")
    return int(workers)


@contextlib.contextmanager
def _numba_threads(workers):
    """Run the numba kernels on at most ``workers`` threads, restoring the previous count."""
    previous = numba.get_num_threads()
    numba.set_num_threads(max(1, min(workers, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(previous)


# --------------------------------------------------------------------------------------------
# window layout and field interpolation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Layout:
    """Window grid of one pass: start voxel and centre (voxels) per axis, ``(z, y, x)``."""

    window: tuple
    starts: tuple  # three 1-D int arrays
    centres: tuple  # three 1-D float arrays

    @property
    def shape(self):
        return tuple(s.size for s in self.starts)

    def all_starts(self):
        zz, yy, xx = np.meshgrid(*self.starts, indexing="ij")
        return np.stack([zz.ravel(), yy.ravel(), xx.ravel()], axis=1).astype(np.int64)


def _window_layout(shape, window, overlap):
    """Place windows with the given overlap, centred in the volume."""
    starts, centres = [], []
    for n, w in zip(shape, window, strict=True):
        step = max(1, round(w * (1.0 - overlap)))
        count = (n - w) // step + 1
        first = (n - ((count - 1) * step + w)) // 2
        s = first + step * np.arange(count)
        starts.append(s.astype(np.int64))
        centres.append(s + (w - 1) / 2.0)
    return _Layout(tuple(window), tuple(starts), tuple(centres))


def _lerp_axis(values, axis, source, target):
    """Linear interpolation of ``values`` along ``axis`` from ``source`` to ``target`` positions.

    ``source`` is evenly spaced. Beyond its ends the end segments are extended (linear
    extrapolation), so that a linear flow stays linear up to the volume's border.
    """
    n = source.size
    if n == 1:
        return np.repeat(values, target.size, axis=axis)
    pos = (np.asarray(target, dtype=float) - source[0]) / (source[1] - source[0])
    i0 = np.clip(np.floor(pos).astype(np.int64), 0, n - 2)
    t = (pos - i0).astype(values.dtype)
    shape = [1] * values.ndim
    shape[axis] = target.size
    t = t.reshape(shape)
    return np.take(values, i0, axis=axis) * (1 - t) + np.take(values, i0 + 1, axis=axis) * t


def _interpolate_field(field_vox, source, target):
    """Trilinearly interpolate a ``(3, nz, ny, nx)`` field from grid ``source`` to ``target``.

    ``source`` and ``target`` are triples of 1-D voxel positions ``(z, y, x)``; ``source`` is
    evenly spaced per axis. The field is interpolated linearly along one axis after the other,
    which on a regular grid is exactly trilinear, and extrapolated linearly beyond it.
    """
    out = field_vox
    for axis in (3, 2, 1):
        out = _lerp_axis(out, axis, source[axis - 1], target[axis - 1])
    return out


# --------------------------------------------------------------------------------------------
# one correlation pass
# --------------------------------------------------------------------------------------------


def _regular_spectra(volume, layout, workers):
    """Yield ``(iz, y0, y1, spectra)`` for the windows of a regular layout, a row at a time.

    ``spectra`` is the 3-D real FFT of the windows ``[iz, y0:y1, :]`` of ``volume``, laid out
    ``(kz, y1 - y0, ky, n_x, kx)`` (complex64). The transform is taken one axis at a time so
    that the 1-D transforms that overlapping windows share are computed once: along x for
    every (z, y) line segment of the volume, along y for every z plane of a window column,
    and only the last, along z, per window. With 50 % overlap this does about 60 % of the
    work of transforming every window on its own.
    """
    wz, wy, wx = layout.window
    sz, sy, sx = layout.starts
    step_z, step_y, step_x = (int(s[1] - s[0]) if s.size > 1 else 1 for s in layout.starts)
    n_z, n_y, n_x = layout.shape
    kx = wx // 2 + 1
    y_lo, y_hi = int(sy[0]), int(sy[-1]) + wy
    plane_bytes = n_y * wy * n_x * kx * 8
    rows_per_slab = max(1, (_SLAB_BYTES // plane_bytes - wz) // step_z + 1)
    rows_per_batch = max(1, _CHUNK_BYTES // (4 * wz * wy * wx * n_x))
    as_strided = np.lib.stride_tricks.as_strided
    for r0 in range(0, n_z, rows_per_slab):
        r1 = min(n_z, r0 + rows_per_slab)
        z_lo, z_hi = int(sz[r0]), int(sz[r1 - 1]) + wz
        slab = volume[z_lo:z_hi, y_lo:y_hi, int(sx[0]) :]
        s0, s1, s2 = slab.strides
        lines = as_strided(
            slab,
            shape=(z_hi - z_lo, y_hi - y_lo, n_x, wx),
            strides=(s0, s1, step_x * s2, s2),
            writeable=False,
        )
        fx = scipy.fft.rfft(lines, axis=-1, workers=workers)
        f0, f1, f2, f3 = fx.strides
        columns = as_strided(
            fx,
            shape=(z_hi - z_lo, n_y, wy, n_x, kx),
            strides=(f0, step_y * f1, f1, f2, f3),
            writeable=False,
        )
        fy = scipy.fft.fft(columns, axis=2, workers=workers, overwrite_x=False)
        del fx, columns
        for iz in range(r0, r1):
            off = int(sz[iz]) - z_lo
            for y0 in range(0, n_y, rows_per_batch):
                y1 = min(n_y, y0 + rows_per_batch)
                yield iz, y0, y1, scipy.fft.fft(fy[off : off + wz, y0:y1], axis=0, workers=workers)


def _spectrum_batches(volume_a, volume_b, layout, shift, workers, kernels):
    """Yield ``(lo, hi, fa, fb)``: real-FFT spectra of the window pairs ``lo:hi`` of a pass.

    ``fa`` and ``fb`` are (possibly strided) arrays laid out ``(kz, p, ky, q, kx)``, with
    ``p * q = hi - lo`` windows in the layout's flat (z, y, x) order. Without ``shift`` the
    windows lie on the regular grid of ``layout`` (:func:`_regular_spectra`); with ``shift``
    ((n, 3) int voxels, B relative to A) each pair is moved by ``-(shift // 2)`` in A and
    ``shift - shift // 2`` in B and copied out first, zero outside the volume.
    """
    window = layout.window
    n_z, n_y, n_x = layout.shape
    if shift is None:
        spectra = zip(
            _regular_spectra(volume_a, layout, workers),
            _regular_spectra(volume_b, layout, workers),
            strict=True,
        )
        for (iz, y0, y1, fa), (_, _, _, fb) in spectra:
            lo = (iz * n_y + y0) * n_x
            yield lo, lo + (y1 - y0) * n_x, fa, fb
    else:
        starts = layout.all_starts()
        starts_a = starts - shift // 2
        starts_b = starts_a + shift
        per_batch = max(1, _CHUNK_BYTES // (4 * math.prod(window)))
        for lo in range(0, starts.shape[0], per_batch):
            hi = min(starts.shape[0], lo + per_batch)
            fa, fb = (
                scipy.fft.rfftn(
                    kernels.extract_windows(vol, st[lo:hi], *window),
                    axes=(1, 2, 3),
                    workers=workers,
                )
                for vol, st in ((volume_a, starts_a), (volume_b, starts_b))
            )
            # (n, kz, ky, kx) seen as the (kz, 1, ky, n, kx) layout of _regular_spectra
            yield lo, hi, fa[None].transpose(2, 0, 3, 1, 4), fb[None].transpose(2, 0, 3, 1, 4)


def _correlate_pass(volume_a, volume_b, layout, *, shift, gaussian, workers, kernels):
    """Correlate every window pair of one pass.

    Returns the displacement (n, 3) in voxels ``(z, y, x)`` (NaN for windows without
    intensity variation), the peak height as a correlation coefficient and the peak ratio.
    """
    window = layout.window
    n = math.prod(layout.shape)
    disp = np.empty((n, 3))
    peak = np.empty(n)
    snr = np.empty(n)
    for lo, hi, fa, fb in _spectrum_batches(volume_a, volume_b, layout, shift, workers, kernels):
        kz, p, ky, q, kx = fa.shape
        cross = np.empty((p, q, kz, ky, kx), dtype=np.complex64)
        energy = kernels.cross_spectrum(fa, fb, window[2], cross)
        del fa, fb
        corr = scipy.fft.irfftn(
            cross.reshape((hi - lo,) + cross.shape[2:]),
            s=window,
            axes=(1, 2, 3),
            workers=workers,
            overwrite_x=True,
        )
        del cross
        d, p, r = kernels.find_peaks(corr, gaussian)
        # a window without intensity variation (energy about its mean at the float32
        # rounding level of its total energy) gives no vector
        empty = ~np.all(energy[:, :2] > _MIN_ENERGY_FRACTION * energy[:, 2:], axis=1)
        norm = np.sqrt(np.abs(energy[:, 0] * energy[:, 1]))
        d[empty] = np.nan
        r[empty] = np.nan
        with np.errstate(divide="ignore", invalid="ignore"):
            peak[lo:hi] = np.where(empty, 0.0, p / norm)
        disp[lo:hi] = d
        snr[lo:hi] = r
    return disp, peak, snr


def _spline_coefficients(volume, order):
    """Return the B-spline coefficients of ``volume``, taken as zero outside it.

    The coefficients live on a grid padded by ``_SPLINE_PAD`` voxels per side (they decay by
    a factor 0.27 per voxel for order 3, so the padding makes the zero border exact to float32).
    """
    padded = np.pad(volume, _SPLINE_PAD, mode="constant")
    return scipy.ndimage.spline_filter(padded, order=order, output=np.float32, mode="mirror")


def _deform(volume, field_vox, factor, order, kernels, coeffs=None):
    """Sample ``volume`` at ``p + factor * field_vox(p)`` for every voxel ``p`` (zero outside).

    Order 1 interpolates ``volume`` trilinearly; higher orders evaluate the B-spline whose
    coefficients ``coeffs`` come from :func:`_spline_coefficients`.
    """
    if order == 1:
        return kernels.deform_trilinear(volume, field_vox, factor)
    if order == 3:
        return kernels.deform_cubic(coeffs, field_vox, factor, _SPLINE_PAD)
    out = np.empty_like(volume)
    nz, ny, nx = volume.shape
    slab = max(1, _DEFORM_CHUNK_VOXELS // (ny * nx))
    iy, ix = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    for z0 in range(0, nz, slab):
        z1 = min(nz, z0 + slab)
        iz = np.arange(z0, z1, dtype=np.float64)[:, None, None]
        coords = np.empty((3, z1 - z0, ny, nx))
        coords[0] = iz + _SPLINE_PAD + factor * field_vox[0, z0:z1]
        coords[1] = iy + _SPLINE_PAD + factor * field_vox[1, z0:z1]
        coords[2] = ix + _SPLINE_PAD + factor * field_vox[2, z0:z1]
        out[z0:z1] = scipy.ndimage.map_coordinates(
            coeffs, coords, order=order, mode="grid-constant", cval=0.0, prefilter=False
        )
    return out


# --------------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------------


def _as_field(u, v, w):
    arrays = [np.asarray(a, dtype=np.float64) for a in (u, v, w)]
    if arrays[0].ndim != 3 or any(a.shape != arrays[0].shape for a in arrays):
        raise ValueError(
            f"u, v, w have shapes {[a.shape for a in arrays]}: expected three arrays of one "
            "(nz, ny, nx) shape"
        )
    return np.stack(arrays)


def _check_engine(engine):
    if engine not in ENGINES:
        raise ValueError(f"engine = {engine!r}: expected one of {tuple(ENGINES)}")
    return ENGINES[engine]


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
    """Replace like :func:`_replace`, with the mean of the usable 3x3x3 neighbours.

    The mean takes the place of the median; the border is completed by linear extrapolation
    as well.
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


# --------------------------------------------------------------------------------------------
# the public driver
# --------------------------------------------------------------------------------------------


def correlate_volumes(
    volume_a,
    volume_b,
    grid,
    *,
    settings=None,
    workers=None,
    engine="numba",
    progress: Callable[[dict], None] | None = None,
    mask=None,
):
    r"""Measure the displacement field between two particle volumes by multi-pass 3-D PIV.

    Parameters
    ----------
    volume_a, volume_b : array_like, shape (nz, ny, nx)
        Reconstructed intensities (arbitrary units) at the first and second exposure, indexed
        ``[z, y, x]`` on the same grid; finite values. Converted to float32; not changed.
    grid : VolumeGrid or similar
        The volumes' grid: ``origin``, the ``(x, y, z)`` centre of voxel ``[0, 0, 0]`` in
        metres, and the voxel edge ``(dx, dy, dz)`` (or one edge) in metres, named ``voxel``
        as in :class:`plenopiv.volume.VolumeGrid` or ``voxel_size``. If it has ``shape``,
        that must equal the volumes' shape.
    settings : PIVSettings, keyword-only
        Windows, passes, deformation and validation settings; ``PIVSettings()`` if None.
    workers : int, keyword-only
        Threads for the FFTs (``scipy.fft`` ``workers``) and the numba kernels (>= 1);
        None uses every core.
    engine : {"numba", "numpy"}, keyword-only
        Kernel implementation: ``"numba"`` (fast) or its plain-NumPy twin (reference). The
        correlation statistics of a small field (at most ``NUMPY_STATISTICS_MAX_VOXELS``
        window voxels) use the twin with either engine: compiling their numba kernel costs
        more than it saves there.
    progress : callable, keyword-only
        Called after each pass with a dict holding ``pass`` (1-based), ``passes``,
        ``window_vox``, ``n_vectors`` and ``n_outliers``.
    mask : array_like of bool, shape (nz, ny, nx), keyword-only
        Volume mask on the volumes' grid: True for voxels outside the flow (a model, a wall).
        Masked voxels are set to zero in both volumes before correlating, and a vector whose
        window centre lies in the mask (the mask, interpolated trilinearly at the centre, is
        at least 0.5) is NaN, not valid, and flagged ``FLAG_MASKED``. None: no mask.

    Returns
    -------
    VectorField
        Displacements (metres) on the window-centre grid of the last pass, with each
        vector's quality (peak height, peak ratio, flag, replaced) and standard uncertainty.

    Raises
    ------
    PIVError
        If the volumes differ in shape, are not 3-D, hold non-finite values, do not fit the
        windows, or the grid is unusable.
    ValueError
        If an option is outside its valid set.

    Notes
    -----
    *Correlation.* Each window pair ``a, b`` (means removed) is correlated circularly through
    real FFTs, without zero padding, batched over all windows of a pass:

    .. math:: R(s) = \frac{\sum_x a(x)\, b(x + s)}{\sqrt{\sum_x a^2 \sum_x b^2}}
              = \frac{\mathcal{F}^{-1}[\overline{\hat a}\, \hat b](s)}
                      {\lVert a\rVert\, \lVert b\rVert}

    so the peak height is a correlation coefficient. The integer peak ``s_0`` is refined per
    axis by the 3-point Gaussian fit (Willert & Gharib 1991)

    .. math:: \delta = \frac{\ln R_{-1} - \ln R_{+1}}{2(\ln R_{-1} - 2 \ln R_0 + \ln R_{+1})}

    falling back to the parabola (``R`` in place of ``ln R``) where a value is not positive,
    and to the integer peak where the parabola is not concave. The peak ratio ``snr`` is the
    primary peak over the highest other face-connected local maximum.

    The window spectra are computed one axis at a time, so that the 1-D transforms shared by
    overlapping windows are done once (x for every line segment of the volume, y for every
    plane of a window column, z per window), in float32 on ``workers`` threads.

    *Bias of one pass.* Particle images cut by the window border move less than the
    particles, so one correlation underestimates a displacement by a fraction that grows with
    the particle size over the window size: about 20 % for images of standard deviation
    1 voxel in 16-voxel windows, about 50 % along z for images of 2.5 voxels in 24-voxel
    windows (measured on synthetic volumes). Window deformation removes this bias: each pass
    measures only what the predictor left, and the corrector tends to zero as the passes
    converge, each pass reducing the remaining error by about that fraction. Particles much
    longer than the window along an axis therefore need more passes. The discrete window
    offset (``deformation=False``) keeps the bias on the sub-voxel remainder (up to about
    0.1 voxel for 16-voxel windows).

    *Multi-pass window deformation* (WIDIM, Scarano 2002). After each pass the field is
    validated (:func:`normalized_median_test`), outliers are replaced
    (:func:`replace_outliers`), and the result, the predictor ``d_p``, is interpolated
    trilinearly to every voxel. Both volumes are then deformed symmetrically (central
    difference),

    .. math:: A'(x) = A(x - d_p(x)/2), \qquad B'(x) = B(x + d_p(x)/2),

    with interpolation of order ``settings.deformation_order``, and the correlation of the
    deformed volumes gives the corrector ``d_c``; the new estimate is ``d_p + d_c`` at the
    window centres of the (possibly smaller) windows of the next pass. The predictor is
    extrapolated linearly beyond the outermost window centres and, with
    ``settings.smooth_predictor``, low-passed by a [1, 2, 1]/4 filter per axis, which keeps
    repeated passes from amplifying errors whose wavelength is close to the window size
    (Schrijer & Scarano 2008). With ``deformation=False`` each window pair is instead shifted
    by ``-/+ d_p/2`` rounded to whole voxels (discrete window offset).

    The last pass is validated too; ``valid`` marks the rejected vectors and
    ``settings.replacement`` says whether they are filled by the local median or mean or
    left NaN. The returned field is not smoothed.

    *Uncertainty* (correlation statistics, Wieneke 2015, per axis in 3-D). After the last
    pass the two (deformed) windows ``a, b`` (means removed) nearly coincide. Along axis
    ``e`` the correlation values beside the integer peak ``s_0`` are sums of per-voxel
    products, :math:`C^\pm = \sum_x c^\pm(x)` with :math:`c^+(x) = a(x)\, b(x + s_0 + e)`
    and :math:`c^-(x) = a(x + e)\, b(x + s_0)` (circular within the window, as the
    correlation), so that :math:`\Delta c = c^+ - c^-` vanishes voxel by voxel where the two
    windows are equal. The asymmetry :math:`\Delta C = C^+ - C^-` moves the sub-voxel peak;
    its standard deviation is estimated from the spread of :math:`\Delta c` about its mean,
    with the covariance of neighbouring voxels (a particle image spans several voxels)
    counted by summing :math:`\Delta c` over circular blocks of ``2h + 1`` voxels per axis
    (Bartlett's estimator):

    .. math:: \sigma_{\Delta C}^2 = \frac{1}{|B|} \sum_x
              \Big( \sum_{y \in B(x)} (\Delta c(y) - \overline{\Delta c}) \Big)^2

    with ``h`` per axis the particle image's correlation width, ``ceil(sqrt(2) s_p)`` for
    particle images of standard deviation ``s_p`` (from the volume's autocorrelation at a
    lag of one voxel, :func:`particle_image_size`). The standard uncertainty is the shift of
    the 3-point fit when the neighbours differ by :math:`\pm\sigma_{\Delta C}/2` about
    their mean :math:`\bar C = (C^+ + C^-)/2`:

    .. math:: \sigma = \left| \delta\big(C_0,\ \bar C + \sigma_{\Delta C}/2,\
              \bar C - \sigma_{\Delta C}/2\big) \right|

    with :math:`\delta` the Gaussian (or parabolic) estimator above. The statistics see
    only what makes the two deformed windows differ; the error the iteration left behind is
    not in them. After two or more passes the change the last pass made to the estimate,
    :math:`\Delta d` (its corrector), estimates it: the passes converge geometrically, each
    removing a fraction of the remaining error, so what remains after the last pass is of
    the order of the last correction (window-border truncation of elongated particle images,
    flow structures smaller than the smoothed predictor resolves). The standard uncertainty
    per axis is

    .. math:: \sigma^2 = \sigma_{CS}^2 + \Delta d^2.

    On noisy synthetic particle volumes 85-98 % of the true errors lie within
    :math:`\pm 2\sigma` (the statistics alone: 50-85 %). A replaced vector gets the root sum
    of squares of its neighbours' median uncertainty and the spread of the neighbours
    (1.4826 times their median absolute residual). For plenoptic volumes
    :mod:`plenopiv.uncertainty` adds the chain's measured response; see
    ``docs/validation/uncertainty.md`` for the coverage of true errors on the vortex flows.

    References
    ----------
    F. Scarano, "Iterative image deformation methods in PIV", Measurement Science and
    Technology 13, R1-R19 (2002). doi:10.1088/0957-0233/13/1/201

    J. Westerweel and F. Scarano, "Universal outlier detection for PIV data", Experiments in
    Fluids 39, 1096-1100 (2005). doi:10.1007/s00348-005-0016-6

    C. E. Willert and M. Gharib, "Digital particle image velocimetry", Experiments in Fluids
    10, 181-193 (1991). doi:10.1007/BF00190388

    F. F. J. Schrijer and F. Scarano, "Effect of predictor-corrector filtering on the
    stability and spatial resolution of iterative PIV interrogation", Experiments in Fluids
    45, 927-941 (2008).

    B. Wieneke, "PIV uncertainty quantification from correlation statistics", Measurement
    Science and Technology 26, 074002 (2015). doi:10.1088/0957-0233/26/7/074002

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> rng = np.random.default_rng(0)
    >>> a = rng.random((32, 32, 32), dtype=np.float32)
    >>> b = np.roll(a, (1, -2, 3), axis=(0, 1, 2))  # [z, y, x]
    >>> grid = SimpleNamespace(origin=(0.0, 0.0, 0.0), voxel_size=1e-4)
    >>> field = correlate_volumes(a, b, grid, settings=PIVSettings(windows=32, passes=1))
    >>> [round(float(c[0, 0, 0]) / 1e-4, 3) for c in (field.u, field.v, field.w)]
    [3.0, -2.0, 1.0]
    """
    settings = PIVSettings() if settings is None else settings
    if not isinstance(settings, PIVSettings):
        raise ValueError(f"settings = {settings!r}: expected a PIVSettings")
    kernels = _check_engine(engine)
    workers = _resolve_workers(workers)
    if progress is not None and not callable(progress):
        raise ValueError(f"progress = {progress!r}: expected a callable or None")
    vol_a, vol_b = _check_volumes(volume_a, volume_b)
    origin, voxel = _grid_geometry(grid, vol_a.shape)
    _check_windows(settings, vol_a.shape)
    mask = _check_mask(mask, vol_a.shape)
    if mask is not None:
        vol_a = np.where(mask, np.float32(0), vol_a)
        vol_b = np.where(mask, np.float32(0), vol_b)
    with _numba_threads(workers):
        return _multipass(
            vol_a, vol_b, origin, voxel, settings, workers, kernels, progress, mask=mask
        )


def _check_mask(mask, shape):
    """Return the volume mask as a bool array of ``shape`` (None if no voxel is masked)."""
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise PIVError(
            f"mask has shape {m.shape}: expected the volumes' [z, y, x] shape {tuple(shape)}"
        )
    if m.dtype != bool:
        if not (np.issubdtype(m.dtype, np.integer) and np.isin(m, (0, 1)).all()):
            raise PIVError(f"mask has dtype {m.dtype}: expected bool (True = masked voxel)")
        m = m.astype(bool)
    return m if m.any() else None


def _centre_mask(mask, layout):
    """Return True for the windows of ``layout`` whose centre lies in ``mask`` (flat, (n,))."""
    n = math.prod(layout.shape)
    if mask is None:
        return np.zeros(n, dtype=bool)
    zz, yy, xx = np.meshgrid(*layout.centres, indexing="ij")
    coords = np.stack([zz.ravel(), yy.ravel(), xx.ravel()])
    inside = scipy.ndimage.map_coordinates(
        mask.astype(np.float32), coords, order=1, mode="nearest", prefilter=False
    )
    return inside >= 0.5


def _multipass(vol_a, vol_b, origin, voxel, settings, workers, kernels, progress, mask=None):
    """Run the WIDIM loop of :func:`correlate_volumes` on checked inputs."""
    gaussian = settings.subpixel == "gaussian"
    order = settings.deformation_order
    coeffs_a = coeffs_b = None
    if settings.deformation and order > 1 and settings.passes > 1:
        coeffs_a = _spline_coefficients(vol_a, order)
        coeffs_b = _spline_coefficients(vol_b, order)
    voxel_axes = tuple(np.arange(n, dtype=float) for n in vol_a.shape)

    predictor = None  # (3, nz, ny, nx) field in voxels on `previous.centres`
    previous = None
    for k in range(settings.passes):
        layout = _window_layout(vol_a.shape, settings.window_vox(k), settings.overlap)
        if predictor is None:
            estimate, peak, snr = _correlate_pass(
                vol_a,
                vol_b,
                layout,
                shift=None,
                gaussian=gaussian,
                workers=workers,
                kernels=kernels,
            )
            # what the last correlation saw: the volumes, the window shifts, its displacement
            last = (vol_a, vol_b, None, estimate)
            change = None  # what the pass changed in the estimate (none for the first)
        elif settings.deformation:
            # float32 throughout: ten times faster than float64 for a full-size field
            dense = _interpolate_field(predictor.astype(np.float32), previous.centres, voxel_axes)
            a_def = _deform(vol_a, dense, -0.5, order, kernels, coeffs_a)
            b_def = _deform(vol_b, dense, +0.5, order, kernels, coeffs_b)
            del dense
            corrector, peak, snr = _correlate_pass(
                a_def,
                b_def,
                layout,
                shift=None,
                gaussian=gaussian,
                workers=workers,
                kernels=kernels,
            )
            at_centres = _interpolate_field(predictor, previous.centres, layout.centres)
            estimate = at_centres.reshape(3, -1).T + corrector
            last = (a_def, b_def, None, corrector)
            change = corrector
        else:
            at_centres = _interpolate_field(predictor, previous.centres, layout.centres)
            shift = np.rint(at_centres.reshape(3, -1).T).astype(np.int64)
            corrector, peak, snr = _correlate_pass(
                vol_a,
                vol_b,
                layout,
                shift=shift,
                gaussian=gaussian,
                workers=workers,
                kernels=kernels,
            )
            estimate = shift + corrector
            last = (vol_a, vol_b, shift, corrector)
            change = estimate - at_centres.reshape(3, -1).T

        in_mask = _centre_mask(mask, layout)
        empty = ~np.all(np.isfinite(estimate), axis=1) & ~in_mask
        estimate[in_mask] = np.nan
        field_vox = estimate.T.reshape((3,) + layout.shape)
        outlier, _ = _median_test(
            field_vox,
            settings.median_threshold,
            settings.median_epsilon_vox,
            settings.median_iterations,
            kernels,
        )
        validated = _replace(field_vox, outlier, kernels)
        predictor = _smooth_predictor(validated) if settings.smooth_predictor else validated
        previous = layout
        if progress is not None:
            progress(
                {
                    "pass": k + 1,
                    "passes": settings.passes,
                    "window_vox": layout.window,
                    "n_vectors": int(outlier.size),
                    "n_outliers": int(outlier.sum()),
                }
            )

    shape = previous.shape
    in_mask = in_mask.reshape(shape)
    empty = empty.reshape(shape)
    rejected = outlier | in_mask
    flag = (
        np.where(outlier & ~empty & ~in_mask, FLAG_OUTLIER, 0)
        | np.where(empty, FLAG_EMPTY, 0)
        | np.where(in_mask, FLAG_MASKED, 0)
    ).astype(np.uint8)
    if settings.replacement == "median":
        result = validated.copy()
    elif settings.replacement == "mean":
        result = _replace_mean(field_vox, outlier, kernels)
    else:
        result = np.where(rejected[None], np.nan, field_vox)
    result[:, in_mask] = np.nan
    replaced = rejected & ~in_mask & np.all(np.isfinite(result), axis=0)

    sigma_cs = _correlation_uncertainty(*last, previous, settings, kernels)
    last_change = np.zeros_like(sigma_cs)
    if change is not None:
        # the last pass's change of the estimate: what the iteration still had to correct
        last_change = np.abs(np.nan_to_num(change.T.reshape(sigma_cs.shape)))
    sigma_vox = np.sqrt(sigma_cs**2 + last_change**2)
    sigma_vox = _rejected_uncertainty(sigma_vox, result, rejected, in_mask, kernels)
    metres = np.array([voxel[2], voxel[1], voxel[0]])[:, None, None, None]  # (z, y, x) order
    parts = {name: (a * metres)[::-1] for name, a in
             (("correlation", sigma_cs), ("last_correction", last_change))}
    cz, cy, cx = previous.centres
    zeros = np.zeros
    x = voxel_to_world(np.stack([zeros(cx.size), zeros(cx.size), cx], axis=-1), origin, voxel)[:, 0]
    y = voxel_to_world(np.stack([zeros(cy.size), cy, zeros(cy.size)], axis=-1), origin, voxel)[:, 1]
    z = voxel_to_world(np.stack([cz, zeros(cz.size), zeros(cz.size)], axis=-1), origin, voxel)[:, 2]
    dx, dy, dz = voxel
    return VectorField(
        x=x,
        y=y,
        z=z,
        u=result[2] * dx,
        v=result[1] * dy,
        w=result[0] * dz,
        valid=~rejected,
        snr=snr.reshape(shape),
        correlation=peak.reshape(shape),
        n_replaced=int(replaced.sum()),
        settings=settings,
        replaced=replaced,
        flag=flag,
        u_uncertainty=sigma_vox[2] * dx,
        v_uncertainty=sigma_vox[1] * dy,
        w_uncertainty=sigma_vox[0] * dz,
        uncertainty_parts=parts,
    )


# --------------------------------------------------------------------------------------------
# uncertainty (correlation statistics)
# --------------------------------------------------------------------------------------------


def particle_image_size(volume):
    r"""Measure the particle images' standard deviation per axis, voxels ``(z, y, x)``.

    Parameters
    ----------
    volume : array_like, shape (nz, ny, nx)
        Reconstructed intensities (arbitrary units).

    Returns
    -------
    ndarray, shape (3,)
        ``s_p`` per axis in voxels (0 where neighbouring voxels are uncorrelated).

    Notes
    -----
    For Gaussian particle images of standard deviation :math:`s_p` the autocorrelation of the
    volume (mean removed) is a Gaussian of standard deviation :math:`\sqrt 2 s_p`, so its
    value at a lag of one voxel along an axis, relative to lag 0, is
    :math:`\rho_1 = \exp(-1/(4 s_p^2))`, and :math:`s_p = (-4 \ln \rho_1)^{-1/2}`.
    """
    v = np.asarray(volume, dtype=np.float64)
    v = v - v.mean()
    energy = float(np.vdot(v, v))
    out = np.zeros(3)
    if energy <= 0:
        return out
    for axis in range(3):
        if v.shape[axis] < 2:
            continue
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis] = slice(0, -1)
        hi[axis] = slice(1, None)
        rho = float(np.vdot(v[tuple(lo)], v[tuple(hi)])) / energy
        if 0 < rho < 1:
            out[axis] = math.sqrt(-1.0 / (4.0 * math.log(rho)))
    return out


def _statistics_block(volume, window):
    """Block of the covariance sum per axis: ``2 h + 1`` voxels, ``h = ceil(sqrt(2) s_p)``."""
    size = particle_image_size(volume)
    half = np.ceil(np.sqrt(2.0) * size).astype(np.int64)
    half = np.minimum(half, (np.asarray(window) - 1) // 2)
    return 2 * half + 1


def _sigma_from_asymmetry(c0, cp, cm, spread, gaussian):
    """Shift of the 3-point fit for neighbours ``mean(cp, cm) +/- spread / 2``, voxels."""
    mean = 0.5 * (cp + cm)
    hi = mean + 0.5 * spread
    lo = mean - 0.5 * spread
    with np.errstate(divide="ignore", invalid="ignore"):
        parabolic = 0.5 * spread / (2.0 * (c0 - mean))
        sigma = np.where(c0 > hi, np.abs(parabolic), 0.5)
        if gaussian:
            use = (lo > 0) & (c0 > hi)
            l0 = np.log(np.where(use, c0, 1.0))
            lh = np.log(np.where(use, hi, 1.0))
            ll = np.log(np.where(use, lo, 1.0))
            g = (lh - ll) / (2.0 * (2.0 * l0 - lh - ll))
            sigma = np.where(use, np.abs(g), sigma)
    # a peak no higher than its neighbours locates nothing better than half a voxel
    return np.where(np.isfinite(sigma), np.minimum(sigma, 0.5), 0.5)


def _statistics_kernel(kernels, n_windows, window):
    """Choose the ``peak_statistics`` kernel for ``n_windows`` windows of shape ``window``.

    The NumPy twin when they hold at most ``NUMPY_STATISTICS_MAX_VOXELS`` voxels, else the
    engine's own.
    """
    if n_windows * math.prod(window) <= NUMPY_STATISTICS_MAX_VOXELS:
        return ENGINES["numpy"].peak_statistics
    return kernels.peak_statistics


def _correlation_uncertainty(vol_a, vol_b, shift, measured, layout, settings, kernels):
    """Estimate the standard uncertainty (3, nz, ny, nx), voxels ``(z, y, x)``, by statistics.

    The statistics are those of the correlation peak (Wieneke 2015).

    ``vol_a, vol_b`` are the volumes the last pass correlated (deformed, or with the window
    ``shift`` of a discrete offset), ``measured`` ((n, 3) voxels) the displacement that pass
    found between its windows; its integer part is the correlation peak.
    """
    n = math.prod(layout.shape)
    starts = layout.all_starts()
    if shift is None:
        starts_a = starts_b = starts
    else:
        starts_a = starts - shift // 2
        starts_b = starts_a + shift
    ok = np.all(np.isfinite(measured), axis=1)
    peak = np.zeros((n, 3), dtype=np.int64)
    peak[ok] = np.rint(measured[ok]).astype(np.int64)
    block = _statistics_block(vol_a, layout.window).astype(np.int64)
    stats = _statistics_kernel(kernels, n, layout.window)(
        vol_a,
        vol_b,
        np.ascontiguousarray(starts_a),
        np.ascontiguousarray(starts_b),
        *layout.window,
        peak,
        block,
    )
    sigma = np.empty((3, n))
    for axis in range(3):
        spread = np.sqrt(np.maximum(stats[:, 7 + axis], 0.0))
        sigma[axis] = _sigma_from_asymmetry(
            stats[:, 0],
            stats[:, 1 + 2 * axis],
            stats[:, 2 + 2 * axis],
            spread,
            settings.subpixel == "gaussian",
        )
    sigma[:, ~ok] = np.nan
    return sigma.reshape((3,) + layout.shape)


def _rejected_uncertainty(sigma_vox, result, rejected, in_mask, kernels):
    """Uncertainty of the final field.

    Rejected vectors get their neighbours' (see Notes of :func:`correlate_volumes`); NaN where
    no vector is given.
    """
    sigma = np.where(rejected[None], np.nan, sigma_vox)
    usable = ~rejected & np.all(np.isfinite(sigma), axis=0)
    fill = rejected & np.all(np.isfinite(result), axis=0)
    if fill.any() and usable.any():
        med_sigma, _ = kernels.neighbour_median(
            np.ascontiguousarray(np.nan_to_num(sigma)), np.ascontiguousarray(usable)
        )
        _, spread = _extrapolated_neighbours(result, usable, kernels)
        combined = np.sqrt(med_sigma**2 + (1.4826 * spread) ** 2)
        fill_ok = fill & np.all(np.isfinite(combined), axis=0)
        sigma[:, fill_ok] = combined[:, fill_ok]
    sigma[:, ~np.all(np.isfinite(result), axis=0)] = np.nan
    sigma[:, in_mask] = np.nan
    return sigma
