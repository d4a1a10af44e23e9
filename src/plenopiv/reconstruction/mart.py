"""Tomographic reconstruction of a particle volume from one plenoptic image: MLOS and MART.

The recorded intensity of pixel i is ``I_i = sum_j w_ij E_j``
(:mod:`plenopiv.reconstruction.projector`); this module inverts it with non-negative
multiplicative iterations: :func:`mlos` (the multiplicative line-of-sight first guess),
:func:`reconstruct` (row-action MART, block-iterative MART or SMART) and
:func:`reconstruction_quality` (the normalised correlation Q with a known volume). Volumes are
flat ``(n_voxels,)`` float32 arrays in ``[z, y, x]`` C order unless a ``shape`` is given;
images are ``(row, col)`` C order, in counts.

See docs/methods.md#mlos-mart-and-smart for the updates, the pixel order and the references.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable

import numpy as np

from plenopiv.errors import ImageError, ReconstructionError
from plenopiv.reconstruction._kernels import mart as _k
from plenopiv.reconstruction.projector import Projector, RowAccessProjector

__all__ = ["METHODS", "INITIAL_GUESSES", "reconstruct", "mlos", "reconstruction_quality"]

#: Bound on the log-ratio of a ceiling row (a dark pixel): it lowers its voxels by at most
#: exp(-0.5 μ w_ij / Σ_i w_ij) per sweep, so that the few dark pixels among the ~200 that see
#: a voxel trim it rather than outvote its lit pixels in one sweep: more particles are found
#: than without a bound, at the same ghost rate, and single particles keep their depth
#: (benchmarks/grid_independence.py, docs/validation/depth_study.md).
CEILING_LOG_BOUND = 0.5
#: Valid values of ``reconstruct(method=...)``.
METHODS = ("mart", "block", "smart")
#: Valid names for ``reconstruct(initial=...)`` (an array is accepted too).
INITIAL_GUESSES = ("mlos", "ones")


def reconstruct(
    image,
    projector: Projector,
    *,
    method: str,
    iterations: int,
    relaxation: float,
    pixel_threshold: float = 0.0,
    blocks=None,
    initial="mlos",
    shape: tuple[int, int, int] | None = None,
    callback: Callable[[int, np.ndarray], None] | None = None,
    ceiling=None,
) -> np.ndarray:
    r"""Reconstruct the voxel intensities E from one image by multiplicative iterations.

    ``method``, ``iterations`` and ``relaxation`` have no defaults here: they are the
    ``[reconstruction]`` settings
    (:class:`~plenopiv.reconstruction.settings.ReconstructionSettings`, whose
    defaults are SMART, 10 sweeps, μ = 2), given by the caller.

    Parameters
    ----------
    image : array_like, n_pixels values
        Recorded intensities I (counts, finite, >= 0), any shape of ``projector.n_pixels``
        values in ``(row, col)`` C order.
    projector : Projector
        The weights W. ``method="mart"`` and ``"block"`` need row access
        (:class:`~plenopiv.reconstruction.projector.RowAccessProjector`, e.g.
        :class:`~plenopiv.reconstruction.projector.SparseProjector`); ``"smart"`` and the MLOS
        first guess
        use only ``forward``/``back``.
    method : {"mart", "block", "smart"}
        ``"mart"``: row action, one pixel at a time (Elsinga et al. 2006).
        ``"block"``: the pixels of a block (``blocks``) act simultaneously, blocks in turn.
        ``"smart"``: all pixels act simultaneously (one block).
    iterations : int
        Sweeps over all pixels (>= 0; 0 returns the first guess).
    relaxation : float
        Relaxation factor mu (dimensionless, > 0); 1 is the classical MART.
    pixel_threshold : float
        Pixels with ``I_i <= pixel_threshold`` (counts) are dark: zero, which zeroes every
        voxel they see, once, before the first sweep (see Notes).
    blocks : array_like of int, n_pixels values, optional
        Block label of each pixel, required by ``method="block"`` (for example the
        perspective view a pixel belongs to, or the set of lenslets it lies under); blocks
        are updated in ascending label order. Must be None for the other methods.
    initial : {"mlos", "ones"} or array_like
        First guess: the MLOS volume (:func:`mlos`), uniform ones, or a volume of
        ``n_voxels`` non-negative values (e.g. the previous time step). Voxels seen by a dark
        pixel, or by no pixel at all, are set to zero whichever is chosen.
    shape : tuple of 3 int, optional
        ``(nz, ny, nx)`` to return the volume reshaped (``projector.n_voxels`` voxels).
    callback : callable, optional
        ``callback(iteration, volume)`` after each sweep (from 1), a read-only view.
    ceiling : array_like of bool, n_pixels values, optional
        ``method="smart"`` only: pixels whose intensity is an upper bound rather than a
        measurement (dark pixels given the noise floor as intensity). Their ratio
        ``I_i / sum_k w_ik E_k`` is capped at 1, so they only ever lower the voxels they see
        (where the projection exceeds the floor), never raise them, and its logarithm is
        bounded below by ``-CEILING_LOG_BOUND``.

    Returns
    -------
    ndarray of float32
        The volume E (>= 0), shape ``(n_voxels,)`` or ``shape``.

    Raises
    ------
    ImageError
        The image holds NaN/inf or negative values, or no pixel above ``pixel_threshold``.
    ReconstructionError
        The image, ``blocks``, ``initial`` or ``shape`` does not match the projector, the
        projector lacks row access for ``"mart"``/``"block"``, or (``initial`` "mlos" or
        "ones") the dark pixels see every voxel the lit ones see.
    ValueError
        An option is outside its valid set.

    Notes
    -----
    The methods, their updates, the sweep's order and the dark pixels: the module docstring.
    """
    iterations, relaxation, pixel_threshold, ceiling = _checked_options(
        projector, method, iterations, relaxation, pixel_threshold, blocks, callback, ceiling)
    volume_shape = _check_shape(shape, projector.n_voxels)
    intensity = _check_image(image, projector.n_pixels, pixel_threshold)
    bright = intensity > pixel_threshold
    schedule = projector.block_schedule(blocks) if method == "block" else None

    volume = _first_guess(initial, intensity, bright, projector)
    if isinstance(initial, str):
        _check_not_empty(volume, pixel_threshold)
    sweep = _sweep_of(method, projector, intensity, bright, relaxation, schedule, ceiling)
    _sweeps(projector, sweep, volume, iterations, callback, volume_shape)
    return _shaped(volume, volume_shape)


def mlos(image, projector: Projector, *, pixel_threshold: float = 0.0,
         shape: tuple[int, int, int] | None = None) -> np.ndarray:
    r"""Multiplicative line-of-sight (MLOS) estimate of the volume, the first guess of MART.

    Parameters
    ----------
    image : array_like, n_pixels values
        Recorded intensities I (counts, finite, >= 0), ``(row, col)`` C order.
    projector : Projector
        The weights W; only ``forward``/``back``/``row_sums``/``column_sums`` are used, so a
        matrix-free projector works too.
    pixel_threshold : float
        Pixels with ``I_i <= pixel_threshold`` (counts) are dark.
    shape : tuple of 3 int, optional
        ``(nz, ny, nx)`` to return the volume reshaped.

    Returns
    -------
    ndarray of float32
        ``(n_voxels,)`` or ``shape``; zero wherever a dark pixel, or no pixel, sees the voxel.

    Notes
    -----
    A voxel is zero if any pixel that sees it (``w_ij > 0``) is dark; otherwise it is the
    weighted geometric mean of the normalised intensities of the pixels that see it,

    .. math:: E_j = \exp\left(\frac{\sum_i w_{ij} \ln(I_i / R_i)}{\sum_i w_{ij}}\right),
              \qquad R_i = \sum_k w_{ik},

    where ``I_i / R_i`` is the voxel intensity that would give I_i if pixel i's beam were
    uniformly bright. This is the product form of MLOS (Atkinson & Soria 2009), taken to
    the power ``1 / sum_i w_ij`` so that E keeps the units of intensity whatever the number
    of views. It is chosen over the minimum form (Putze & Maas 2008) because it needs only
    two back projections, ``Wᵀ·[dark]`` and ``Wᵀ·ln(I/R)``, so it works for any
    :class:`~plenopiv.reconstruction.projector.Projector`, matrix-free ones included; the minimum
    needs the
    rows. Both zero the same voxels.

    References
    ----------
    .. [1] C. Atkinson, J. Soria, "An efficient simultaneous reconstruction technique for
       tomographic particle image velocimetry", Exp. Fluids 47, 553-568 (2009).
    .. [2] T. Putze, H.-G. Maas, "3D determination of very dense particle velocity fields by
       tomographic reconstruction from four camera views and voxel space tracking", Int.
       Arch. Photogramm. Remote Sens. Spat. Inf. Sci. 37, 33-38 (2008).
    """
    pixel_threshold = _check_float(pixel_threshold, "pixel_threshold", positive=False)
    _check_projector(projector, need_rows=False, method="mlos")
    volume_shape = _check_shape(shape, projector.n_voxels)
    intensity = _check_image(image, projector.n_pixels, pixel_threshold)
    bright = intensity > pixel_threshold
    return _shaped(_mlos(intensity, bright, projector), volume_shape)


def reconstruction_quality(volume, volume_true) -> float:
    r"""Normalised correlation Q between a reconstructed and a true volume.

    Parameters
    ----------
    volume : array_like
        Reconstructed intensities E (any shape).
    volume_true : array_like
        True intensities E* on the same grid (same shape).

    Returns
    -------
    float
        Q in [-1, 1]; 1 for a perfect reconstruction up to a positive scale factor.

    Notes
    -----
    .. math:: Q = \frac{\sum_j E_j E^*_j}{\sqrt{\sum_j E_j^2 \, \sum_j E^{*2}_j}}

    (Elsinga et al. 2006, Eq. 3), summed in float64. Q >= 0.75 is the usual bar for a
    volume fit for cross-correlation.

    Examples
    --------
    >>> reconstruction_quality([0.0, 2.0, 1.0], [0.0, 4.0, 2.0])
    1.0
    """
    e = np.asarray(volume, dtype=np.float64)
    t = np.asarray(volume_true, dtype=np.float64)
    if e.shape != t.shape:
        raise ReconstructionError(
            f"volume has shape {e.shape} but volume_true has shape {t.shape}; they must match"
        )
    if not (np.all(np.isfinite(e)) and np.all(np.isfinite(t))):
        raise ReconstructionError("volume and volume_true must be finite (found NaN or inf)")
    norm = math.sqrt(float(np.sum(e * e)) * float(np.sum(t * t)))
    if norm == 0.0:
        raise ReconstructionError("Q is undefined: volume or volume_true is all zero")
    return float(np.sum(e * t)) / norm


# -- helpers ------------------------------------------------------------------------------


def _checked_options(projector, method, iterations, relaxation, pixel_threshold, blocks,
                     callback, ceiling) -> tuple:
    """``(iterations, relaxation, pixel_threshold, ceiling)`` of :func:`reconstruct`, checked.

    Raises ValueError for an option outside its valid set, ReconstructionError for one that
    does not match the projector.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}; got {method!r}")
    iterations = _check_int(iterations, "iterations", minimum=0)
    relaxation = _check_float(relaxation, "relaxation", positive=True)
    pixel_threshold = _check_float(pixel_threshold, "pixel_threshold", positive=False)
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be callable or None; got {type(callback).__name__}")
    _check_projector(projector, need_rows=method in ("mart", "block"), method=method)
    if method == "block" and blocks is None:
        raise ValueError("method='block' needs blocks: one integer label per pixel")
    if method != "block" and blocks is not None:
        raise ValueError(f"blocks is used only by method='block'; got method={method!r}")
    if ceiling is not None:
        if method != "smart":
            raise ValueError(f"ceiling is used only by method='smart'; got method={method!r}")
        ceiling = np.asarray(ceiling, bool).reshape(-1)
        if ceiling.size != projector.n_pixels:
            raise ReconstructionError(f"ceiling has {ceiling.size} values; the projector "
                                      f"expects n_pixels = {projector.n_pixels}")
    return iterations, relaxation, pixel_threshold, ceiling


