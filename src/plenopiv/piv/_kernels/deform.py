"""Kernels that sample a volume at positions moved by a displacement field.

``deform_trilinear`` samples a volume at ``x + factor * d(x)`` by trilinear interpolation
(zero outside); ``deform_cubic`` samples a cubic B-spline, given by its coefficients on a
zero-padded grid, at ``x + factor * d(x)``. See docs/methods.md#window-deformation.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, parallel=True)
def deform_trilinear(volume, field, factor):
    nz, ny, nx = volume.shape
    out = np.empty_like(volume)
    for i in numba.prange(nz):
        for j in range(ny):
            for m in range(nx):
                pz = i + factor * field[0, i, j, m]
                py = j + factor * field[1, i, j, m]
                px = m + factor * field[2, i, j, m]
                z0 = math.floor(pz)
                y0 = math.floor(py)
                x0 = math.floor(px)
                tz = pz - z0
                ty = py - y0
                tx = px - x0
                acc = 0.0
                for a in range(2):
                    zz = z0 + a
                    if zz < 0 or zz >= nz:
                        continue
                    wa = tz if a == 1 else 1.0 - tz
                    for b in range(2):
                        yy = y0 + b
                        if yy < 0 or yy >= ny:
                            continue
                        wb = ty if b == 1 else 1.0 - ty
                        for c in range(2):
                            xx = x0 + c
                            if xx < 0 or xx >= nx:
                                continue
                            wc = tx if c == 1 else 1.0 - tx
                            acc += wa * wb * wc * volume[zz, yy, xx]
                out[i, j, m] = acc
    return out


def deform_trilinear_numpy(volume, field, factor):
    nz, ny, nx = volume.shape
    grid = np.indices(volume.shape, dtype=np.float64)
    pos = grid + factor * field.astype(np.float64)
    base = np.floor(pos).astype(np.int64)
    frac = pos - base
    out = np.zeros(volume.shape, dtype=np.float64)
    for a in (0, 1):
        for b in (0, 1):
            for c in (0, 1):
                zz, yy, xx = base[0] + a, base[1] + b, base[2] + c
                weight = (
                    (frac[0] if a else 1.0 - frac[0])
                    * (frac[1] if b else 1.0 - frac[1])
                    * (frac[2] if c else 1.0 - frac[2])
                )
                inside = (zz >= 0) & (zz < nz) & (yy >= 0) & (yy < ny) & (xx >= 0) & (xx < nx)
                values = volume[
                    np.clip(zz, 0, nz - 1), np.clip(yy, 0, ny - 1), np.clip(xx, 0, nx - 1)
                ]
                out += np.where(inside, weight * values, 0.0)
    return out.astype(volume.dtype)


@numba.njit(cache=True, inline="always")
def _bspline3_weights(t, out):
    s = 1.0 - t
    out[0] = s * s * s / 6.0
    out[1] = 2.0 / 3.0 - t * t + 0.5 * t * t * t
    out[2] = 2.0 / 3.0 - s * s + 0.5 * s * s * s
    out[3] = t * t * t / 6.0


@numba.njit(cache=True)
def deform_cubic(coeffs, field, factor, pad):
    _, nz, ny, nx = field.shape
    cz, cy, cx = coeffs.shape
    out = np.empty((nz, ny, nx), dtype=np.float32)
    for i in range(nz):
        wz = np.empty(4)
        wy = np.empty(4)
        wx = np.empty(4)
        for j in range(ny):
            for m in range(nx):
                pz = i + pad + factor * field[0, i, j, m]
                py = j + pad + factor * field[1, i, j, m]
                px = m + pad + factor * field[2, i, j, m]
                z0 = math.floor(pz)
                y0 = math.floor(py)
                x0 = math.floor(px)
                _bspline3_weights(pz - z0, wz)
                _bspline3_weights(py - y0, wy)
                _bspline3_weights(px - x0, wx)
                acc = 0.0
                for a in range(4):
                    zz = z0 - 1 + a
                    if zz < 0 or zz >= cz:
                        continue
                    for b in range(4):
                        yy = y0 - 1 + b
                        if yy < 0 or yy >= cy:
                            continue
                        row = 0.0
                        for c in range(4):
                            xx = x0 - 1 + c
                            if 0 <= xx < cx:
                                row += wx[c] * coeffs[zz, yy, xx]
                        acc += wz[a] * wy[b] * row
                out[i, j, m] = acc
    return out


def _bspline3_numpy(t):
    t = np.abs(t)
    return np.where(
        t < 1.0, 2.0 / 3.0 - t**2 + 0.5 * t**3, np.where(t < 2.0, (2.0 - t) ** 3 / 6.0, 0.0)
    )


def deform_cubic_numpy(coeffs, field, factor, pad):
    shape = field.shape[1:]
    pos = np.indices(shape, dtype=np.float64) + pad + factor * field.astype(np.float64)
    base = np.floor(pos).astype(np.int64)
    out = np.zeros(shape, dtype=np.float64)
    limits = coeffs.shape
    for a in range(-1, 3):
        for b in range(-1, 3):
            for c in range(-1, 3):
                idx = (base[0] + a, base[1] + b, base[2] + c)
                inside = np.ones(shape, dtype=bool)
                for q in range(3):
                    inside &= (idx[q] >= 0) & (idx[q] < limits[q])
                values = coeffs[tuple(np.clip(idx[q], 0, limits[q] - 1) for q in range(3))]
                weight = (
                    _bspline3_numpy(pos[0] - idx[0])
                    * _bspline3_numpy(pos[1] - idx[1])
                    * _bspline3_numpy(pos[2] - idx[2])
                )
                out += np.where(inside, weight * values, 0.0)
    return out.astype(np.float32)
