"""Numba kernels of the lattice (matrix-free) projector of :mod:`plenopiv.reconstruction.lattice`.

With an axis-aligned square lattice a pixel's weights on depth slice k are the outer product
of a column profile and a row profile, ``W[(row, col), (k, iy, ix)] = scale(row, col) ·
wy[k, row, iy] · wx[k, col, ix]``, tables of the voxel-integrated trapezoid of
:mod:`plenopiv.reconstruction._kernels.weights`. The forward projection contracts x first
(``T[k, iy, col]``), then y, slice after slice; the back projection is the same in reverse.
Nothing of size (pixels × voxels) is held. See docs/methods.md#projectors.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from plenopiv.reconstruction._kernels.weights import _axis_range, box_sum_cdf


def row_blocks(n_rows: int, block: int) -> int:
    """Blocks of ``block`` sensor rows :func:`contract_y` runs over."""
    return (n_rows + block - 1) // block


@njit(cache=True)
def axis_tables(u, xf, valid, t, al, be, half, origin, vox, n, kmax, start, count, w):
    """1-D beam profiles of every sensor line (column or row) on every slice.

    ``u``, ``xf``: the line's aperture and focal-plane coordinates (metres); ``valid``: lines
    that hold rays. Writes the first voxel ``start[k, p]``, the number of voxels
    ``count[k, p]`` and their overlaps ``w[k, p, :count]`` (fractions of the beam's profile).
    Returns the largest count met (the caller checks it against ``kmax``).
    """
    nz = t.shape[0]
    npx = u.shape[0]
    worst = np.zeros(nz, np.int64)
    for k in range(nz):
        tk = t[k]
        for p in range(npx):
            start[k, p] = 0
            count[k, p] = 0
            if not valid[p]:
                continue
            m = (1.0 - tk) * u[p] + tk * xf[p]
            i0, i1 = _axis_range(m, half[k], origin, vox, n)
            c = i1 - i0 + 1
            if c <= 0:
                continue
            if c > worst[k]:
                worst[k] = c
            if c > kmax:
                c = kmax
            start[k, p] = i0
            count[k, p] = c
            edge = origin + (i0 - 0.5) * vox
            prev = box_sum_cdf(edge, m, al[k], be[k])
            for j in range(c):
                cur = box_sum_cdf(edge + (j + 1) * vox, m, al[k], be[k])
                v = cur - prev
                w[k, p, j] = v if v > 0.0 else 0.0
                prev = cur
    return worst.max()


@njit(nogil=True, cache=True)
def contract_x(volume, xs, xc, xw, out, lo, hi):
    """``out[k, iy, col] = sum_ix wx[k, col, ix] volume[k, iy, ix]`` (forward, first half).

    For the voxel rows ``lo <= k * ny + iy < hi`` (of ``nz * ny``).
    """
    _, ny, _ = volume.shape
    ncol = xs.shape[1]
    for q in range(lo, hi):
        k = q // ny
        iy = q % ny
        row = volume[k, iy]
        dst = out[k, iy]
        for c in range(ncol):
            acc = np.float32(0.0)
            s = xs[k, c]
            for j in range(xc[k, c]):
                acc += xw[k, c, j] * row[s + j]
            dst[c] = acc


@njit(nogil=True, cache=True)
def contract_y(tmp, ys, yc, yw, row_ptr, ray_col, ray_scale, block, out, lo, hi):
    """Forward, second half: sum the slices' row profiles into each pixel row.

    Then read the rays of the row (``row_ptr``: rays of sensor row r are
    ``row_ptr[r]:row_ptr[r + 1]``). For the blocks ``lo <= b < hi`` of ``block`` sensor rows
    (:func:`row_blocks` of them in all).
    """
    nz, _, ncol = tmp.shape
    nrow = ys.shape[1]
    for b in range(lo, hi):
        r0 = b * block
        r1 = min(nrow, r0 + block)
        if row_ptr[r1] == row_ptr[r0]:
            continue
        acc = np.zeros((r1 - r0, ncol), np.float32)
        for k in range(nz):
            for r in range(r0, r1):
                if row_ptr[r + 1] == row_ptr[r]:
                    continue
                a = acc[r - r0]
                s = ys[k, r]
                for j in range(yc[k, r]):
                    w = yw[k, r, j]
                    src = tmp[k, s + j]
                    for c in range(ncol):
                        a[c] += w * src[c]
        for r in range(r0, r1):
            for i in range(row_ptr[r], row_ptr[r + 1]):
                out[i] = acc[r - r0, ray_col[i]] * ray_scale[i]


@njit(nogil=True, cache=True)
def spread_y(image, row_used, ptr, t_row, t_w, out, lo, hi):
    """Back projection, first half: ``out[k, iy, col] = sum_r wy[k, r, iy] image[r, col]``.

    ``ptr``, ``t_row``, ``t_w``: the row profiles transposed, the sensor rows (and weights)
    that reach voxel row iy on slice k being ``ptr[iy * nz + k]:ptr[iy * nz + k + 1]``.
    For the voxel rows ``lo <= iy < hi``; parallel over voxel rows, slices inside: the band
    of image rows that reaches one voxel row stays in cache from slice to slice, and no two
    threads write the same element.
    """
    nz, _, ncol = out.shape
    for iy in range(lo, hi):
        for k in range(nz):
            dst = out[k, iy]
            for c in range(ncol):
                dst[c] = 0.0
            q = iy * nz + k
            for e in range(ptr[q], ptr[q + 1]):
                r = t_row[e]
                if not row_used[r]:
                    continue
                w = t_w[e]
                src = image[r]
                for c in range(ncol):
                    dst[c] += w * src[c]


@njit(nogil=True, cache=True)
def spread_x(tmp, xs, xc, xw, out, lo, hi):
    """Back projection, second half: ``out[k, iy, ix] = sum_col wx[k, col, ix] tmp[k, iy, col]``.

    For the voxel rows ``lo <= k * ny + iy < hi`` (of ``nz * ny``).
    """
    _, ny, nx = out.shape
    ncol = xs.shape[1]
    for q in range(lo, hi):
        k = q // ny
        iy = q % ny
        dst = out[k, iy]
        for ix in range(nx):
            dst[ix] = 0.0
        src = tmp[k, iy]
        for c in range(ncol):
            v = src[c]
            if v == 0.0:
                continue
            s = xs[k, c]
            for j in range(xc[k, c]):
                dst[s + j] += xw[k, c, j] * v


@njit(nogil=True, cache=True)
def row_max(ray_row, ray_col, ray_scale, col_max, row_max_, out, lo, hi):
    """Largest weight of every ray: ``scale · max_k col_max[col, k] · row_max_[row, k]``.

    ``col_max``, ``row_max_``: the profiles' largest values per line and slice, slices
    contiguous. For the rays ``lo <= i < hi``.
    """
    nz = col_max.shape[1]
    for i in range(lo, hi):
        a = col_max[ray_col[i]]
        b = row_max_[ray_row[i]]
        best = np.float32(0.0)
        for k in range(nz):
            v = a[k] * b[k]
            if v > best:
                best = v
        out[i] = best * ray_scale[i]
