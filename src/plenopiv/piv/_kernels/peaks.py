"""Kernels that locate the correlation peak of each window pair to sub-voxel.

For a batch of circular correlation planes, ``find_peaks`` gives the displacement (n, 3) of
the highest peak refined by a 3-point fit per axis, the raw peak height, and the ratio of the
primary peak to the highest other face-connected local maximum. ``refine_peaks`` refines the
same peak on the correlation divided by the windows' overlap fraction (the loss of particle
pairs across the window border, which pulls a fitted peak towards zero), with a
least-squares Gaussian on five samples along an axis where the peak is broad and on seven
where it is wide (:func:`_refine_axis_numba`). See docs/methods.md#peak-fit.
"""

from __future__ import annotations

import math

import numba
import numpy as np


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
def find_peaks(corr, gaussian):
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


def find_peaks_numpy(corr, gaussian):
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
# refine_peaks
# --------------------------------------------------------------------------------------------

#: Smallest overlap fraction a correlation sample is divided by (a lag of 3/4 of the window).
MIN_OVERLAP = 0.25

#: A peak whose 3-point Gaussian width is at least this (voxels, one standard deviation) is
#: broad: five samples along that axis are fitted instead of three.
BROAD_SIGMA_VOX = 1.0

#: Shortest window edge along an axis for the five-point fit (its samples must be distinct).
MIN_BROAD_WINDOW = 8

#: A peak whose five-point Gaussian width is at least this (voxels, one standard deviation) is
#: wide: its samples at ±2 lie within one standard deviation and see only its top, so seven
#: samples (±3) are fitted instead. Depth peaks of plenoptic volumes are this wide (particles
#: 4-10 times longer in depth than across); lateral peaks are not.
WIDE_SIGMA_VOX = 2.0

#: Shortest window edge along an axis for the seven-point fit (its lags of ±3 keep at least
#: three quarters of the window's particle pairs).
MIN_WIDE_WINDOW = 12

#: Half the number of samples the refinement reads per axis (lags ``-HALF_SPAN .. HALF_SPAN``).
HALF_SPAN = 3

#: Largest offset (voxels) a 3-point fit may move the integer peak: its vertex beyond the
#: neighbours it read would be an extrapolation. A five- or seven-sample fit may move it up to
#: half a voxel inside its outermost lags (1.5 and 2.5 voxels).
THREE_POINT_BOUND_VOX = 1.0


@numba.njit(cache=True, inline="always")
def _fit_log_numba(u, first, count):
    """Least-squares parabola through ``ln u`` of ``u[first:first + count]`` with weights ``u**2``.

    The samples sit at the lags ``first - HALF_SPAN ...`` about the integer peak. Returns
    ``(vertex, sigma2)``: the offset of the maximum and the variance of the fitted Gaussian,
    ``-1 / (2 c)`` with ``c`` the curvature (NaN, NaN where it is not concave). The weights
    make it the maximum-likelihood fit for samples of equal absolute noise (the variance of
    ``ln u`` is ``(noise / u)**2``).
    """
    s0 = s1 = s2 = s3 = s4 = 0.0
    t0 = t1 = t2 = 0.0
    for q in range(first, first + count):
        x = q - float(HALF_SPAN)
        w = u[q] * u[q]
        y = math.log(u[q])
        s0 += w
        s1 += w * x
        s2 += w * x * x
        s3 += w * x * x * x
        s4 += w * x * x * x * x
        t0 += w * y
        t1 += w * x * y
        t2 += w * x * x * y
    det = s0 * (s2 * s4 - s3 * s3) - s1 * (s1 * s4 - s3 * s2) + s2 * (s1 * s3 - s2 * s2)
    if det == 0.0:
        return np.nan, np.nan
    b = (s0 * (t1 * s4 - s3 * t2) - t0 * (s1 * s4 - s3 * s2) + s2 * (s1 * t2 - t1 * s2)) / det
    c = (s0 * (s2 * t2 - t1 * s3) - s1 * (s1 * t2 - t1 * s2) + t0 * (s1 * s3 - s2 * s2)) / det
    if not c < 0.0:
        return np.nan, np.nan
    return -b / (2.0 * c), -1.0 / (2.0 * c)


