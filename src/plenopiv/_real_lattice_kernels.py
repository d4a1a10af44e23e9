"""Numba kernels of the per-lenslet matrix-free projector (see :mod:`plenopiv.real_lattice`).

Within one lenslet every ray has the same focal-plane position X_f and an aperture position
``u = -(pixel - spot) · cell`` whose x depends only on the pixel's column and y only on its
row, whatever the lattice's rotation, packing or per-lens jitter. On depth slice k the
lenslet's weights are therefore an outer product:

    W[(r, c), (k, iy, ix)] = scale(r, c) · f_k · wy[k, r, iy] · wx[k, c, ix]

with the per-axis voxel overlaps of the trapezoid beam profile
(:func:`plenopiv._weights_kernels.box_sum_cdf`, the explicit weights' own factors) and
``f_k = (a β_k)² / (A Δx Δy)``. The profiles are computed on the fly, per lenslet, slice and
micro-image line, into small per-thread buffers; nothing of size (pixels × voxels) is stored.

Forward: per lenslet (in parallel), per slice, contract x over the lenslet's voxel patch
(``T[iy, c]``), then y into the lenslet's local image. Back: per slice (in parallel, so no
two threads write one voxel), per lenslet, the same two contractions in reverse.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from plenopiv._weights_kernels import _axis_range


@njit(cache=True, inline="always")
def _cdf(y, shape):
    """Return :func:`plenopiv._weights_kernels.box_sum_cdf` at ``y`` = x - centre.

    ``shape``: the slice's constants (p1, p2, p3, p4, 1 / (2 lo hi), uniform, 1 / hi) from
    :func:`cdf_shapes`, so that no division or sorting is left per evaluation.
    """
    if shape[5] > 0.0:                      # one box is a point: a plain uniform
        v = y * shape[6] + 0.5
        return 0.0 if v < 0.0 else (1.0 if v > 1.0 else v)
    a = max(y - shape[0], 0.0)
    b = max(y - shape[1], 0.0)
    c = max(y - shape[2], 0.0)
    d = max(y - shape[3], 0.0)
    return (a * a - b * b - c * c + d * d) * shape[4]


def cdf_shapes(al, be):
    """Return the per-slice constants of :func:`_cdf`, shape (slices, 7).

    For box widths ``al``, ``be`` (metres, arrays): the trapezoid's corners relative to its
    centre, 1 / (2 lo hi), whether one box is a point (lo <= 1e-9 hi, as in
    ``box_sum_cdf``) and 1 / hi.
    """
    lo = np.minimum(al, be)
    hi = np.maximum(al, be)
    uniform = lo <= 1e-9 * hi
    safe = np.where(uniform, 1.0, lo)
    return np.ascontiguousarray(np.stack(
        [-0.5 * (lo + hi), -0.5 * (hi - lo), 0.5 * (hi - lo), 0.5 * (lo + hi),
         1.0 / (2.0 * safe * hi), uniform.astype(np.float64), 1.0 / hi], axis=1))


@njit(cache=True)
def _profiles(u_line, n_line, xf, tk, shape, half, origin, vox, n_vox, start, count, w):
    """Voxel overlaps of the lines' beams on one slice, along one axis.

    ``u_line[:n_line]``: the lines' aperture coordinates (metres); ``xf``: the lenslet's
    focal-plane coordinate (metres); ``shape``: the slice's :func:`cdf_shapes` row. Writes
    ``start``, ``count``, ``w[:, :count]`` per line; returns the first and one past the last
    voxel any line reaches (``lo >= hi`` if none).
    """
    lo = n_vox
    hi = 0
    kmax = w.shape[1]
    for p in range(n_line):
        m = (1.0 - tk) * u_line[p] + tk * xf
        i0, i1 = _axis_range(m, half, origin, vox, n_vox)
        c = i1 - i0 + 1
        if c <= 0:
            count[p] = 0
            start[p] = 0
            continue
        if c > kmax:
            c = kmax
        start[p] = i0
        count[p] = c
        if i0 < lo:
            lo = i0
        if i0 + c > hi:
            hi = i0 + c
        y = origin + (i0 - 0.5) * vox - m
        prev = _cdf(y, shape)
        for j in range(c):
            cur = _cdf(y + (j + 1) * vox, shape)
            v = cur - prev
            w[p, j] = v if v > 0.0 else 0.0
            prev = cur
    return lo, hi


@njit(parallel=True, cache=True)
def forward(volume, t, shape, half, slice_factor, ox, oy, vx, vy, u_col, u_row, n_col, n_row,
            xf_x, xf_y, ray_ptr, ray_r, ray_c, ray_scale, ray_pos, kmax, out):
    """``out[ray_pos[i]] = scale_i · sum_k f_k sum_iy wy sum_ix wx volume[k, iy, ix]``.

    Parallel over lenslets (each writes only its own rays). ``u_col[L, :n_col[L]]`` and
    ``u_row[L, :n_row[L]]``: aperture coordinates of lenslet L's micro-image columns and rows
    (metres); ``ray_ptr``: lenslet L's rays are ``ray_ptr[L]:ray_ptr[L + 1]``, at local
    (``ray_r``, ``ray_c``). Returns ``out``.
    """
    nz, ny, nx = volume.shape
    n_lens = xf_x.shape[0]
    bmax = u_col.shape[1]
    for lens in prange(n_lens):
        if ray_ptr[lens + 1] == ray_ptr[lens]:
            continue
        nc = n_col[lens]
        nr = n_row[lens]
        xs = np.empty(bmax, np.int64)
        xc = np.empty(bmax, np.int64)
        xw = np.empty((bmax, kmax), np.float64)
        ys = np.empty(bmax, np.int64)
        yc = np.empty(bmax, np.int64)
        yw = np.empty((bmax, kmax), np.float64)
        local = np.zeros((nr, nc), np.float64)
        tmp = np.empty((ny, nc), np.float64)
        for k in range(nz):
            x_lo, x_hi = _profiles(u_col[lens], nc, xf_x[lens], t[k], shape[k], half[k],
                                   ox, vx, nx, xs, xc, xw)
            if x_lo >= x_hi:
                continue
            y_lo, y_hi = _profiles(u_row[lens], nr, xf_y[lens], t[k], shape[k], half[k],
                                   oy, vy, ny, ys, yc, yw)
            if y_lo >= y_hi:
                continue
            vk = volume[k]
            for iy in range(y_lo, y_hi):
                src = vk[iy]
                dst = tmp[iy]
                for c in range(nc):
                    acc = 0.0
                    s = xs[c]
                    for j in range(xc[c]):
                        acc += xw[c, j] * src[s + j]
                    dst[c] = acc
            f = slice_factor[k]
            for r in range(nr):
                s = ys[r]
                a = local[r]
                for j in range(yc[r]):
                    wgt = f * yw[r, j]
                    src = tmp[s + j]
                    for c in range(nc):
                        a[c] += wgt * src[c]
        for i in range(ray_ptr[lens], ray_ptr[lens + 1]):
            out[ray_pos[i]] = np.float32(local[ray_r[i], ray_c[i]] * ray_scale[i])
    return out


@njit(parallel=True, cache=True)
def back(image, t, shape, half, slice_factor, ox, oy, vx, vy, u_col, u_row, n_col, n_row,
         xf_x, xf_y, ray_ptr, ray_r, ray_c, ray_scale, ray_pos, kmax, out):
    """Back projection, the adjoint of :func:`forward`.

    ``out[k, iy, ix] = sum_i scale_i f_k wy wx image[ray_pos[i]]``; parallel over slices,
    so each thread writes only its own slice.
    """
    nz, ny, nx = out.shape
    n_lens = xf_x.shape[0]
    bmax = u_col.shape[1]
    # the rays' values gathered into each lenslet's local image, once
    local = np.zeros((n_lens, bmax, bmax), np.float32)
    for lens in prange(n_lens):
        for i in range(ray_ptr[lens], ray_ptr[lens + 1]):
            local[lens, ray_r[i], ray_c[i]] = image[ray_pos[i]] * ray_scale[i]
    for k in prange(nz):
        ok = out[k]
        for iy in range(ny):
            for ix in range(nx):
                ok[iy, ix] = 0.0
        xs = np.empty(bmax, np.int64)
        xc = np.empty(bmax, np.int64)
        xw = np.empty((bmax, kmax), np.float64)
        ys = np.empty(bmax, np.int64)
        yc = np.empty(bmax, np.int64)
        yw = np.empty((bmax, kmax), np.float64)
        tmp = np.zeros((ny, bmax), np.float64)
        f = slice_factor[k]
        for lens in range(n_lens):
            if ray_ptr[lens + 1] == ray_ptr[lens]:
                continue
            nc = n_col[lens]
            nr = n_row[lens]
            x_lo, x_hi = _profiles(u_col[lens], nc, xf_x[lens], t[k], shape[k], half[k],
                                   ox, vx, nx, xs, xc, xw)
            if x_lo >= x_hi:
                continue
            y_lo, y_hi = _profiles(u_row[lens], nr, xf_y[lens], t[k], shape[k], half[k],
                                   oy, vy, ny, ys, yc, yw)
            if y_lo >= y_hi:
                continue
            img = local[lens]
            for iy in range(y_lo, y_hi):
                for c in range(nc):
                    tmp[iy, c] = 0.0
            for r in range(nr):
                s = ys[r]
                src = img[r]
                for j in range(yc[r]):
                    wgt = f * yw[r, j]
                    dst = tmp[s + j]
                    for c in range(nc):
                        dst[c] += wgt * src[c]
            for iy in range(y_lo, y_hi):
                src = tmp[iy]
                dst = ok[iy]
                for c in range(nc):
                    v = src[c]
                    if v == 0.0:
                        continue
                    s = xs[c]
                    for j in range(xc[c]):
                        dst[s + j] += np.float32(xw[c, j] * v)
    return out


@njit(parallel=True, cache=True)
def row_max(t, shape, half, slice_factor, ox, oy, vx, vy, nx, ny, u_col, u_row, n_col, n_row,
            xf_x, xf_y, ray_ptr, ray_r, ray_c, ray_scale, ray_pos, kmax, out):
    """Largest weight of every ray: ``scale · max_k f_k · max_ix wx · max_iy wy``."""
    nz = t.shape[0]
    n_lens = xf_x.shape[0]
    bmax = u_col.shape[1]
    for lens in prange(n_lens):
        if ray_ptr[lens + 1] == ray_ptr[lens]:
            continue
        nc = n_col[lens]
        nr = n_row[lens]
        xs = np.empty(bmax, np.int64)
        xc = np.empty(bmax, np.int64)
        xw = np.empty((bmax, kmax), np.float64)
        ys = np.empty(bmax, np.int64)
        yc = np.empty(bmax, np.int64)
        yw = np.empty((bmax, kmax), np.float64)
        mx = np.empty(bmax, np.float64)
        my = np.empty(bmax, np.float64)
        best = np.zeros((nr, nc), np.float64)
        for k in range(nz):
            _profiles(u_col[lens], nc, xf_x[lens], t[k], shape[k], half[k], ox, vx, nx,
                      xs, xc, xw)
            _profiles(u_row[lens], nr, xf_y[lens], t[k], shape[k], half[k], oy, vy, ny,
                      ys, yc, yw)
            for c in range(nc):
                m = 0.0
                for j in range(xc[c]):
                    m = max(m, xw[c, j])
                mx[c] = m
            for r in range(nr):
                m = 0.0
                for j in range(yc[r]):
                    m = max(m, yw[r, j])
                my[r] = m * slice_factor[k]
            for i in range(ray_ptr[lens], ray_ptr[lens + 1]):
                v = mx[ray_c[i]] * my[ray_r[i]]
                if v > best[ray_r[i], ray_c[i]]:
                    best[ray_r[i], ray_c[i]] = v
        for i in range(ray_ptr[lens], ray_ptr[lens + 1]):
            out[ray_pos[i]] = np.float32(best[ray_r[i], ray_c[i]] * ray_scale[i])
    return out
