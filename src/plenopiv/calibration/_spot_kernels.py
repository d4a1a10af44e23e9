"""Numba kernels for sub-pixel spot centres, each with a plain-NumPy twin.

The public wrapper :func:`plenopiv.calibration.spot_detection.detect_spots` validates the image and
resolves every option; these kernels take only contiguous arrays and scalars. The twins
(``*_numpy``) compute the same numbers with vectorised NumPy and exist so that the tests can
check the kernels against an independent implementation.

Pixel convention (see :mod:`plenopiv.conventions`): ``(row, col)``, the centre of the
top-left pixel at (0, 0); pixel ``(r, c)`` covers ``[r - 0.5, r + 0.5] x [c - 0.5, c + 0.5]``.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# ----------------------------------------------------------------------------------------------
# Iterative thresholded centroid in a circular window
# ----------------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _window_bounds(cy, cx, reach, n_rows, n_cols):
    """Rows ``r0..r1`` and columns ``c0..c1`` within ``reach`` px of ``(cy, cx)``, in the image."""
    r0 = max(int(math.ceil(cy - reach)), 0)
    r1 = min(int(math.floor(cy + reach)), n_rows - 1)
    c0 = max(int(math.ceil(cx - reach)), 0)
    c1 = min(int(math.floor(cx + reach)), n_cols - 1)
    return r0, r1, c0, c1


@numba.njit(cache=True)
def _peak_3x3_mean(image, r0, r1, c0, c1, cy, cx, radius2):
    """Largest 3 x 3 mean among the pixels of the window (hot-pixel-robust peak height)."""
    n_rows, n_cols = image.shape
    best = -np.inf
    for r in range(r0, r1 + 1):
        dr = r - cy
        for c in range(c0, c1 + 1):
            dc = c - cx
            if dr * dr + dc * dc > radius2:
                continue
            s = 0.0
            n = 0
            for rr in range(max(r - 1, 0), min(r + 2, n_rows)):
                for cc in range(max(c - 1, 0), min(c + 2, n_cols)):
                    s += image[rr, cc]
                    n += 1
            m = s / n
            if m > best:
                best = m
    return best


@numba.njit(cache=True)
def centroid_refine_numba(image, start, radius, threshold, max_iter, tol):
    """Refine each spot centre by an iterative thresholded centroid (numba kernel).

    For every start position the window is the set of pixels whose centres lie within
    ``radius`` of the current estimate. Inside it the weight of a pixel is
    ``max(I - threshold * P, 0)`` with ``P`` the largest 3 x 3 mean in the first window (a
    peak height that one hot pixel cannot inflate); the new estimate is the weighted mean of
    the pixel positions. The window is re-centred on the estimate until it moves less than
    ``tol`` or ``max_iter`` passes are done. A point-symmetric spot is a fixed point of this
    iteration, so the estimate carries no window bias.

    Parameters
    ----------
    image : ndarray of float32 or float64, shape (R, C)
        Background-subtracted image.
    start : ndarray of float64, shape (N, 2)
        First estimates ``(row, col)``, px.
    radius : float
        Window radius, px.
    threshold : float
        Fraction of the spot's peak height below which a pixel has no weight.
    max_iter : int
        Largest number of re-centring passes.
    tol : float
        Convergence tolerance, px.

    Returns
    -------
    centres : ndarray, shape (N, 2)
        ``(row, col)`` px; NaN where the window held no positive weight.
    intensity : ndarray, shape (N,)
        Sum of the weights (image units x px).
    area : ndarray, shape (N,)
        Effective area, px: the sum of weights over the largest weight (1 for a lone pixel).
    peak : ndarray, shape (N,)
        Peak height ``P`` (image units).
    """
    n = start.shape[0]
    n_rows, n_cols = image.shape
    centres = np.full((n, 2), np.nan)
    intensity = np.zeros(n)
    area = np.zeros(n)
    peak = np.zeros(n)
    radius2 = radius * radius
    for k in range(n):
        cy = start[k, 0]
        cx = start[k, 1]
        ok = False
        p = 0.0
        level = 0.0
        for it in range(max_iter):
            r0, r1, c0, c1 = _window_bounds(cy, cx, radius, n_rows, n_cols)
            if r0 > r1 or c0 > c1:
                ok = False
                break
            if it == 0:
                p = _peak_3x3_mean(image, r0, r1, c0, c1, cy, cx, radius2)
                level = threshold * p
            sw = 0.0
            swr = 0.0
            swc = 0.0
            wmax = 0.0
            for r in range(r0, r1 + 1):
                dr = r - cy
                for c in range(c0, c1 + 1):
                    dc = c - cx
                    if dr * dr + dc * dc > radius2:
                        continue
                    w = image[r, c] - level
                    if w > 0.0:
                        sw += w
                        swr += w * r
                        swc += w * c
                        if w > wmax:
                            wmax = w
            if sw <= 0.0 or p <= 0.0:
                ok = False
                break
            ny = swr / sw
            nx = swc / sw
            ok = True
            intensity[k] = sw
            area[k] = sw / wmax
            peak[k] = p
            moved = abs(ny - cy) + abs(nx - cx)
            cy = ny
            cx = nx
            if moved < tol:
                break
        if ok:
            centres[k, 0] = cy
            centres[k, 1] = cx
    return centres, intensity, area, peak


def _window_stack(image, centre, half):
    """Square windows of half-size ``half`` around ``round(centre)``, padded with NaN outside."""
    n_rows, n_cols = image.shape
    pad = np.pad(np.asarray(image, dtype=np.float64), half + 1, constant_values=np.nan)
    base = np.floor(centre).astype(np.int64)
    offs = np.arange(-half, half + 2)
    rows = base[:, 0, None] + offs[None, :]
    cols = base[:, 1, None] + offs[None, :]
    rows_p = np.clip(rows + half + 1, 0, pad.shape[0] - 1)
    cols_p = np.clip(cols + half + 1, 0, pad.shape[1] - 1)
    win = pad[rows_p[:, :, None], cols_p[:, None, :]]
    return win, rows.astype(np.float64), cols.astype(np.float64)


def centroid_refine_numpy(image, start, radius, threshold, max_iter, tol):
    """Plain-NumPy twin of :func:`centroid_refine_numba` (same arguments, same results)."""
    image = np.asarray(image, dtype=np.float64)
    n_rows, n_cols = image.shape
    start = np.asarray(start, dtype=np.float64).reshape(-1, 2)
    n = start.shape[0]
    half = int(math.ceil(radius)) + 1
    # 3 x 3 means with the image edge handled as in the kernel (mean of the pixels inside)
    ones = np.ones_like(image)
    pad_i = np.pad(image, 1)
    pad_o = np.pad(ones, 1)
    s = sum(
        pad_i[1 + a : 1 + a + n_rows, 1 + b : 1 + b + n_cols]
        for a in (-1, 0, 1)
        for b in (-1, 0, 1)
    )
    m = sum(
        pad_o[1 + a : 1 + a + n_rows, 1 + b : 1 + b + n_cols]
        for a in (-1, 0, 1)
        for b in (-1, 0, 1)
    )
    mean3 = s / m

    centres = np.full((n, 2), np.nan)
    intensity = np.zeros(n)
    area = np.zeros(n)
    peak = np.zeros(n)
    cur = start.copy()
    active = np.ones(n, dtype=bool)
    level_all = np.zeros(n)
    peak_all = np.zeros(n)
    for it in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        c = cur[idx]
        win, rows, cols = _window_stack(image, c, half)
        dr = rows - c[:, 0, None]
        dc = cols - c[:, 1, None]
        inside = (dr[:, :, None] ** 2 + dc[:, None, :] ** 2 <= radius * radius) & np.isfinite(win)
        if it == 0:
            win3, _, _ = _window_stack(mean3, c, half)
            peak_all[idx] = np.where(inside, win3, -np.inf).max(axis=(1, 2))
            level_all[idx] = threshold * peak_all[idx]
        p = peak_all[idx]
        level = level_all[idx]
        w = np.where(inside, win - level[:, None, None], 0.0)
        w = np.where(w > 0.0, w, 0.0)
        sw = w.sum(axis=(1, 2))
        failed = (sw <= 0.0) | (p <= 0.0) | ~np.any(inside, axis=(1, 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            ny = (w * rows[:, :, None]).sum(axis=(1, 2)) / sw
            nx = (w * cols[:, None, :]).sum(axis=(1, 2)) / sw
            ar = sw / w.max(axis=(1, 2))
        good = ~failed
        gi = idx[good]
        intensity[gi] = sw[good]
        area[gi] = ar[good]
        peak[gi] = p[good]
        moved = np.abs(ny - c[:, 0]) + np.abs(nx - c[:, 1])
        cur[gi, 0] = ny[good]
        cur[gi, 1] = nx[good]
        centres[gi] = cur[gi]
        # a failure ends that spot with NaN, as in the kernel
        centres[idx[failed]] = np.nan
        active[idx[failed]] = False
        active[gi[moved[good] < tol]] = False
    return centres, intensity, area, peak


# ----------------------------------------------------------------------------------------------
# Least-squares fit of a circular 2-D Gaussian plus a constant
# ----------------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _solve5(a, b):
    """Solve the symmetric 5 x 5 system ``a x = b`` by Gaussian elimination with pivoting."""
    m = a.copy()
    v = b.copy()
    n = 5
    for i in range(n):
        piv = i
        for j in range(i + 1, n):
            if abs(m[j, i]) > abs(m[piv, i]):
                piv = j
        if m[piv, i] == 0.0:
            return v * np.nan
        if piv != i:
            for j in range(n):
                t = m[i, j]
                m[i, j] = m[piv, j]
                m[piv, j] = t
            t = v[i]
            v[i] = v[piv]
            v[piv] = t
        for j in range(i + 1, n):
            f = m[j, i] / m[i, i]
            for q in range(i, n):
                m[j, q] -= f * m[i, q]
            v[j] -= f * v[i]
    x = np.zeros(n)
    for i in range(n - 1, -1, -1):
        s = v[i]
        for q in range(i + 1, n):
            s -= m[i, q] * x[q]
        x[i] = s / m[i, i]
    return x


@numba.njit(cache=True)
def _disc_pixels(image, rc, cc, h, radius2, pr, pc, pv):
    """Gather the pixels within ``sqrt(radius2)`` of pixel ``(rc, cc)`` into ``pr, pc, pv``.

    Returns their number and the smallest and largest value among them.
    """
    n_rows, n_cols = image.shape
    npx = 0
    vmin = np.inf
    vmax = -np.inf
    for r in range(max(rc - h, 0), min(rc + h, n_rows - 1) + 1):
        for c in range(max(cc - h, 0), min(cc + h, n_cols - 1) + 1):
            if (r - rc) * (r - rc) + (c - cc) * (c - cc) <= radius2:
                pr[npx] = r
                pc[npx] = c
                v = image[r, c]
                pv[npx] = v
                vmin = min(vmin, v)
                vmax = max(vmax, v)
                npx += 1
    return npx, vmin, vmax


@numba.njit(cache=True)
def _gauss_cost(p, pr, pc, pv, npx):
    """Sum of squared residuals of the Gaussian ``p = (A, row0, col0, s, B)`` on the pixels."""
    cost = 0.0
    for i in range(npx):
        dr = pr[i] - p[1]
        dc = pc[i] - p[2]
        res = p[0] * math.exp(-(dr * dr + dc * dc) / (2.0 * p[3] * p[3])) + p[4] - pv[i]
        cost += res * res
    return cost


@numba.njit(cache=True)
def _gauss_normal_equations(p, pr, pc, pv, npx, jac):
    """``J^T J`` (5 x 5) and ``J^T r`` (5) of the Gaussian ``p`` on the pixels."""
    jtj = np.zeros((5, 5))
    jtr = np.zeros(5)
    for i in range(npx):
        dr = pr[i] - p[1]
        dc = pc[i] - p[2]
        s2 = p[3] * p[3]
        d2 = dr * dr + dc * dc
        e = math.exp(-d2 / (2.0 * s2))
        res = p[0] * e + p[4] - pv[i]
        jac[i, 0] = e
        jac[i, 1] = p[0] * e * dr / s2
        jac[i, 2] = p[0] * e * dc / s2
        jac[i, 3] = p[0] * e * d2 / (s2 * p[3])
        jac[i, 4] = 1.0
        for a in range(5):
            jtr[a] += jac[i, a] * res
            for b in range(5):
                jtj[a, b] += jac[i, a] * jac[i, b]
    return jtj, jtr


@numba.njit(cache=True)
def _lm_step(p, cost, lam, jtj, jtr, pr, pc, pv, npx):
    """One Levenberg-Marquardt step, the damping ``lam`` raised tenfold until the cost falls.

    Returns the new parameters, cost and damping, whether a step was taken (at most 10
    tries) and whether it moved the centre by less than 1e-6 px.
    """
    for _try in range(10):
        a_mat = jtj.copy()
        for a in range(5):
            a_mat[a, a] += lam * jtj[a, a]
        step = _solve5(a_mat, -jtr)
        if not np.all(np.isfinite(step)):
            lam *= 10.0
            continue
        q = p + step
        if q[3] <= 0.0:
            lam *= 10.0
            continue
        new_cost = _gauss_cost(q, pr, pc, pv, npx)
        if new_cost <= cost:
            converged = abs(step[1]) + abs(step[2]) < 1e-6
            return q, new_cost, max(lam / 10.0, 1e-12), True, converged
        lam *= 10.0
    return p, cost, lam, False, False


@numba.njit(cache=True)
def gaussian_fit_numba(image, start, sigma0, radius, max_iter):
    """Levenberg-Marquardt fit of ``A exp(-|x - x0|^2 / (2 s^2)) + B`` to each spot (kernel).

    The pixels are those whose centres lie within ``radius`` of ``round(start)``; they stay
    fixed during the fit.

    Parameters
    ----------
    image : ndarray of float32 or float64, shape (R, C)
        Background-subtracted image.
    start : ndarray of float64, shape (N, 2)
        First centres ``(row, col)``, px (the centroids).
    sigma0 : ndarray of float64, shape (N,)
        First Gaussian standard deviations, px.
    radius : float
        Window radius, px.
    max_iter : int
        Largest number of Levenberg-Marquardt steps.

    Returns
    -------
    params : ndarray, shape (N, 5)
        ``(A, row0, col0, s, B)``: amplitude, centre (px), standard deviation (px), offset.
        NaN where the fit failed (too few pixels, singular system, centre left the window).
    """
    n = start.shape[0]
    out = np.full((n, 5), np.nan)
    h = int(math.ceil(radius))
    npx_max = (2 * h + 1) * (2 * h + 1)
    pr = np.empty(npx_max)
    pc = np.empty(npx_max)
    pv = np.empty(npx_max)
    jac = np.empty((npx_max, 5))
    for k in range(n):
        rc = int(math.floor(start[k, 0] + 0.5))
        cc = int(math.floor(start[k, 1] + 0.5))
        npx, vmin, vmax = _disc_pixels(image, rc, cc, h, radius * radius, pr, pc, pv)
        if npx < 8:
            continue
        p = np.array([vmax - vmin, start[k, 0], start[k, 1], sigma0[k], vmin])
        lam = 1e-3
        cost = _gauss_cost(p, pr, pc, pv, npx)
        for _ in range(max_iter):
            jtj, jtr = _gauss_normal_equations(p, pr, pc, pv, npx, jac)
            p, cost, lam, improved, converged = _lm_step(p, cost, lam, jtj, jtr, pr, pc, pv,
                                                         npx)
            if not improved or converged:
                break
        if abs(p[1] - rc) <= radius and abs(p[2] - cc) <= radius and p[0] > 0.0:
            out[k] = p
    return out


def gaussian_fit_numpy(image, start, sigma0, radius, max_iter):
    """Plain-NumPy twin of :func:`gaussian_fit_numba`, all spots at once (same results)."""
    image = np.asarray(image, dtype=np.float64)
    start = np.asarray(start, dtype=np.float64).reshape(-1, 2)
    n = start.shape[0]
    h = int(math.ceil(radius))
    centre = np.floor(start + 0.5)
    win, rows, cols = _window_stack(image, centre - 0.0, h)
    # _window_stack starts at floor(centre) - h; keep the 2h+1 square around the centre
    win = win[:, : 2 * h + 1, : 2 * h + 1]
    rows = rows[:, : 2 * h + 1]
    cols = cols[:, : 2 * h + 1]
    rr = np.broadcast_to(rows[:, :, None], win.shape)
    cc = np.broadcast_to(cols[:, None, :], win.shape)
    d2c = (rr - centre[:, 0, None, None]) ** 2 + (cc - centre[:, 1, None, None]) ** 2
    mask = (d2c <= radius * radius) & np.isfinite(win)
    v = np.where(mask, win, 0.0)
    npx = mask.sum(axis=(1, 2))
    vmin = np.where(mask, win, np.inf).min(axis=(1, 2))
    vmax = np.where(mask, win, -np.inf).max(axis=(1, 2))
    p = np.stack([vmax - vmin, start[:, 0], start[:, 1], np.asarray(sigma0, float), vmin], axis=1)
    ok = npx >= 8
    p[~ok] = np.nan

    def residual_and_jac(q):
        dr = rr - q[:, 1, None, None]
        dc = cc - q[:, 2, None, None]
        s2 = q[:, 3, None, None] ** 2
        d2 = dr * dr + dc * dc
        e = np.exp(-d2 / (2.0 * s2))
        a = q[:, 0, None, None]
        res = np.where(mask, a * e + q[:, 4, None, None] - v, 0.0)
        jac = np.stack(
            [
                e,
                a * e * dr / s2,
                a * e * dc / s2,
                a * e * d2 / (s2 * q[:, 3, None, None]),
                np.ones_like(e),
            ],
            axis=-1,
        )
        jac = np.where(mask[..., None], jac, 0.0)
        return res, jac

    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        res, _ = residual_and_jac(p)
        cost = (res**2).sum(axis=(1, 2))
        lam = np.full(n, 1e-3)
        active = ok.copy()
        for _ in range(max_iter):
            if not active.any():
                break
            res, jac = residual_and_jac(p)
            jtj = np.einsum("nrca,nrcb->nab", jac, jac)
            jtr = np.einsum("nrca,nrc->na", jac, res)
            improved = np.zeros(n, dtype=bool)
            converged = np.zeros(n, dtype=bool)
            pending = active.copy()
            for _try in range(10):
                if not pending.any():
                    break
                a_mat = jtj + lam[:, None, None] * np.einsum("nii->ni", jtj)[:, :, None] * np.eye(5)
                step = np.full((n, 5), np.nan)
                idx = np.flatnonzero(pending)
                for i in idx:  # a 5 x 5 solve per spot, as the kernel does
                    try:
                        step[i] = np.linalg.solve(a_mat[i], -jtr[i])
                    except np.linalg.LinAlgError:
                        pass
                q = p + step
                finite = np.all(np.isfinite(step), axis=1) & (q[:, 3] > 0.0)
                res_q, _ = residual_and_jac(np.where(finite[:, None], q, p))
                new_cost = (res_q**2).sum(axis=(1, 2))
                accept = pending & finite & (new_cost <= cost)
                converged |= accept & (np.abs(step[:, 1]) + np.abs(step[:, 2]) < 1e-6)
                p[accept] = q[accept]
                cost[accept] = new_cost[accept]
                lam[accept] = np.maximum(lam[accept] / 10.0, 1e-12)
                improved |= accept
                reject = pending & ~accept
                lam[reject] *= 10.0
                pending = reject
            active &= improved & ~converged
    inside = (np.abs(p[:, 1] - centre[:, 0]) <= radius) & (np.abs(p[:, 2] - centre[:, 1]) <= radius)
    good = ok & inside & (p[:, 0] > 0.0)
    p[~good] = np.nan
    return p


# ----------------------------------------------------------------------------------------------
# Background-subtracted window centroid (soft-edged circular window, annulus plane background)
# ----------------------------------------------------------------------------------------------


@numba.njit(cache=True)
def _solve3(a, b):
    """Solve the 3 x 3 system ``a x = b`` by Cramer's rule; NaN when singular."""
    det = (a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
           - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
           + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]))
    x = np.full(3, np.nan)
    if det == 0.0 or not np.isfinite(det):
        return x
    for k in range(3):
        m = a.copy()
        for i in range(3):
            m[i, k] = b[i]
        x[k] = (m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
                - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
                + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])) / det
    return x