@numba.njit(cache=True, inline="always")
def _positive(u, first, count):
    for q in range(first, first + count):
        if not u[q] > 0.0:
            return False
    return True


@numba.njit(cache=True)
def _refine_axis_numba(v, lag0, w, gaussian, overlap, broad):
    """Sub-voxel offset from the integer peak ``lag0`` along one axis of window length ``w``.

    ``v`` holds the correlation at the lags ``lag0 - 3 .. lag0 + 3`` (circularly sampled).
    With ``overlap`` each sample is first divided by the overlap fraction ``1 - |lag|/w`` of
    its lag (at least ``MIN_OVERLAP``): the particle pairs a window loses across its border
    weight the correlation by that triangle, which pulls a fitted peak towards zero by about
    ``2 sigma**2 / w`` voxels for particle images of standard deviation ``sigma``. With
    ``broad`` and the Gaussian estimator, where the five central samples are positive and the
    window holds ``MIN_BROAD_WINDOW`` voxels, :func:`_fit_log_numba` fits those five; its
    vertex is taken when the fitted peak is broad (standard deviation at least
    ``BROAD_SIGMA_VOX``). Where that peak is wide (at least ``WIDE_SIGMA_VOX``), the window
    holds ``MIN_WIDE_WINDOW`` voxels and all seven samples are positive, the seven are
    fitted and their vertex taken if that fit is wide too. Otherwise the 3-point fit
    (:func:`_fit3_numba`) is used. The offset is clipped to half a voxel inside the lags
    the chosen fit read (1.5 voxel for five samples, 2.5 for seven: the overlap correction
    moves a wide peak's vertex up to ``2 sigma**2 / w``, over a voxel, from the raw
    correlation's highest sample), and to ``THREE_POINT_BOUND_VOX`` for the 3-point fit.
    """
    h = HALF_SPAN
    u = np.empty(2 * h + 1)
    for q in range(2 * h + 1):
        f = 1.0
        if overlap:
            f = max(1.0 - abs(lag0 + q - h) / w, MIN_OVERLAP)
        u[q] = v[q] / f
    frac = _fit3_numba(u[h - 1], u[h], u[h + 1], gaussian)
    bound = THREE_POINT_BOUND_VOX
    if broad and gaussian and w >= MIN_BROAD_WINDOW and _positive(u, h - 2, 5):
        f5, sigma2 = _fit_log_numba(u, h - 2, 5)
        if sigma2 >= BROAD_SIGMA_VOX * BROAD_SIGMA_VOX:
            frac = f5
            bound = h - 1.5
            if (sigma2 >= WIDE_SIGMA_VOX * WIDE_SIGMA_VOX and w >= MIN_WIDE_WINDOW
                    and _positive(u, 0, 2 * h + 1)):
                f7, sigma7 = _fit_log_numba(u, 0, 2 * h + 1)
                if sigma7 >= WIDE_SIGMA_VOX * WIDE_SIGMA_VOX:
                    frac = f7
                    bound = h - 0.5
    return min(bound, max(-bound, frac))


@numba.njit(cache=True)
def refine_peaks(corr, gaussian, overlap, broad):
    # serial: little work per window, while parallel loops compile much longer
    n, wz, wy, wx = corr.shape
    disp = np.empty((n, 3), dtype=np.float64)
    for k in range(n):
        c = corr[k]
        best = -np.inf
        bi = 0
        bj = 0
        bm = 0
        for i in range(wz):
            for j in range(wy):
                for m in range(wx):
                    if c[i, j, m] > best:
                        best = c[i, j, m]
                        bi = i
                        bj = j
                        bm = m
        li = bi - wz if 2 * bi >= wz else bi
        lj = bj - wy if 2 * bj >= wy else bj
        lm = bm - wx if 2 * bm >= wx else bm
        h = HALF_SPAN
        v = np.empty(2 * h + 1)
        for q in range(2 * h + 1):
            v[q] = c[(bi + q - h) % wz, bj, bm]
        disp[k, 0] = li + _refine_axis_numba(v, li, wz, gaussian, overlap, broad)
        for q in range(2 * h + 1):
            v[q] = c[bi, (bj + q - h) % wy, bm]
        disp[k, 1] = lj + _refine_axis_numba(v, lj, wy, gaussian, overlap, broad)
        for q in range(2 * h + 1):
            v[q] = c[bi, bj, (bm + q - h) % wx]
        disp[k, 2] = lm + _refine_axis_numba(v, lm, wx, gaussian, overlap, broad)
    return disp


