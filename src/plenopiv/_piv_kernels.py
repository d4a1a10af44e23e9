"""Numerical kernels of :mod:`plenopiv.piv`, each as a numba function and a plain-NumPy twin.

Every kernel takes arrays and scalars only and returns new arrays; only ``cross_spectrum``
writes into an ``out`` array its caller passes (possibly one of its inputs, a scratch buffer).
The two implementations of a kernel share one signature and one meaning; the tests run both
on the same inputs and :func:`plenopiv.piv.correlate_volumes` chooses one by its ``engine``
argument (``"numba"``, the default, or ``"numpy"``). All positions, shifts and displacements
here are in voxels and in the volume's index order ``(z, y, x)``.

``find_peaks``, ``deform_cubic``, ``neighbour_median`` and ``peak_statistics`` are serial
numba functions: their work in a run is small (a few hundred windows or vectors), and
numba compiles a parallel (``prange``) loop several times more slowly than a serial one,
which on the first run cost more than the threads save (README, "What the first run
costs"). The heavy kernels (``extract_windows``, ``cross_spectrum``, ``deform_trilinear``)
stay parallel.

Kernels
-------
extract_windows
    Copy interrogation windows at arbitrary start voxels out of a volume (zero outside it).
cross_spectrum
    From the real-FFT spectra ``A, B`` of ``p * q`` windows, laid out ``(kz, p, ky, q, kx)``
    as the staged transform of :mod:`plenopiv.piv` leaves them (``nx`` is the real window
    length along x): the cross spectrum ``conj(A) B`` without its mean (DC) term, written
    into ``out`` shaped ``(p, q, kz, ky, kx)``, and per window (Parseval's theorem) the
    energies about the mean ``sum((a - mean(a))**2)``, ``sum((b - mean(b))**2)`` and the
    total energies ``sum(a**2)``, ``sum(b**2)``, returned as the columns of an (n, 4) array.
find_peaks
    For a batch of circular correlation planes: the displacement (n, 3) of the highest peak
    refined by a 3-point fit per axis, the raw peak height, and the ratio of the primary
    peak to the highest other face-connected local maximum.
deform_trilinear
    Sample a volume at ``x + factor * d(x)`` by trilinear interpolation (zero outside).
deform_cubic
    Sample a cubic B-spline, given by its coefficients on a zero-padded grid, at
    ``x + factor * d(x)``.
neighbour_median
    Median of the usable 3x3x3 neighbours (centre excluded) of every vector of a field, and
    the median of those neighbours' absolute residuals: the two ingredients of the
    normalised median test.
peak_statistics
    For window pairs at given start voxels and their integer correlation peak: the peak
    value and its two neighbours along each axis, built from the products of the two
    windows' intensities, and the variance of the asymmetry of those neighbours (the
    correlation statistics of Wieneke 2015, in 3-D, with the covariance of neighbouring
    voxels' contributions).
"""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace

import numba
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

# --------------------------------------------------------------------------------------------
# extract_windows
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True, parallel=True)
def _extract_windows_numba(volume, starts, wz, wy, wx):
    n = starts.shape[0]
    nz, ny, nx = volume.shape
    out = np.zeros((n, wz, wy, wx), dtype=np.float32)
    for k in numba.prange(n):
        z0 = starts[k, 0]
        y0 = starts[k, 1]
        x0 = starts[k, 2]
        xa = max(0, -x0)
        xb = min(wx, nx - x0)
        if xb <= xa:
            continue
        for i in range(max(0, -z0), min(wz, nz - z0)):
            for j in range(max(0, -y0), min(wy, ny - y0)):
                out[k, i, j, xa:xb] = volume[z0 + i, y0 + j, x0 + xa : x0 + xb]
    return out


def _extract_windows_numpy(volume, starts, wz, wy, wx):
    starts = np.asarray(starts, dtype=np.int64)
    shape = np.array(volume.shape)
    if starts.shape[0] == 0:
        return np.empty((0, wz, wy, wx), np.float32)
    window = np.array([wz, wy, wx])
    pad_lo = np.maximum(0, -starts.min(axis=0))
    pad_hi = np.maximum(0, (starts + window).max(axis=0) - shape)
    padded = np.pad(volume, list(zip(pad_lo, pad_hi, strict=True)), mode="constant")
    s = starts + pad_lo
    iz = s[:, 0, None, None, None] + np.arange(wz)[None, :, None, None]
    iy = s[:, 1, None, None, None] + np.arange(wy)[None, None, :, None]
    ix = s[:, 2, None, None, None] + np.arange(wx)[None, None, None, :]
    return padded[iz, iy, ix].astype(np.float32)