def _sweeps(projector, sweep, volume, iterations: int, callback, volume_shape) -> None:
    """Run ``iterations`` sweeps on ``volume`` in place, ``callback`` after each.

    A matrix-free projector keeps its projection buffer from sweep to sweep.
    """
    with getattr(projector, "reusing_buffers", contextlib.nullcontext)():
        for iteration in range(1, iterations + 1):
            sweep(volume)
            if callback is not None:
                view = _shaped(volume, volume_shape).view()
                view.flags.writeable = False
                callback(iteration, view)


def _sweep_of(method, projector, intensity, bright, relaxation, schedule, ceiling):
    """``sweep(volume)``: one iteration of ``method``, updating the float32 volume in place."""
    mu = np.float32(relaxation)
    if method == "smart":
        column_norm = np.maximum(np.asarray(projector.column_sums(), np.float32), 1.0)
        work = {"log_ratio": np.zeros(projector.n_pixels, np.float32),
                "projection": np.empty(projector.n_pixels, np.float32),
                "correction": np.empty(projector.n_voxels, np.float32)}
        return lambda volume: _smart_iteration(projector, intensity, bright, volume, relaxation,
                                               column_norm, work, ceiling)
    csr = (projector.indptr, projector.indices, projector.data, projector.row_index,
           projector.row_scale)
    if method == "mart":
        rows = projector.row_schedule()
        return lambda volume: _k.mart_sweep(*csr, rows.rows, rows.chunk_ptr, rows.group_ptr,
                                            intensity, bright, volume, mu)
    log_ratio = np.zeros(projector.n_pixels, np.float64)
    return lambda volume: _k.block_sweep(
        *csr, schedule.block_column_sums, schedule.rows, schedule.chunk_ptr,
        schedule.group_ptr, schedule.block_group_ptr, intensity, bright, volume, mu, log_ratio)


