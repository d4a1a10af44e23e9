"""Numba kernels of the voxel-pixel weight builder (see :mod:`plenopiv.reconstruction.weights`).

The beam of a pixel crosses depth Z as the set X = (1 - t) u' + t X_f' with t = (S_o + Z)/S_o,
u' uniform on the aperture cell (width a) and X_f' uniform on the lenslet footprint (width b).
Per axis its density is the convolution of two boxes of widths α = |1 - t| a and β = t b, a
trapezoid whose cumulative distribution is piecewise quadratic (:func:`box_sum_cdf`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _r2(y):
    return y * y if y > 0.0 else 0.0


@njit(cache=True)
def box_sum_cdf(x, centre, alpha, beta):
    """CDF at x of the sum of two independent uniforms of widths alpha, beta (any order).

    The sum is centred at ``centre``.
    """
    lo, hi = (alpha, beta) if alpha <= beta else (beta, alpha)
    if lo <= 1e-9 * hi:                     # one box is a point: a plain uniform
        v = (x - centre) / hi + 0.5
        return 0.0 if v < 0.0 else (1.0 if v > 1.0 else v)
    p1 = centre - 0.5 * (lo + hi)
    p2 = centre - 0.5 * (hi - lo)
    p3 = centre + 0.5 * (hi - lo)
    p4 = centre + 0.5 * (lo + hi)
    return (_r2(x - p1) - _r2(x - p2) - _r2(x - p3) + _r2(x - p4)) / (2.0 * lo * hi)


def box_sum_cdf_numpy(x, centre, alpha, beta):
    """Plain-NumPy twin of :func:`box_sum_cdf` (by numerical convolution); ``x`` may be an array."""
    lo, hi = sorted((alpha, beta))
    if lo <= 1e-9 * hi:
        return np.clip((x - centre) / hi + 0.5, 0, 1)
    # the density is a trapezoid; integrate it with a fine trapezoid rule
    grid = np.linspace(centre - (lo + hi) / 2, centre + (lo + hi) / 2, 20001)
    dens = np.clip(np.minimum(grid - grid[0], grid[-1] - grid) / lo, 0, 1) / hi
    cum = np.concatenate([[0], np.cumsum((dens[1:] + dens[:-1]) / 2 * np.diff(grid))])
    return np.interp(x, grid, cum, left=0.0, right=1.0)


@njit(cache=True)
def _axis_range(m, half, origin, vox, n):
    """First and last voxel index along an axis overlapping [m - half, m + half]."""
    i0 = int(math.floor((m - half - origin) / vox + 0.5))
    i1 = int(math.floor((m + half - origin) / vox + 0.5))
    if i0 < 0:
        i0 = 0
    if i1 > n - 1:
        i1 = n - 1
    return i0, i1


@njit(cache=True)
def _row(i, ux, uy, xfx, xfy, lit, so, a, b, area, zs, ox, oy, vx, vy, nx, ny, min_w,
         out_idx, out_w, fill):
    """Weights of pixel i; counts them (fill=False) or writes them (fill=True)."""
    count = 0
    for iz in range(zs.shape[0]):
        t = (so + zs[iz]) / so
        al = abs(1.0 - t) * a
        be = t * b
        half = 0.5 * (al + be)
        mx = (1.0 - t) * ux[i] + t * xfx[i]
        my = (1.0 - t) * uy[i] + t * xfy[i]
        ix0, ix1 = _axis_range(mx, half, ox, vx, nx)
        iy0, iy1 = _axis_range(my, half, oy, vy, ny)
        if ix1 < ix0 or iy1 < iy0:
            continue
        scale = lit[i] * (a * be) * (a * be) / (area * vx * vy)
        for iy in range(iy0, iy1 + 1):
            yl = oy + (iy - 0.5) * vy
            fy = box_sum_cdf(yl + vy, my, al, be) - box_sum_cdf(yl, my, al, be)
            if fy <= 0.0:
                continue
            for ix in range(ix0, ix1 + 1):
                xl = ox + (ix - 0.5) * vx
                fx = box_sum_cdf(xl + vx, mx, al, be) - box_sum_cdf(xl, mx, al, be)
                w = scale * fx * fy
                if w <= min_w:
                    continue
                if fill:
                    out_idx[count] = (iz * ny + iy) * nx + ix
                    out_w[count] = w
                count += 1
    return count


@njit(parallel=True, cache=True)
def weight_rows(ux, uy, xfx, xfy, lit, so, a, b, area, zs, ox, oy, vx, vy, nx, ny, min_w,
                indptr, indices, data, fill):
    """Count (``fill`` False) or write (``fill`` True) the weights of every pixel row.

    Returns the non-zeros of every row (int64, (n,)). Writing, row i goes to
    ``indices[indptr[i]:indptr[i + 1]]`` and ``data[...]``; counting, ``indptr`` is zeros and
    nothing is written. One kernel for both passes: it compiles once (a parallel loop is slow
    to compile), with one variant of :func:`_row`.
    """
    n = ux.shape[0]
    counts = np.zeros(n, np.int64)
    for i in prange(n):
        s, e = indptr[i], indptr[i + 1]
        # np.int64: the parallel loop's index is unsigned; one type compiles _row once
        counts[i] = _row(np.int64(i), ux, uy, xfx, xfy, lit, so, a, b, area, zs, ox, oy, vx,
                         vy, nx, ny, min_w, indices[s:e], data[s:e], fill)
    return counts


def count_nnz(ux, uy, xfx, xfy, lit, so, a, b, area, zs, ox, oy, vx, vy, nx, ny, min_w):
    """Non-zeros of every pixel row (int64, (n,))."""
    return weight_rows(ux, uy, xfx, xfy, lit, so, a, b, area, zs, ox, oy, vx, vy, nx, ny,
                       min_w, np.zeros(ux.shape[0] + 1, np.int64), np.zeros(0, np.int32),
                       np.zeros(0, np.float32), False)


def fill_rows(indptr, ux, uy, xfx, xfy, lit, so, a, b, area, zs, ox, oy, vx, vy, nx, ny, min_w,
              indices, data):
    """Write every pixel row into the CSR arrays (``indptr`` from :func:`count_nnz`)."""
    weight_rows(ux, uy, xfx, xfy, lit, so, a, b, area, zs, ox, oy, vx, vy, nx, ny, min_w,
                indptr, indices, data, True)