# --------------------------------------------------------------------------------------------
# cross_spectrum
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True, parallel=True)
def _cross_spectrum_numba(fa, fb, nx, out):
    kz, p, ky, q, kx = fa.shape
    size = kz * ky * nx
    # loops follow the memory order of the inputs; per-kz partial sums keep threads apart
    partial = np.zeros((kz, p * q, 2), dtype=np.float64)
    for i in numba.prange(kz):
        for u in range(p):
            for j in range(ky):
                for v in range(q):
                    k = u * q + v
                    sa = 0.0
                    sb = 0.0
                    for m in range(kx):
                        a = fa[i, u, j, v, m]
                        b = fb[i, u, j, v, m]
                        weight = 1.0 if (m == 0 or 2 * m == nx) else 2.0
                        sa += weight * (a.real * a.real + a.imag * a.imag)
                        sb += weight * (b.real * b.real + b.imag * b.imag)
                        out[u, v, i, j, m] = a.conjugate() * b
                    partial[i, k, 0] += sa
                    partial[i, k, 1] += sb
    energy = np.empty((p * q, 4), dtype=np.float64)
    for u in range(p):
        for v in range(q):
            k = u * q + v
            a0 = fa[0, u, 0, v, 0]
            b0 = fb[0, u, 0, v, 0]
            sa = 0.0
            sb = 0.0
            for i in range(kz):
                sa += partial[i, k, 0]
                sb += partial[i, k, 1]
            energy[k, 0] = (sa - (a0.real * a0.real + a0.imag * a0.imag)) / size
            energy[k, 1] = (sb - (b0.real * b0.real + b0.imag * b0.imag)) / size
            energy[k, 2] = sa / size
            energy[k, 3] = sb / size
            out[u, v, 0, 0, 0] = 0.0
    return energy


def _cross_spectrum_numpy(fa, fb, nx, out):
    kz, p, ky, q, kx = fa.shape
    fa = fa.transpose(1, 3, 0, 2, 4).astype(np.complex128)
    fb = fb.transpose(1, 3, 0, 2, 4).astype(np.complex128)
    weight = np.full(kx, 2.0)
    weight[0] = 1.0
    if nx % 2 == 0:
        weight[-1] = 1.0
    power_a = (np.abs(fa) ** 2).reshape(p * q, kz, ky, kx)
    power_b = (np.abs(fb) ** 2).reshape(p * q, kz, ky, kx)
    size = kz * ky * nx
    total_a = (power_a * weight).sum(axis=(1, 2, 3)) / size
    total_b = (power_b * weight).sum(axis=(1, 2, 3)) / size
    energy = np.stack(
        [
            total_a - power_a[:, 0, 0, 0] / size,
            total_b - power_b[:, 0, 0, 0] / size,
            total_a,
            total_b,
        ],
        axis=1,
    )
    out[...] = np.conj(fa) * fb
    out[:, :, 0, 0, 0] = 0.0
    return energy


# --------------------------------------------------------------------------------------------
# find_peaks
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _fit3_numba(cm, c0, cp, gaussian):
    if gaussian and cm > 0.0 and c0 > 0.0 and cp > 0.0:
        lm = math.log(cm)
        l0 = math.log(c0)
        lp = math.log(cp)
        den = lm - 2.0 * l0 + lp
        if den < 0.0:
            return 0.5 * (lm - lp) / den
    den = cm - 2.0 * c0 + cp
    if den < 0.0:
        return 0.5 * (cm - cp) / den
    return 0.0