def _smart_iteration(projector, intensity, bright, volume, relaxation, column_norm, work,
                     ceiling=None):
    """Run one SMART iteration through the Projector protocol (forward, then back).

    Rows of ``ceiling`` only lower their voxels. ``work``: the float32 arrays
    ``log_ratio`` and ``projection`` (n_pixels) and ``correction`` (n_voxels), reused from
    sweep to sweep (a volume-sized array allocated afresh costs its page faults each time).
    """
    log_ratio, correction = work["log_ratio"], work["correction"]
    projection = projector.forward(volume, out=work["projection"])
    log_ratio[:] = 0.0
    update = bright & (projection > 0.0)
    log_ratio[update] = np.clip(np.log(intensity[update] / projection[update]),
                                -_k.LOG_RATIO_BOUND, _k.LOG_RATIO_BOUND)
    if ceiling is not None:
        np.clip(log_ratio, -CEILING_LOG_BOUND, 0.0, out=log_ratio, where=ceiling)
    projector.back(log_ratio, out=correction)
    correction *= np.float32(relaxation)
    correction /= column_norm
    np.exp(correction, out=correction)
    volume *= correction
    np.minimum(volume, _k.VOXEL_MAX, out=volume)


def _mlos(intensity, bright, projector) -> np.ndarray:
    """MLOS volume (float32) from a checked image; see :func:`mlos`."""
    row_sums = np.asarray(projector.row_sums())
    column_sums = np.asarray(projector.column_sums())
    seen_dark = _seen_by_dark(bright, projector)
    log_norm = np.zeros(projector.n_pixels, np.float32)
    use = bright & (row_sums > 0)
    log_norm[use] = np.log(intensity[use] / row_sums[use])
    mean_log = projector.back(log_norm)
    volume = np.zeros(projector.n_voxels, np.float32)
    keep = ~seen_dark & (column_sums > 0)
    volume[keep] = np.exp(mean_log[keep] / column_sums[keep])
    return volume


