"""Numba kernels of the per-lenslet matrix-free projector.

Within one lenslet the weights on depth slice k are an outer product,
``W[(r, c), (k, iy, ix)] = scale(r, c) · f_k · wy[k, r, iy] · wx[k, c, ix]``, whatever the
lattice's rotation, packing or jitter. The profiles are computed on the fly, per lenslet,
slice and micro-image line, into small per-thread buffers. Forward: per lenslet (in parallel),
per slice, contract x then y into the lenslet's local image. Back: per slice (in parallel, so
that no two threads write one voxel), per lenslet, the reverse; tall patches through the
slice transposed (:data:`TRANSPOSED_MIN_ROWS`). Both release the GIL, so that
:func:`plenopiv.reconstruction.real_lattice.compile_ahead` compiles beside them.

See :mod:`plenopiv.reconstruction.real_lattice` and docs/methods.md#projectors.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

#: Voxel rows of a lenslet's patch on a slice from which the back projection accumulates
#: it in the slice transposed (``[ix, iy]``), whose rows are contiguous there: the
#: compiler vectorises that loop. Shorter patches (near focus) go straight into the slice,
#: where a vector of a few rows would cost more than it saves. At full size on a turned
#: 16 MP array the back projection takes 11 % less time on footprint voxels, 33 % less on a
#: 2 x 2 subdivision (docs/performance.md).
TRANSPOSED_MIN_ROWS = 8


def interleaved_order(n: int, n_threads: int) -> np.ndarray:
    """Return ``range(n)`` dealt round-robin into ``n_threads`` runs (int64).

    A parallel loop hands each thread one contiguous run of its iterations; a slice's cost
    grows with its distance from the focal plane (a beam's width), so a depth slab that
    lies on one side of focus would give one thread the wide slices and the other the
    narrow ones.
    Dealt round-robin, every run spans the slab's whole depth.
    """
    k = max(1, int(n_threads))
    return np.concatenate([np.arange(i, n, k) for i in range(k)]).astype(np.int64)


@njit(cache=True, inline="always")
def _cdf(y, shape):
    """Return :func:`plenopiv.reconstruction._kernels.weights.box_sum_cdf` at ``y`` = x - centre.

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


@njit(cache=True, inline="always")
def _profiles(u_line, n_line, xf, tk, shape, half, origin, vox, n_vox, start, count, w, edge):
    """Voxel overlaps of the lines' beams on one slice, along one axis.

    ``u_line[:n_line]``: the lines' aperture coordinates (metres); ``xf``: the lenslet's
    focal-plane coordinate (metres); ``shape``: the slice's :func:`cdf_shapes` row. Writes
    ``start``, ``count``, ``w[:, :count]`` per line; returns the first and one past the last
    voxel any line reaches (``lo >= hi`` if none). ``edge``: scratch of shape
    (kmax + 2, lines); the CDF is evaluated edge by edge across the lines, a loop without
    branches that the compiler vectorises.
    """
    lo = n_vox
    hi = 0
    kmax = w.shape[1]
    inv_vox = 1.0 / vox
    most = 0
    first = edge[kmax + 1]          # offset of each line's first voxel edge from its centre
    for p in range(n_line):
        m = (1.0 - tk) * u_line[p] + tk * xf
        i0 = int(math.floor((m - half - origin) * inv_vox + 0.5))
        i1 = int(math.floor((m + half - origin) * inv_vox + 0.5))
        if i0 < 0:
            i0 = 0
        if i1 > n_vox - 1:
            i1 = n_vox - 1
        c = i1 - i0 + 1
        first[p] = origin + (i0 - 0.5) * vox - m
        if c <= 0:
            count[p] = 0
            start[p] = 0
            continue
        if c > kmax:
            c = kmax
        start[p] = i0
        count[p] = c
        if c > most:
            most = c
        if i0 < lo:
            lo = i0
        if i0 + c > hi:
            hi = i0 + c
    p1, p2, p3, p4, inv = shape[0], shape[1], shape[2], shape[3], shape[4]
    uniform = shape[5] > 0.0
    for j in range(most + 1):
        row = edge[j]
        dj = j * vox
        if uniform:
            for p in range(n_line):
                v = (first[p] + dj) * shape[6] + 0.5
                row[p] = min(max(v, 0.0), 1.0)
        else:
            for p in range(n_line):
                y = first[p] + dj
                r1 = max(y - p1, 0.0)
                r2 = max(y - p2, 0.0)
                r3 = max(y - p3, 0.0)
                r4 = max(y - p4, 0.0)
                row[p] = (r1 * r1 - r2 * r2 - r3 * r3 + r4 * r4) * inv
    for p in range(n_line):
        for j in range(count[p]):
            v = edge[j + 1, p] - edge[j, p]
            w[p, j] = v if v > 0.0 else 0.0
    return lo, hi


@njit(cache=True, inline="always")
def _slice_profiles(ucol, urow, nc, nr, xf_x, xf_y, tk, shape, half, ox, oy, vx, vy, nx, ny,
                    xs, xc, xw, ys, yc, yw, edge):
    """Both voxel profiles of one lenslet on one slice: ``(x_lo, x_hi, y_lo, y_hi)``.

    The column profiles (``xs, xc, xw``) first; the row profiles only when those reach a
    voxel. The slice adds nothing when ``x_lo >= x_hi`` or ``y_lo >= y_hi``.
    """
    x_lo, x_hi = _profiles(ucol, nc, xf_x, tk, shape, half, ox, vx, nx, xs, xc, xw, edge)
    if x_lo >= x_hi:
        return x_lo, x_hi, 0, 0
    y_lo, y_hi = _profiles(urow, nr, xf_y, tk, shape, half, oy, vy, ny, ys, yc, yw, edge)
    return x_lo, x_hi, y_lo, y_hi


@njit(cache=True, inline="always")
def _span(u_line, n_line, xf, tk, half, origin, vox, n_vox):
    """Return the first and one past the last voxel any of the lines' beams reaches.

    The beam centre is linear in u, so the end lines bound it; ``lo >= hi`` if none.
    """
    m0 = (1.0 - tk) * u_line[0] + tk * xf
    m1 = (1.0 - tk) * u_line[n_line - 1] + tk * xf
    a = min(m0, m1)
    b = max(m0, m1)
    lo = int(math.floor((a - half - origin) / vox + 0.5))
    hi = int(math.floor((b + half - origin) / vox + 0.5)) + 1
    return max(lo, 0), min(hi, n_vox)


@njit(cache=True, inline="always")
def _patch_is_empty(vk, y_lo, y_hi, x_lo, x_hi):
    """Return True when ``vk[y_lo:y_hi, x_lo:x_hi]`` holds only zeros."""
    for iy in range(y_lo, y_hi):
        row = vk[iy]
        for ix in range(x_lo, x_hi):
            if row[ix] != 0.0:
                return False
    return True


@njit(cache=True, inline="always")
def _profile_workspace(bmax, kmax):
    """Per-thread buffers of the x and y voxel profiles (start, count, weights) and edges."""
    return (np.empty(bmax, np.int64), np.empty(bmax, np.int64),
            np.empty((bmax, kmax), np.float32), np.empty(bmax, np.int64),
            np.empty(bmax, np.int64), np.empty((bmax, kmax), np.float32),
            np.empty((kmax + 2, bmax), np.float64))


@njit(parallel=True, cache=True, nogil=True)
def forward(volume, t, shape, half, slice_factor, ox, oy, vx, vy, u_col, u_row, window,
            xf_x, xf_y, ray_ptr, ray_r, ray_c, ray_scale, ray_pos, kmax, out):
    """``out[ray_pos[i]] = scale_i · sum_k f_k sum_iy wy sum_ix wx volume[k, iy, ix]``.

    Parallel over lenslets (each writes only its own rays). ``u_col[L]`` and ``u_row[L]``:
    aperture coordinates of lenslet L's micro-image columns and rows (metres);
    ``window[L]``: the rows ``[0]:[1]`` and columns ``[2]:[3]`` that hold its rays;
    ``ray_ptr``: lenslet L's rays are ``ray_ptr[L]:ray_ptr[L + 1]``, at local (``ray_r``,
    ``ray_c``). Returns ``out``.
    """
    nz, ny, nx = volume.shape
    n_lens = xf_x.shape[0]
    bmax = u_col.shape[1]
    for lens in prange(n_lens):
        if ray_ptr[lens + 1] == ray_ptr[lens]:
            continue
        r0, r1, c0, c1 = window[lens, 0], window[lens, 1], window[lens, 2], window[lens, 3]
        nr, nc = r1 - r0, c1 - c0
        ucol = u_col[lens, c0:c1]
        urow = u_row[lens, r0:r1]
        xs, xc, xw, ys, yc, yw, edge = _profile_workspace(bmax, kmax)
        local = np.zeros((nr, nc), np.float32)
        tmp = np.empty((ny, nc), np.float32)
        for k in range(nz):
            # a patch of zeros (most of a sparse volume) adds nothing: skip its profiles
            x_lo, x_hi = _span(ucol, nc, xf_x[lens], t[k], half[k], ox, vx, nx)
            y_lo, y_hi = _span(urow, nr, xf_y[lens], t[k], half[k], oy, vy, ny)
            if x_lo >= x_hi or y_lo >= y_hi or _patch_is_empty(volume[k], y_lo, y_hi, x_lo,
                                                                x_hi):
                continue
            x_lo, x_hi, y_lo, y_hi = _slice_profiles(
                ucol, urow, nc, nr, xf_x[lens], xf_y[lens], t[k], shape[k], half[k], ox, oy,
                vx, vy, nx, ny, xs, xc, xw, ys, yc, yw, edge)
            if x_lo >= x_hi or y_lo >= y_hi:
                continue
            vk = volume[k]
            for iy in range(y_lo, y_hi):
                src = vk[iy]
                dst = tmp[iy]
                for c in range(nc):
                    acc = np.float32(0.0)
                    s = xs[c]
                    for j in range(xc[c]):
                        acc += xw[c, j] * src[s + j]
                    dst[c] = acc
            f = np.float32(slice_factor[k])
            for r in range(nr):
                s = ys[r]
                a = local[r]
                for j in range(yc[r]):
                    wgt = f * yw[r, j]
                    src = tmp[s + j]
                    for c in range(nc):
                        a[c] += wgt * src[c]
        for i in range(ray_ptr[lens], ray_ptr[lens + 1]):
            out[ray_pos[i]] = local[ray_r[i] - r0, ray_c[i] - c0] * ray_scale[i]
    return out


@njit(parallel=True, cache=True, nogil=True)
def back(image, t, shape, half, slice_factor, ox, oy, vx, vy, u_col, u_row, window,
         xf_x, xf_y, ray_ptr, ray_r, ray_c, ray_scale, ray_pos, kmax, out, order):
    """Back projection, the adjoint of :func:`forward`.

    ``out[k, iy, ix] = sum_i scale_i f_k wy wx image[ray_pos[i]]``; parallel over slices,
    so each thread writes only its own slice. Each lenslet works on the window of its rays
    whose value is not zero (``window`` is not used: the arguments are forward's).
    ``order``: the slices in the order the parallel loop takes them (a permutation of
    ``range(nz)``, see :func:`interleaved_order`); the result does not depend on it.
    """
    nz, ny, nx = out.shape
    n_lens = xf_x.shape[0]
    bmax = u_col.shape[1]
    # the rays' values gathered into each lenslet's local image, once, and the window of
    # the non-zero ones (rows [0]:[1], columns [2]:[3]; empty when all are zero)
    local = np.zeros((n_lens, bmax, bmax), np.float32)
    box = np.zeros((n_lens, 4), np.int64)
    for lens in prange(n_lens):
        r0, r1, c0, c1 = bmax, 0, bmax, 0
        for i in range(ray_ptr[lens], ray_ptr[lens + 1]):
            v = image[ray_pos[i]] * ray_scale[i]
            if v == 0.0:
                continue
            r, c = ray_r[i], ray_c[i]
            local[lens, r, c] = v
            r0, r1, c0, c1 = min(r0, r), max(r1, r + 1), min(c0, c), max(c1, c + 1)
        box[lens, 0], box[lens, 1], box[lens, 2], box[lens, 3] = r0, r1, c0, c1
    for kk in prange(nz):
        k = order[kk]
        ok = out[k]
        for iy in range(ny):
            for ix in range(nx):
                ok[iy, ix] = 0.0
        xs, xc, xw, ys, yc, yw, edge = _profile_workspace(bmax, kmax)
        tmp = np.zeros((ny, bmax), np.float32)
        tmpt = np.empty((bmax, ny), np.float32)
        okt = np.zeros((nx, ny), np.float32)       # the slice transposed: [ix, iy]
        f = np.float32(slice_factor[k])
        for lens in range(n_lens):
            r0, r1, c0, c1 = box[lens, 0], box[lens, 1], box[lens, 2], box[lens, 3]
            if r1 <= r0:
                continue
            nr, nc = r1 - r0, c1 - c0
            x_lo, x_hi, y_lo, y_hi = _slice_profiles(
                u_col[lens, c0:c1], u_row[lens, r0:r1], nc, nr, xf_x[lens], xf_y[lens], t[k],
                shape[k], half[k], ox, oy, vx, vy, nx, ny, xs, xc, xw, ys, yc, yw, edge)
            if x_lo >= x_hi or y_lo >= y_hi:
                continue
            img = local[lens]
            for iy in range(y_lo, y_hi):
                for c in range(nc):
                    tmp[iy, c] = 0.0
            for r in range(nr):
                s = ys[r]
                src = img[r0 + r, c0:c1]
                for j in range(yc[r]):
                    wgt = f * yw[r, j]
                    dst = tmp[s + j]
                    for c in range(nc):
                        dst[c] += wgt * src[c]
            # x: column by column, rows innermost. Near focus all of a lenslet's columns
            # land on the same one or two voxels; with the rows innermost successive
            # additions go to different voxels instead of waiting on each other. A patch
            # TRANSPOSED_MIN_ROWS or more rows tall goes through the transposed slice,
            # where those rows are contiguous and the loop is vectorised
            nyp = y_hi - y_lo
            if nyp >= TRANSPOSED_MIN_ROWS:
                for e in range(nyp):
                    row = tmp[y_lo + e]
                    for c in range(nc):
                        tmpt[c, e] = row[c]
                for c in range(nc):
                    s = xs[c]
                    src = tmpt[c, :nyp]
                    for j in range(xc[c]):
                        w = xw[c, j]
                        dst = okt[s + j, y_lo:y_hi]
                        for e in range(nyp):
                            dst[e] += w * src[e]
            else:
                for c in range(nc):
                    s = xs[c]
                    for j in range(xc[c]):
                        w = xw[c, j]
                        ix = s + j
                        for iy in range(y_lo, y_hi):
                            ok[iy, ix] += w * tmp[iy, c]
        for iy in range(ny):
            row = ok[iy]
            for ix in range(nx):
                row[ix] += okt[ix, iy]
    return out


@njit(cache=True, nogil=True)
def row_reduce(t, shape, half, slice_factor, ox, oy, vx, vy, nx, ny, u_col, u_row, window,
               xf_x, xf_y, ray_ptr, ray_r, ray_c, ray_scale, ray_pos, kmax, maximum, out,
               lo, hi):
    """Largest (``maximum``) or summed weight of every ray, without the contractions.

    On each slice the weights of a ray are the outer product of its column's and its row's
    voxel profiles, so their largest value is the product of the profiles' maxima and their
    sum the product of the profiles' sums: ``scale · max_k f_k · max wx · max wy`` or
    ``scale · sum_k f_k · (sum wx) · (sum wy)`` (the sum is a forward projection of ones).
    Lenslets ``lo:hi`` (each writes only its own rays; run on slices by
    :func:`plenopiv._threads.run_slices`: used once or twice a reconstruction, it is not worth
    a parallel kernel's compilation), reduced in float64.
    """
    nz = t.shape[0]
    bmax = u_col.shape[1]
    for lens in range(lo, hi):
        if ray_ptr[lens + 1] == ray_ptr[lens]:
            continue
        r0, r1, c0, c1 = window[lens, 0], window[lens, 1], window[lens, 2], window[lens, 3]
        nr, nc = r1 - r0, c1 - c0
        xs, xc, xw, ys, yc, yw, edge = _profile_workspace(bmax, kmax)
        px = np.empty(bmax, np.float64)
        py = np.empty(bmax, np.float64)
        acc = np.zeros((nr, nc), np.float64)
        for k in range(nz):
            x_lo, x_hi, y_lo, y_hi = _slice_profiles(
                u_col[lens, c0:c1], u_row[lens, r0:r1], nc, nr, xf_x[lens], xf_y[lens], t[k],
                shape[k], half[k], ox, oy, vx, vy, nx, ny, xs, xc, xw, ys, yc, yw, edge)
            if x_lo >= x_hi or y_lo >= y_hi:
                continue
            for c in range(nc):
                v = 0.0
                for j in range(xc[c]):
                    v = max(v, xw[c, j]) if maximum else v + xw[c, j]
                px[c] = v
            for r in range(nr):
                v = 0.0
                for j in range(yc[r]):
                    v = max(v, yw[r, j]) if maximum else v + yw[r, j]
                py[r] = v * slice_factor[k]
            for r in range(nr):
                for c in range(nc):
                    v = py[r] * px[c]
                    acc[r, c] = max(acc[r, c], v) if maximum else acc[r, c] + v
        for i in range(ray_ptr[lens], ray_ptr[lens + 1]):
            out[ray_pos[i]] = np.float32(acc[ray_r[i] - r0, ray_c[i] - c0] * ray_scale[i])
    return out