@numba.njit(cache=True)
def _annulus_plane(image, cy, cx, r0, r1, c0, c1, bg_inner, bg_outer, a, rhs):
    """Background plane ``b0 + br dr + bc dc`` fitted to the annulus about ``(cy, cx)``.

    The pixels of rows ``r0..r1`` and columns ``c0..c1`` with ``bg_inner < d <= bg_outer``
    (px) are fitted by least squares; with fewer than 6 (or a singular system) the level is
    their mean and the slopes zero; with none, all three are zero. ``a`` (3 x 3) and ``rhs``
    (3) are work space, overwritten.
    """
    a[:, :] = 0.0
    rhs[:] = 0.0
    npx = 0
    for r in range(r0, r1 + 1):
        dr = r - cy
        for c in range(c0, c1 + 1):
            dc = c - cx
            d2 = dr * dr + dc * dc
            if d2 <= bg_inner * bg_inner or d2 > bg_outer * bg_outer:
                continue
            v = image[r, c]
            a[0, 0] += 1.0
            a[0, 1] += dr
            a[0, 2] += dc
            a[1, 1] += dr * dr
            a[1, 2] += dr * dc
            a[2, 2] += dc * dc
            rhs[0] += v
            rhs[1] += v * dr
            rhs[2] += v * dc
            npx += 1
    a[1, 0] = a[0, 1]
    a[2, 0] = a[0, 2]
    a[2, 1] = a[1, 2]
    if npx >= 6:
        x = _solve3(a, rhs)
        if np.isfinite(x[0]):
            return x[0], x[1], x[2]
    if npx > 0:
        return rhs[0] / npx, 0.0, 0.0
    return 0.0, 0.0, 0.0