def _seen_by_dark(bright, projector) -> np.ndarray:
    """Boolean per voxel: some dark pixel has a positive weight on it.

    No back projection when every pixel is bright (nothing is dark).
    """
    if bright.all():
        return np.zeros(projector.n_voxels, bool)
    return np.asarray(projector.back((~bright).astype(np.float32))) > 0


def _check_not_empty(volume, pixel_threshold: float) -> None:
    """Refuse a first guess of its own making that the dark pixels emptied."""
    if not volume.any():
        raise ReconstructionError(
            f"every voxel a lit pixel sees is also seen by a dark pixel (I <= pixel_threshold "
            f"= {pixel_threshold:g} counts), so the line of sight leaves an empty volume: "
            "give the dark pixels as ceilings (method='smart', ceiling=, their intensity the "
            "noise floor) or use plenopiv.reconstruction.solve.solve_volume, which does")


def _first_guess(initial, intensity, bright, projector) -> np.ndarray:
    """Return the starting volume (float32, writeable), dark-seen and unseen voxels zeroed."""
    if isinstance(initial, str):
        if initial not in INITIAL_GUESSES:
            raise ValueError(
                f"initial must be one of {INITIAL_GUESSES} or an array of n_voxels values; "
                f"got {initial!r}"
            )
        if initial == "mlos":
            return _mlos(intensity, bright, projector)
        volume = np.ones(projector.n_voxels, np.float32)
    else:
        given = np.asarray(initial)
        if given.size != projector.n_voxels or not np.issubdtype(given.dtype, np.number):
            raise ReconstructionError(
                f"initial volume has {given.size} values of dtype {given.dtype}; the "
                f"projector expects n_voxels = {projector.n_voxels} numbers"
            )
        volume = np.array(given.reshape(-1), dtype=np.float32)
        if not np.all(np.isfinite(volume)) or volume.min() < 0:
            raise ReconstructionError("initial volume must be finite and >= 0")
    column_sums = np.asarray(projector.column_sums())
    volume[_seen_by_dark(bright, projector) | (column_sums <= 0)] = 0.0
    return volume