def _fit_log_numpy(u, first, count):
    """NumPy twin of :func:`_fit_log_numba` on the columns of ``u`` (2·HALF_SPAN + 1, n).

    Returns ``(vertex, sigma2, ok)`` with ``ok`` where every sample is positive and the fit
    is concave.
    """
    sel = u[first:first + count]
    positive = np.all(sel > 0.0, axis=0)
    lu = np.log(np.where(positive, sel, 1.0))
    x = (np.arange(first, first + count) - float(HALF_SPAN))[:, None]
    wt = np.where(positive, sel, 0.0) ** 2
    s = [np.sum(wt * x**p, axis=0) for p in range(5)]
    t = [np.sum(wt * x**p * lu, axis=0) for p in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        det = (s[0] * (s[2] * s[4] - s[3] * s[3]) - s[1] * (s[1] * s[4] - s[3] * s[2])
               + s[2] * (s[1] * s[3] - s[2] * s[2]))
        bb = (s[0] * (t[1] * s[4] - s[3] * t[2]) - t[0] * (s[1] * s[4] - s[3] * s[2])
              + s[2] * (s[1] * t[2] - t[1] * s[2])) / det
        cc = (s[0] * (s[2] * t[2] - t[1] * s[3]) - s[1] * (s[1] * t[2] - t[1] * s[2])
              + t[0] * (s[1] * s[3] - s[2] * s[2])) / det
        ok = positive & (det != 0.0) & (cc < 0.0)
        sigma2 = np.where(ok, -1.0 / (2.0 * cc), np.nan)
        vertex = np.where(ok, -bb / (2.0 * cc), np.nan)
    return vertex, sigma2, ok


def refine_peaks_numpy(corr, gaussian, overlap, broad):
    n, wz, wy, wx = corr.shape
    best_idx = np.argmax(corr.reshape(n, -1), axis=1)
    peak = np.unravel_index(best_idx, (wz, wy, wx))
    k = np.arange(n)
    h = HALF_SPAN
    disp = np.empty((n, 3))
    for axis, w in enumerate((wz, wy, wx)):
        b = peak[axis]
        lag0 = np.where(2 * b >= w, b - w, b).astype(np.float64)
        u = np.empty((2 * h + 1, n))
        for q in range(2 * h + 1):
            idx = list(peak)
            idx[axis] = (b + q - h) % w
            f = np.maximum(1.0 - np.abs(lag0 + q - h) / w, MIN_OVERLAP) if overlap else 1.0
            u[q] = corr[k, idx[0], idx[1], idx[2]].astype(np.float64) / f
        frac = _fit3_numpy(u[h - 1], u[h], u[h + 1], gaussian)
        bound = np.full(n, THREE_POINT_BOUND_VOX)
        if broad and gaussian and w >= MIN_BROAD_WINDOW:
            f5, s5, ok5 = _fit_log_numpy(u, h - 2, 5)
            broad_peak = ok5 & (s5 >= BROAD_SIGMA_VOX**2)
            frac = np.where(broad_peak, f5, frac)
            bound = np.where(broad_peak, h - 1.5, bound)
            if w >= MIN_WIDE_WINDOW:
                f7, s7, ok7 = _fit_log_numpy(u, 0, 2 * h + 1)
                wide = (broad_peak & (s5 >= WIDE_SIGMA_VOX**2) & ok7
                        & (s7 >= WIDE_SIGMA_VOX**2))
                frac = np.where(wide, f7, frac)
                bound = np.where(wide, h - 0.5, bound)
        disp[:, axis] = lag0 + np.clip(frac, -bound, bound)
    return disp