@numba.njit(cache=True)
def _find_peaks_numba(corr, gaussian):
    n, wz, wy, wx = corr.shape
    disp = np.empty((n, 3), dtype=np.float64)
    peak = np.empty(n, dtype=np.float64)
    snr = np.empty(n, dtype=np.float64)
    for k in range(n):
        c = corr[k]
        # one sweep keeps the two highest face-connected local maxima; the global maximum is
        # one of them, the other is the secondary peak. A voxel is examined further only
        # when it beats the current secondary value.
        best = -np.inf
        second = -np.inf
        bi = 0
        bj = 0
        bm = 0
        for i in range(wz):
            im = i - 1 if i > 0 else wz - 1
            ip = i + 1 if i < wz - 1 else 0
            for j in range(wy):
                jm = j - 1 if j > 0 else wy - 1
                jp = j + 1 if j < wy - 1 else 0
                for m in range(wx):
                    v = c[i, j, m]
                    if v <= second:
                        continue
                    mm = m - 1 if m > 0 else wx - 1
                    mp = m + 1 if m < wx - 1 else 0
                    if (
                        v >= c[im, j, m]
                        and v >= c[ip, j, m]
                        and v >= c[i, jm, m]
                        and v >= c[i, jp, m]
                        and v >= c[i, j, mm]
                        and v >= c[i, j, mp]
                    ):
                        if v > best:
                            second = best
                            best = v
                            bi = i
                            bj = j
                            bm = m
                        else:
                            second = v
        fz = _fit3_numba(c[(bi - 1) % wz, bj, bm], best, c[(bi + 1) % wz, bj, bm], gaussian)
        fy = _fit3_numba(c[bi, (bj - 1) % wy, bm], best, c[bi, (bj + 1) % wy, bm], gaussian)
        fx = _fit3_numba(c[bi, bj, (bm - 1) % wx], best, c[bi, bj, (bm + 1) % wx], gaussian)
        disp[k, 0] = (bi - wz if 2 * bi >= wz else bi) + fz
        disp[k, 1] = (bj - wy if 2 * bj >= wy else bj) + fy
        disp[k, 2] = (bm - wx if 2 * bm >= wx else bm) + fx
        peak[k] = best
        if second > 0.0 and best > 0.0:
            snr[k] = best / second
        else:
            snr[k] = np.inf
    return disp, peak, snr


def _fit3_numpy(cm, c0, cp, gaussian):
    cm, c0, cp = (np.asarray(a, dtype=np.float64) for a in (cm, c0, cp))
    den_p = cm - 2.0 * c0 + cp
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(den_p < 0.0, 0.5 * (cm - cp) / den_p, 0.0)
        if gaussian:
            positive = (cm > 0) & (c0 > 0) & (cp > 0)
            lm, l0, lp = (np.log(np.where(positive, a, 1.0)) for a in (cm, c0, cp))
            den_g = lm - 2.0 * l0 + lp
            use = positive & (den_g < 0.0)
            frac = np.where(use, 0.5 * (lm - lp) / np.where(use, den_g, -1.0), frac)
    return frac


def _find_peaks_numpy(corr, gaussian):
    n, wz, wy, wx = corr.shape
    flat = corr.reshape(n, -1)
    best_idx = np.argmax(flat, axis=1)
    best = flat[np.arange(n), best_idx].astype(np.float64)
    bi, bj, bm = np.unravel_index(best_idx, (wz, wy, wx))
    local_max = np.ones(corr.shape, dtype=bool)
    for axis in (1, 2, 3):
        for step in (1, -1):
            local_max &= corr >= np.roll(corr, step, axis=axis)
    local_max[np.arange(n), bi, bj, bm] = False
    candidates = np.where(local_max, corr, -np.inf).reshape(n, -1)
    second = candidates.max(axis=1) if candidates.shape[1] else np.full(n, -np.inf)
    k = np.arange(n)
    fz = _fit3_numpy(corr[k, (bi - 1) % wz, bj, bm], best, corr[k, (bi + 1) % wz, bj, bm], gaussian)
    fy = _fit3_numpy(corr[k, bi, (bj - 1) % wy, bm], best, corr[k, bi, (bj + 1) % wy, bm], gaussian)
    fx = _fit3_numpy(corr[k, bi, bj, (bm - 1) % wx], best, corr[k, bi, bj, (bm + 1) % wx], gaussian)
    disp = np.stack(
        [
            np.where(2 * bi >= wz, bi - wz, bi) + fz,
            np.where(2 * bj >= wy, bj - wy, bj) + fy,
            np.where(2 * bm >= wx, bm - wx, bm) + fx,
        ],
        axis=1,
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = np.where((second > 0.0) & (best > 0.0), best / second, np.inf)
    return disp, best, snr


# --------------------------------------------------------------------------------------------
# deform_trilinear
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True, parallel=True)
def _deform_trilinear_numba(volume, field, factor):
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


