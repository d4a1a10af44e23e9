"""One correlation pass: staged FFTs of every window pair, cross spectrum and peak fit.

Displacements are voxels in the volume's index order ``(z, y, x)``.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft

_CHUNK_BYTES = 4 * 2**20
"""Float32 window bytes correlated at once (small enough to stay in cache)."""

_SLAB_BYTES = 64 * 2**20
"""Bytes of partial (x, y) spectra held per volume while a slab of window rows is transformed."""

_MIN_ENERGY_FRACTION = 1e-6
"""A window whose energy about its mean is below this fraction of its total energy is empty."""

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


def _peak_refinement(settings):
    """``(overlap, broad)`` for the ``refine_peaks`` kernel, or None for the plain fit."""
    if not (settings.overlap_correction or settings.broad_peaks):
        return None
    return bool(settings.overlap_correction), bool(settings.broad_peaks)


def _correlate_pass(volume_a, volume_b, layout, *, shift, gaussian, workers, kernels,
                    refine=None):
    """Correlate every window pair of one pass.

    Returns the displacement (n, 3) in voxels ``(z, y, x)`` (NaN for windows without
    intensity variation), the peak height as a correlation coefficient and the peak ratio.
    ``refine``: ``(overlap, broad)`` of :func:`_peak_refinement`, or None.
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
        if refine is not None:
            d = kernels.refine_peaks(corr, gaussian, *refine)
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
