"""Kernel of the correlation statistics: peak neighbours and their asymmetry variance.

``peak_statistics``, for window pairs at given start voxels and their integer correlation
peak, builds the peak value and its two neighbours along each axis from the products of the
two windows' intensities, and the variance of the asymmetry of those neighbours (the
correlation statistics of Wieneke 2015, in 3-D, with the covariance of neighbouring voxels'
contributions). See docs/methods.md#per-vector-uncertainty.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from plenopiv.piv._kernels.spectra import extract_windows_numpy


@numba.njit(cache=True)
def _box_sum_circular(x, axis, half, out):
    """Circular running sum of ``x`` over ``2 half + 1`` elements along ``axis`` (0, 1 or 2)."""
    n0, n1, n2 = x.shape
    shape = (n0, n1, n2)
    length = shape[axis]
    if axis == 0:
        for j in range(n1):
            for m in range(n2):
                s = 0.0
                for q in range(-half, half + 1):
                    s += x[q % length, j, m]
                for i in range(length):
                    out[i, j, m] = s
                    s += x[(i + half + 1) % length, j, m] - x[(i - half) % length, j, m]
    elif axis == 1:
        for i in range(n0):
            for m in range(n2):
                s = 0.0
                for q in range(-half, half + 1):
                    s += x[i, q % length, m]
                for j in range(length):
                    out[i, j, m] = s
                    s += x[i, (j + half + 1) % length, m] - x[i, (j - half) % length, m]
    else:
        for i in range(n0):
            for j in range(n1):
                s = 0.0
                for q in range(-half, half + 1):
                    s += x[i, j, q % length]
                for m in range(length):
                    out[i, j, m] = s
                    s += x[i, j, (m + half + 1) % length] - x[i, j, (m - half) % length]


@numba.njit(cache=True)
def peak_statistics(volume_a, volume_b, starts_a, starts_b, wz, wy, wx, peak, block):
    n = starts_a.shape[0]
    nz, ny, nx = volume_a.shape
    out = np.full((n, 10), np.nan)
    hz = min((block[0] - 1) // 2, (wz - 1) // 2)
    hy = min((block[1] - 1) // 2, (wy - 1) // 2)
    hx = min((block[2] - 1) // 2, (wx - 1) // 2)
    box = (2 * hz + 1) * (2 * hy + 1) * (2 * hx + 1)
    size = wz * wy * wx
    for k in range(n):
        a = np.zeros((wz, wy, wx))
        b = np.zeros((wz, wy, wx))
        for i in range(wz):
            za = starts_a[k, 0] + i
            zb = starts_b[k, 0] + i
            for j in range(wy):
                ya = starts_a[k, 1] + j
                yb = starts_b[k, 1] + j
                for m in range(wx):
                    xa = starts_a[k, 2] + m
                    xb = starts_b[k, 2] + m
                    if 0 <= za < nz and 0 <= ya < ny and 0 <= xa < nx:
                        a[i, j, m] = volume_a[za, ya, xa]
                    if 0 <= zb < nz and 0 <= yb < ny and 0 <= xb < nx:
                        b[i, j, m] = volume_b[zb, yb, xb]
        a -= a.mean()
        b -= b.mean()
        sz = peak[k, 0]
        sy = peak[k, 1]
        sx = peak[k, 2]
        d = np.empty((3, wz, wy, wx))
        c0 = 0.0
        cp = np.zeros(3)
        cm = np.zeros(3)
        for i in range(wz):
            bi = (i + sz) % wz
            for j in range(wy):
                bj = (j + sy) % wy
                for m in range(wx):
                    bm = (m + sx) % wx
                    av = a[i, j, m]
                    bv = b[bi, bj, bm]
                    c0 += av * bv
                    p = av * b[(bi + 1) % wz, bj, bm]
                    q = a[(i + 1) % wz, j, m] * bv
                    cp[0] += p
                    cm[0] += q
                    d[0, i, j, m] = p - q
                    p = av * b[bi, (bj + 1) % wy, bm]
                    q = a[i, (j + 1) % wy, m] * bv
                    cp[1] += p
                    cm[1] += q
                    d[1, i, j, m] = p - q
                    p = av * b[bi, bj, (bm + 1) % wx]
                    q = a[i, j, (m + 1) % wx] * bv
                    cp[2] += p
                    cm[2] += q
                    d[2, i, j, m] = p - q
        out[k, 0] = c0
        tmp = np.empty((wz, wy, wx))
        tmp2 = np.empty((wz, wy, wx))
        for ax in range(3):
            out[k, 1 + 2 * ax] = cp[ax]
            out[k, 2 + 2 * ax] = cm[ax]
            dx = d[ax]
            dx -= (cp[ax] - cm[ax]) / size
            # axis and half as run-time values: one compiled variant of the box sum, not
            # one per literal axis
            for axis in range(3):
                half = hz if axis == 0 else (hy if axis == 1 else hx)
                src = dx if axis == 0 else (tmp if axis == 1 else tmp2)
                _box_sum_circular(src, axis, half, tmp2 if axis == 1 else tmp)
            acc = 0.0
            for i in range(wz):
                for j in range(wy):
                    for m in range(wx):
                        acc += tmp[i, j, m] * tmp[i, j, m]
            out[k, 7 + ax] = acc / box
    return out


def peak_statistics_numpy(volume_a, volume_b, starts_a, starts_b, wz, wy, wx, peak, block):
    import scipy.ndimage

    n = starts_a.shape[0]
    a = extract_windows_numpy(volume_a, starts_a, wz, wy, wx).astype(np.float64)
    b = extract_windows_numpy(volume_b, starts_b, wz, wy, wx).astype(np.float64)
    a -= a.mean(axis=(1, 2, 3), keepdims=True)
    b -= b.mean(axis=(1, 2, 3), keepdims=True)
    window = (wz, wy, wx)
    k = np.arange(n)[:, None, None, None]
    idx = [(np.arange(w)[None, :] + peak[:, q, None]) % w for q, w in enumerate(window)]
    b0 = b[k, idx[0][:, :, None, None], idx[1][:, None, :, None], idx[2][:, None, None, :]]
    out = np.empty((n, 10))
    out[:, 0] = (a * b0).sum(axis=(1, 2, 3))
    half = [min((int(block[q]) - 1) // 2, (window[q] - 1) // 2) for q in range(3)]
    size = tuple(2 * h + 1 for h in half)
    for ax in range(3):
        bp = np.roll(b0, -1, axis=ax + 1)  # b(x + s + e)
        ap = np.roll(a, -1, axis=ax + 1)  # a(x + e)
        p = a * bp
        q = ap * b0
        out[:, 1 + 2 * ax] = p.sum(axis=(1, 2, 3))
        out[:, 2 + 2 * ax] = q.sum(axis=(1, 2, 3))
        d = p - q
        d -= d.mean(axis=(1, 2, 3), keepdims=True)
        sums = scipy.ndimage.uniform_filter(d, size=(1,) + size, mode="wrap") * math.prod(size)
        out[:, 7 + ax] = (sums**2).sum(axis=(1, 2, 3)) / math.prod(size)
    return out