def _deform_trilinear_numpy(volume, field, factor):
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
def _deform_cubic_numba(coeffs, field, factor, pad):
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


def _deform_cubic_numpy(coeffs, field, factor, pad):
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


# --------------------------------------------------------------------------------------------
# neighbour_median
# --------------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _small_median(a, n):
    """Median of ``a[:n]`` (n >= 1), sorting ``a[:n]`` in place.

    An insertion sort of at most 26 values, which compiles in a fraction of the time of
    ``np.median``.
    """
    for i in range(1, n):
        v = a[i]
        j = i - 1
        while j >= 0 and a[j] > v:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = v
    h = n // 2
    return a[h] if n % 2 else 0.5 * (a[h - 1] + a[h])


@numba.njit(cache=True)
def _neighbour_median_numba(field, usable):
    ncomp, nz, ny, nx = field.shape
    median = np.full(field.shape, np.nan)
    residual = np.full(field.shape, np.nan)
    for flat in range(nz * ny * nx):
        i = flat // (ny * nx)
        j = (flat // nx) % ny
        m = flat % nx
        values = np.empty(26)
        dev = np.empty(26)
        for c in range(ncomp):
            count = 0
            for di in range(-1, 2):
                ii = i + di
                if ii < 0 or ii >= nz:
                    continue
                for dj in range(-1, 2):
                    jj = j + dj
                    if jj < 0 or jj >= ny:
                        continue
                    for dm in range(-1, 2):
                        mm = m + dm
                        if mm < 0 or mm >= nx:
                            continue
                        if di == 0 and dj == 0 and dm == 0:
                            continue
                        if usable[ii, jj, mm]:
                            values[count] = field[c, ii, jj, mm]
                            count += 1
            if count == 0:
                continue
            med = _small_median(values, count)
            for q in range(count):
                dev[q] = abs(values[q] - med)
            median[c, i, j, m] = med
            residual[c, i, j, m] = _small_median(dev, count)
    return median, residual


def _neighbour_median_numpy(field, usable):
    ncomp, nz, ny, nx = field.shape
    masked = np.where(usable[None], field, np.nan).astype(np.float64)
    padded = np.pad(masked, ((0, 0), (1, 1), (1, 1), (1, 1)), constant_values=np.nan)
    windows = sliding_window_view(padded, (3, 3, 3), axis=(1, 2, 3))
    neighbours = windows.reshape(ncomp, nz, ny, nx, 27).copy()
    neighbours[..., 13] = np.nan  # the centre of the 3x3x3 block
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "All-NaN slice": no usable neighbour
        median = np.nanmedian(neighbours, axis=-1)
        residual = np.nanmedian(np.abs(neighbours - median[..., None]), axis=-1)
    return median, residual


# --------------------------------------------------------------------------------------------
# peak_statistics
# --------------------------------------------------------------------------------------------


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
def _peak_statistics_numba(volume_a, volume_b, starts_a, starts_b, wz, wy, wx, peak, block):
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


def _peak_statistics_numpy(volume_a, volume_b, starts_a, starts_b, wz, wy, wx, peak, block):
    import scipy.ndimage

    n = starts_a.shape[0]
    a = _extract_windows_numpy(volume_a, starts_a, wz, wy, wx).astype(np.float64)
    b = _extract_windows_numpy(volume_b, starts_b, wz, wy, wx).astype(np.float64)
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


# --------------------------------------------------------------------------------------------
# engines
# --------------------------------------------------------------------------------------------

ENGINES = {
    "numba": SimpleNamespace(
        extract_windows=_extract_windows_numba,
        cross_spectrum=_cross_spectrum_numba,
        find_peaks=_find_peaks_numba,
        deform_trilinear=_deform_trilinear_numba,
        deform_cubic=_deform_cubic_numba,
        neighbour_median=_neighbour_median_numba,
        peak_statistics=_peak_statistics_numba,
    ),
    "numpy": SimpleNamespace(
        extract_windows=_extract_windows_numpy,
        cross_spectrum=_cross_spectrum_numpy,
        find_peaks=_find_peaks_numpy,
        deform_trilinear=_deform_trilinear_numpy,
        deform_cubic=_deform_cubic_numpy,
        neighbour_median=_neighbour_median_numpy,
        peak_statistics=_peak_statistics_numpy,
    ),
}
"""The kernel sets by name; both hold the same seven functions with the same signatures."""