@numba.njit(cache=True)
def _window_moments(image, cy, cx, r0, r1, c0, c1, radius, b0, br, bc):
    """Zeroth and first moments ``(s0, s_row, s_col)`` of the soft-windowed light above the plane.

    A pixel at distance ``d`` from ``(cy, cx)`` has the weight ``clip(radius + 0.5 - d, 0, 1)``.
    """
    s0 = 0.0
    sr = 0.0
    sc = 0.0
    lim = radius + 0.5
    for r in range(r0, r1 + 1):
        dr = r - cy
        for c in range(c0, c1 + 1):
            dc = c - cx
            d = math.sqrt(dr * dr + dc * dc)
            if d >= lim:
                continue
            w = min(lim - d, 1.0)
            v = w * (image[r, c] - (b0 + br * dr + bc * dc))
            s0 += v
            sr += v * dr
            sc += v * dc
    return s0, sr, sc


@numba.njit(cache=True)
def window_centroid_numba(image, start, radius, bg_inner, bg_outer, max_iter, tol):
    """First moment of each spot in a soft-edged circular window above a local plane (kernel).

    For the current estimate ``c`` a pixel at distance ``d`` from it has the window weight
    ``w = clip(radius + 0.5 - d, 0, 1)`` (about the fraction of the pixel inside the circle of
    radius ``radius``, so the window's own first moment follows ``c`` smoothly rather than in
    whole-pixel steps). The background is the least-squares plane through the pixels of the
    annulus ``bg_inner < d <= bg_outer`` (none when ``bg_outer <= bg_inner``: zero). The new
    estimate is ``c + sum(w (I - b) (x - c)) / sum(w (I - b))``, without any threshold or
    clipping of the weights, so a symmetric spot on any plane is a fixed point and noise
    enters without bias. Iterates until the estimate moves by less than ``tol``.

    Parameters
    ----------
    image : ndarray of float32 or float64, shape (R, C)
    start : ndarray of float64, shape (N, 2)
        First estimates ``(row, col)``, px.
    radius : float
        Window radius, px.
    bg_inner, bg_outer : float
        Radii of the background annulus, px.
    max_iter : int
    tol : float
        Convergence tolerance, px (sum of the two axes' moves).

    Returns
    -------
    centres : ndarray, shape (N, 2)
        ``(row, col)`` px; NaN where the windowed flux was not positive or the window left the
        image.
    flux : ndarray, shape (N,)
        ``sum(w (I - b))`` at the last estimate (image units x px).
    background : ndarray, shape (N,)
        The background plane's value at the centre (image units).
    """
    n = start.shape[0]
    n_rows, n_cols = image.shape
    centres = np.full((n, 2), np.nan)
    flux = np.zeros(n)
    background = np.zeros(n)
    reach = max(radius + 0.5, bg_outer)
    use_bg = bg_outer > bg_inner
    for k in range(n):
        a = np.zeros((3, 3))
        rhs = np.zeros(3)
        cy = start[k, 0]
        cx = start[k, 1]
        ok = False
        for _it in range(max_iter):
            r0, r1, c0, c1 = _window_bounds(cy, cx, reach, n_rows, n_cols)
            if r0 > r1 or c0 > c1:
                ok = False
                break
            b0, br, bc = 0.0, 0.0, 0.0
            if use_bg:
                b0, br, bc = _annulus_plane(image, cy, cx, r0, r1, c0, c1, bg_inner, bg_outer,
                                            a, rhs)
            s0, sr, sc = _window_moments(image, cy, cx, r0, r1, c0, c1, radius, b0, br, bc)
            if not s0 > 0.0:
                ok = False
                break
            ok = True
            flux[k] = s0
            background[k] = b0
            mr = sr / s0
            mc = sc / s0
            cy += mr
            cx += mc
            if abs(mr) + abs(mc) < tol:
                break
        if ok:
            centres[k, 0] = cy
            centres[k, 1] = cx
    return centres, flux, background


