"""Numba kernel of the recording model: the optical gain of every pixel. See :mod:`.sensor`.

A pixel belongs to the lenslet whose micro-image it lies in: the lenslet at ``x / scale`` on
the lenslet plane, ``scale`` being the paraxial ratio of a micro-image centre to its lenslet
centre (the lattice of micro-images is the lenslet lattice magnified by ``scale``). Its gain
is that lenslet's throughput times the fall-off ``(1 + a ρ²)^-2`` (cos⁴ of an angle whose
tangent grows as ρ), ρ being the pixel's distance from the lenslet's centre of vignetting
(its micro-image's centre, or its axis) over ``rim``. A pixel under no lenslet keeps a gain
of 1.

:func:`optical_gain_numpy` is the plain-NumPy twin (brute-force lenslet search: small
sensors only).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from plenopiv.synthetic._kernels import G_NCOLS, G_NROWS, G_PIX, lenslet_at, lenslet_at_numpy


@njit(nogil=True, cache=True, error_model="numpy")
def optical_gain(g, scale, shift_row, shift_col, throughput, centres, a, rim, out, lo, hi):
    """Fill rows ``lo <= r < hi`` of ``out`` with each pixel's optical gain.

    Parameters
    ----------
    g : float64 vector
        The tracer's geometry vector (:func:`plenopiv.synthetic.tracer.geometry_vector`).
    scale : float
        Micro-image centre over lenslet centre, both from the optical axis (paraxial).
    shift_row, shift_col : float
        The image content moves by this many pixels (the sensor shift of the render).
    throughput : (N,) float64
        Throughput factor of each lenslet (row-major lenslet index).
    centres : (N, 2) float64
        Centre ``(x, y)`` of each lenslet's fall-off on the sensor, metres.
    a : float
        Fall-off coefficient: the gain at ρ is ``(1 + a ρ²)^-2``.
    rim : float
        Where ρ = 1, metres from the centre.
    out : (rows, cols) float64
    lo, hi : int
        The rows this call fills.
    """
    pix = g[G_PIX]
    n_rows, n_cols = int(g[G_NROWS]), int(g[G_NCOLS])
    inv_rim2 = 1.0 / (rim * rim)
    for r in range(lo, hi):
        y = (r - shift_row - (n_rows - 1) * 0.5) * pix
        for c in range(n_cols):
            x = (c - shift_col - (n_cols - 1) * 0.5) * pix
            k, _, _ = lenslet_at(x / scale, y / scale, g)
            if k < 0:
                out[r, c] = 1.0
                continue
            rho2 = ((x - centres[k, 0]) ** 2 + (y - centres[k, 1]) ** 2) * inv_rim2
            q = 1.0 + a * rho2
            out[r, c] = throughput[k] / (q * q)


def optical_gain_numpy(g, scale, shift_row, shift_col, throughput, centres, a, rim):
    """NumPy twin of :func:`optical_gain`: the whole map, (rows, cols) float64."""
    pix = g[G_PIX]
    n_rows, n_cols = int(g[G_NROWS]), int(g[G_NCOLS])
    out = np.empty((n_rows, n_cols))
    x = (np.arange(n_cols) - shift_col - (n_cols - 1) * 0.5) * pix
    for r in range(n_rows):
        y = np.full(n_cols, (r - shift_row - (n_rows - 1) * 0.5) * pix)
        k, _, _ = lenslet_at_numpy(x / scale, y / scale, g)
        c = np.asarray(centres)[np.maximum(k, 0)]
        rho2 = ((x - c[:, 0]) ** 2 + (y - c[:, 1]) ** 2) / (rim * rim)
        gain = np.asarray(throughput)[np.maximum(k, 0)] / (1.0 + a * rho2) ** 2
        out[r] = np.where(k >= 0, gain, 1.0)
    return out
