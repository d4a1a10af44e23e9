"""Per-vector uncertainty of a correlation by correlation statistics (Wieneke 2015, in 3-D).

Uncertainties are voxels in the volume's index order ``(z, y, x)``; the method is described in
:mod:`plenopiv.piv.multipass` (*Uncertainty*).
"""

from __future__ import annotations

import math

import numpy as np

from plenopiv.piv.outliers import _extrapolated_neighbours

#: Below this many window voxels (windows × voxels per window) of the last pass, the
#: correlation statistics use the plain-NumPy twin of their kernel even with
#: ``engine="numba"``: on a small field compiling the numba kernel on a first run costs more
#: than it saves, and the twin's arrays (about ten float64 arrays of this many values) stay
#: under 200 MB. The two give the same statistics (tests).
NUMPY_STATISTICS_MAX_VOXELS = 2**21


def _statistics_kernel(kernels, n_windows: int, window) -> object:
    """Choose the ``peak_statistics`` kernel for ``n_windows`` windows of shape ``window``.

    The NumPy twin when they hold at most ``NUMPY_STATISTICS_MAX_VOXELS`` voxels, else the
    engine's own.
    """
    from plenopiv.piv._kernels import ENGINES

    if n_windows * math.prod(window) <= NUMPY_STATISTICS_MAX_VOXELS:
        return ENGINES["numpy"].peak_statistics
    return kernels.peak_statistics


def particle_image_size(volume):
    r"""Standard deviation of the particle images of a volume per axis, voxels ``(z, y, x)``.

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


def _correlation_uncertainty(vol_a, vol_b, shift, measured, layout, settings, kernels):
    """Standard uncertainty (3, nz, ny, nx) in voxels ``(z, y, x)`` by correlation statistics.

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
    """Uncertainty of the final field: rejected vectors get their neighbours', NaN if no vector.

    See *Uncertainty* in :mod:`plenopiv.piv.multipass`.
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