def window_centroid_numpy(image, start, radius, bg_inner, bg_outer, max_iter, tol):
    """Plain-NumPy twin of :func:`window_centroid_numba`, all spots at once (same results)."""
    image = np.asarray(image, dtype=np.float64)
    start = np.asarray(start, dtype=np.float64).reshape(-1, 2)
    n = start.shape[0]
    reach = max(radius + 0.5, bg_outer)
    half = int(math.ceil(reach)) + 1
    use_bg = bg_outer > bg_inner
    lim = radius + 0.5
    cur = start.copy()
    centres = np.full((n, 2), np.nan)
    flux = np.zeros(n)
    background = np.zeros(n)
    active = np.ones(n, dtype=bool)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        c = cur[idx]
        # windows around floor(c): rows floor(c) - half .. floor(c) + half + 1, NaN outside
        win, rows, cols = _window_stack(image, c, half)
        dr = rows[:, :, None] - c[:, 0, None, None]
        dc = cols[:, None, :] - c[:, 1, None, None]
        d2 = dr * dr + dc * dc
        inside = np.isfinite(win) & (d2 <= reach * reach + 1e-9)
        v = np.where(inside, win, 0.0)
        b0 = np.zeros(idx.size)
        br = np.zeros(idx.size)
        bc = np.zeros(idx.size)
        if use_bg:
            ann = inside & (d2 > bg_inner * bg_inner) & (d2 <= bg_outer * bg_outer)
            one = ann.astype(np.float64)
            cols3 = [one, np.where(ann, dr, 0.0), np.where(ann, dc, 0.0)]
            a = np.stack([np.stack([(p * q).sum(axis=(1, 2)) for q in cols3], -1)
                          for p in cols3], -2)
            rhs = np.stack([(p * v).sum(axis=(1, 2)) for p in cols3], -1)
            npx = one.sum(axis=(1, 2))
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = rhs[:, 0] / npx
            for i in range(idx.size):
                if npx[i] >= 6:
                    det = np.linalg.det(a[i])
                    if det != 0.0 and np.isfinite(det):
                        x = np.linalg.solve(a[i], rhs[i])
                        b0[i], br[i], bc[i] = x
                        continue
                if npx[i] > 0:
                    b0[i] = mean[i]
        d = np.sqrt(d2)
        w = np.where(inside & (d < lim), np.minimum(lim - d, 1.0), 0.0)
        val = w * (v - (b0[:, None, None] + br[:, None, None] * dr + bc[:, None, None] * dc))
        s0 = val.sum(axis=(1, 2))
        failed = ~(s0 > 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            mr = (val * dr).sum(axis=(1, 2)) / s0
            mc = (val * dc).sum(axis=(1, 2)) / s0
        good = ~failed
        gi = idx[good]
        flux[gi] = s0[good]
        background[gi] = b0[good]
        cur[gi, 0] += mr[good]
        cur[gi, 1] += mc[good]
        centres[gi] = cur[gi]
        centres[idx[failed]] = np.nan
        active[idx[failed]] = False
        active[gi[np.abs(mr[good]) + np.abs(mc[good]) < tol]] = False
    return centres, flux, background


@numba.njit(cache=True)
def radial_energy_numba(image, centres, r_max, bin_px):
    """Sum of ``image`` over the pixels of all spots, in rings of ``bin_px`` around each centre.

    Returns ``energy[k]``: the sum over every spot of the pixel values at distance
    ``[k, k + 1) * bin_px`` from its centre, for distances below ``r_max``; and ``count[k]``,
    the number of those pixels.
    """
    n_bins = int(math.ceil(r_max / bin_px))
    energy = np.zeros(n_bins)
    count = np.zeros(n_bins)
    n_rows, n_cols = image.shape
    for k in range(centres.shape[0]):
        cy = centres[k, 0]
        cx = centres[k, 1]
        r0 = max(int(math.ceil(cy - r_max)), 0)
        r1 = min(int(math.floor(cy + r_max)), n_rows - 1)
        c0 = max(int(math.ceil(cx - r_max)), 0)
        c1 = min(int(math.floor(cx + r_max)), n_cols - 1)
        for r in range(r0, r1 + 1):
            for c in range(c0, c1 + 1):
                d = math.sqrt((r - cy) ** 2 + (c - cx) ** 2)
                if d < r_max:
                    b = int(d / bin_px)
                    if b < n_bins:
                        energy[b] += image[r, c]
                        count[b] += 1.0
    return energy, count


def radial_energy_numpy(image, centres, r_max, bin_px):
    """Plain-NumPy twin of :func:`radial_energy_numba`."""
    image = np.asarray(image, dtype=np.float64)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    n_bins = int(math.ceil(r_max / bin_px))
    half = int(math.ceil(r_max)) + 1
    win, rows, cols = _window_stack(image, centres, half)
    d = np.sqrt((rows[:, :, None] - centres[:, 0, None, None]) ** 2
                + (cols[:, None, :] - centres[:, 1, None, None]) ** 2)
    ok = np.isfinite(win) & (d < r_max)
    b = np.minimum((d[ok] / bin_px).astype(np.int64), n_bins)
    energy = np.bincount(b, win[ok], minlength=n_bins + 1)[:n_bins]
    count = np.bincount(b, minlength=n_bins + 1)[:n_bins].astype(np.float64)
    return energy, count