def _check_image(image, n_pixels: int, pixel_threshold: float) -> np.ndarray:
    """Flat contiguous float32 image, or an error naming what is wrong.

    A copy unless it is one already; the reconstruction only reads it.
    """
    a = np.asarray(image)
    if a.size != n_pixels:
        raise ReconstructionError(
            f"image has {a.size} pixels (shape {a.shape}); the projector expects "
            f"n_pixels = {n_pixels}"
        )
    if not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise ImageError(f"image must hold real numbers; got dtype {a.dtype}")
    a = np.ascontiguousarray(a.reshape(-1), dtype=np.float32)
    bad = ~np.isfinite(a)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ImageError(
            f"image has {int(bad.sum())} NaN or infinite pixels (first at flat index "
            f"{first}); intensities must be finite"
        )
    if a.min() < 0:
        raise ImageError(
            f"image has {int((a < 0).sum())} negative pixels (min {float(a.min()):g}); "
            "intensities must be >= 0 (subtract the background and clip at zero first)"
        )
    if not np.any(a > pixel_threshold):
        raise ImageError(
            f"no pixel is above pixel_threshold = {pixel_threshold:g} (image max "
            f"{float(a.max()):g}); nothing to reconstruct"
        )
    return a


def _check_projector(projector, *, need_rows: bool, method: str) -> None:
    if not isinstance(projector, Projector):
        raise ReconstructionError(
            f"projector must implement plenopiv.reconstruction.projector.Projector "
            f"(n_pixels, n_voxels, "
            f"forward, back, row_sums, column_sums); got {type(projector).__name__}"
        )
    if need_rows and not isinstance(projector, RowAccessProjector):
        raise ReconstructionError(
            f"method={method!r} walks the rows of W: the projector needs indptr, indices, "
            f"data, row_schedule and block_schedule (a RowAccessProjector such as "
            f"SparseProjector); {type(projector).__name__} has not; use method='smart'"
        )


def _check_shape(shape, n_voxels: int):
    if shape is None:
        return None
    try:
        dims = tuple(int(s) for s in shape)
    except TypeError as exc:
        raise ReconstructionError(f"shape must be (nz, ny, nx); got {shape!r}") from exc
    if len(dims) != 3 or any(d < 1 for d in dims) or math.prod(dims) != n_voxels:
        raise ReconstructionError(
            f"shape {shape!r} must be (nz, ny, nx) with nz*ny*nx = n_voxels = {n_voxels}"
        )
    return dims


def _check_int(value, name: str, *, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


def _check_float(value, name: str, *, positive: bool) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a number; got {value!r}") from exc
    if not math.isfinite(v) or (v <= 0 if positive else v < 0):
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{name} must be finite and {bound}; got {value!r}")
    return v


def _shaped(volume: np.ndarray, shape):
    return volume if shape is None else volume.reshape(shape)
