"""numba kernels behind :mod:`plenopiv.particles.bundle` (private; arrays and scalars only).

Rays are lines ``(u, -S_o) -> (X_f, 0)`` of the light field, stored sorted by lenslet (rays
``rptr[k]:rptr[k + 1]`` belong to lenslet k, so a lenslet's rays are read contiguously); a
particle's candidate lenslets are a CSR table (``lptr``, ``lidx``). The plain NumPy twin is
the ``engine="numpy"`` path of :func:`plenopiv.particles.bundle.bundle_positions`; the tests
run both.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True)
def _miss(u, xf, i, t, cx, cy):
    """Lateral distance at the particle's depth (t = (S_o + Z)/S_o) of ray i from (cx, cy)."""
    x = u[i, 0] * (1.0 - t) + xf[i, 0] * t - cx
    y = u[i, 1] * (1.0 - t) + xf[i, 1] * t - cy
    return math.sqrt(x * x + y * y)


@numba.njit(cache=True)
def _window(u, xf, first, last, t, cx, cy, r, margin):
    """Return ``(start, lo_y, lo_x, hi_x)``: where a lenslet's candidate rays begin.

    A selected ray's u satisfies ``|u (1 - t) + X_f t - c| <= r``, so it lies within
    ``h = r / |1 - t|`` of ``u* = (c - X_f t) / (1 - t)``. A lenslet's rays run down in
    aperture y (pixel rows in order), so the first candidate is found by bisection on
    ``u_y <= u*_y + h``, and the scan stops below ``u*_y - h``; ``margin`` covers the pixels'
    edge-centroid offsets.
    """
    s = 1.0 - t
    if abs(s) < 1e-12:
        return first, -np.inf, -np.inf, np.inf
    h = r / abs(s) + margin
    uy = (cy - xf[first, 1] * t) / s
    ux = (cx - xf[first, 0] * t) / s
    hi = uy + h
    a, b = first, last
    while a < b:
        mid = (a + b) // 2
        if u[mid, 1] > hi:
            a = mid + 1
        else:
            b = mid
    return a, uy - h, ux - h, ux + h


@numba.njit(cache=True)
def _lenslet_rays(u, xf, weight, first, last, t, cx, cy, r, margin, rays, share):
    """Rays ``first:last`` of one lenslet passing within ``r`` of ``(cx, cy)`` at depth t.

    Only rays whose pixel carries weight (``weight[i] > 0``) are taken. Fills ``rays[:n]``
    with their indices and ``share[:n]`` with the cone profile ``1 - m/r`` of their miss
    distances m; returns n. ``rays`` and ``share`` must hold n entries (``last - first``
    always suffice).
    """
    n = 0
    if last == first:
        return n
    start, lo, lo_x, hi_x = _window(u, xf, first, last, t, cx, cy, r, margin)
    for i in range(start, last):
        if u[i, 1] < lo:
            break
        if u[i, 0] < lo_x or u[i, 0] > hi_x or not weight[i] > 0.0:
            continue
        m = _miss(u, xf, i, t, cx, cy)
        if m <= r:
            rays[n] = i
            share[n] = max(1.0 - m / r, 0.0)
            n += 1
    return n


@numba.njit(cache=True)
def _max_lenslet_rays(rptr):
    """Most rays of one lenslet (buffer size of :func:`_lenslet_rays`)."""
    most = 0
    for k in range(rptr.shape[0] - 1):
        most = max(most, rptr[k + 1] - rptr[k])
    return most


@numba.njit(cache=True, nogil=True)
def count_rays(centre, radius, lptr, lidx, rptr, u, xf, so, margin, weight, p0, p1, counts):
    """Count the rays of particles ``p0:p1`` that a solve's passes read (first of two passes).

    The rays of :func:`_lenslet_rays` (within ``radius[p]`` of ``centre[p]``) whose pixel
    carries weight (``weight[ray] > 0``: a ray without weight adds nothing to any sum of the
    solve). ``counts[a]`` is set to the rays of candidate ``a`` (``lptr[p0] <= a <
    lptr[p1]``); :func:`fill_rays` then writes them where the caller's cumulative counts say.
    Serial and without the GIL: blocks of particles run on threads
    (:func:`plenopiv.particles.bundle.ray_selection`).
    """
    most = _max_lenslet_rays(rptr)
    rays = np.empty(max(most, 1), np.int64)
    share = np.empty(max(most, 1))
    for p in range(p0, p1):
        t = (so + centre[p, 2]) / so
        for a in range(lptr[p], lptr[p + 1]):
            k = lidx[a]
            counts[a] = _lenslet_rays(u, xf, weight, rptr[k], rptr[k + 1], t, centre[p, 0],
                                      centre[p, 1], radius[p], margin, rays, share)


@numba.njit(cache=True, nogil=True)
def fill_rays(centre, radius, lptr, lidx, rptr, u, xf, so, margin, weight, p0, p1, cptr,
              rays, share):
    """Write the rays :func:`count_rays` counted (second pass).

    Candidate ``a``'s go to ``cptr[a]:cptr[a + 1]`` of ``rays`` (indices) and ``share``
    (cone profile ``1 - m/r``), in candidate then ray order. The same arithmetic selects the
    same rays, so each candidate fills its span exactly.
    """
    for p in range(p0, p1):
        t = (so + centre[p, 2]) / so
        for a in range(lptr[p], lptr[p + 1]):
            k = lidx[a]
            _lenslet_rays(u, xf, weight, rptr[k], rptr[k + 1], t, centre[p, 0], centre[p, 1],
                          radius[p], margin, rays[cptr[a]:], share[cptr[a]:])


@numba.njit(cache=True)
def selected_totals(sptr, share, bright, rays, total):
    """Add every particle's expected share ``B (1 - m/r)`` of each selected ray to ``total``.

    Particle p's rays are ``rays[sptr[p]:sptr[p + 1]]`` (:func:`fill_rays`); ``total``
    (P,) is accumulated in place.
    """
    for p in range(sptr.shape[0] - 1):
        for j in range(sptr[p], sptr[p + 1]):
            total[rays[j]] += share[j] * bright[p]


@numba.njit(cache=True)
def selected_normal_equations(sptr, rays, share, bright, u, xf, so, weight, total, normal,
                              rhs, nrays):
    """:func:`normal_equations` on the rays :func:`fill_rays` kept (same sums).

    Serial, as :func:`selected_covariance_sums`: a call is short, and parallel loops would
    compile much longer.
    """
    for p in range(sptr.shape[0] - 1):
        d = np.empty(3)
        a = np.empty(3)
        b = bright[p]
        for j in range(sptr[p], sptr[p + 1]):
            i = rays[j]
            w = weight[i] * share[j] * b / total[i] if total[i] > 0.0 else 0.0
            if w <= 0.0:
                continue
            nrays[p] += 1
            _ray(u, xf, so, i, d, a)
            da = d[0] * a[0] + d[1] * a[1] + d[2] * a[2]
            for e in range(3):
                for c in range(3):
                    normal[p, e, c] += w * ((1.0 if e == c else 0.0) - d[e] * d[c])
                rhs[p, e] += w * (a[e] - d[e] * da)


@numba.njit(cache=True)
def _ray(u, xf, so, i, d, a):
    """Fill ``d`` with ray i's unit direction and ``a`` with its lens-plane point."""
    d[0] = xf[i, 0] - u[i, 0]
    d[1] = xf[i, 1] - u[i, 1]
    d[2] = so
    n = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    for j in range(3):
        d[j] /= n
    a[0], a[1], a[2] = u[i, 0], u[i, 1], -so


@numba.njit(cache=True)
def _ray_weights(rays, share, n, b, weight, total):
    """Turn shares into the rays' weights ``weight[ray] B share / total[ray]`` (in place)."""
    for j in range(n):
        i = rays[j]
        share[j] = weight[i] * share[j] * b / total[i] if total[i] > 0.0 else 0.0


@numba.njit(cache=True)
def selected_covariance_sums(lptr, cptr, sel, share, bright, u, xf, so, weight, total, point,
                             footprint, meat_r, meat_q, nlens):
    """Accumulate the two meats of the bundle covariance, per particle, by lenslet.

    The rays of the last solve (:func:`fill_rays`: candidate lenslet ``a`` of particle p,
    ``lptr[p] <= a < lptr[p + 1]``, holds rays ``sel[cptr[a]:cptr[a + 1]]`` with their cone
    shares ``share``), ``point`` is the
    solution. ``meat_r = sum_k g_k g_k^T``; ``meat_q = (t b)^2/12 sum_k (S_k[:, :2]
    S_k[:2, :] + v_k v_k^T / var_k)`` with ``S_k = sum w M``, ``v_k = sum w M (dtheta, 0)``;
    ``nlens`` counts the lenslets with weight (see
    :func:`plenopiv.particles.bundle.bundle_positions`).
    Serial: a parallel loop gains little here and compiles about twice as long.
    """
    most = 0
    for a in range(cptr.shape[0] - 1):
        most = max(most, cptr[a + 1] - cptr[a])
    for p in range(point.shape[0]):
        tp = (so + point[p, 2]) / so
        var_q = (tp * footprint) ** 2 / 12.0
        d = np.empty(3)
        a = np.empty(3)
        g = np.empty(3)
        s = np.empty((3, 3))
        v = np.empty(3)
        res = np.empty(3)
        rays = np.empty(most, np.int64)
        w = np.empty(most)
        for q in range(lptr[p], lptr[p + 1]):
            nk = cptr[q + 1] - cptr[q]
            for j in range(nk):
                rays[j] = sel[cptr[q] + j]
                w[j] = share[cptr[q] + j]
            _ray_weights(rays, w, nk, bright[p], weight, total)
            # the lenslet's weight and mean slope
            wk = 0.0
            tx = 0.0
            ty = 0.0
            for j in range(nk):
                if w[j] <= 0.0:
                    continue
                _ray(u, xf, so, rays[j], d, a)
                wk += w[j]
                tx += w[j] * d[0] / d[2]
                ty += w[j] * d[1] / d[2]
            if wk <= 0.0:
                continue
            nlens[p] += 1
            tx /= wk
            ty /= wk
            g[:] = 0.0
            s[:, :] = 0.0
            v[:] = 0.0
            var_t = 0.0
            for j in range(nk):
                if w[j] <= 0.0:
                    continue
                _ray(u, xf, so, rays[j], d, a)
                for e in range(3):
                    res[e] = point[p, e] - a[e]
                dr = d[0] * res[0] + d[1] * res[1] + d[2] * res[2]
                dtx = d[0] / d[2] - tx
                dty = d[1] / d[2] - ty
                var_t += w[j] * (dtx * dtx + dty * dty)
                for e in range(3):
                    g[e] += w[j] * (res[e] - d[e] * dr)
                    for c in range(3):
                        s[e, c] += w[j] * ((1.0 if e == c else 0.0) - d[e] * d[c])
                    me = (1.0 if e == 0 else 0.0) * dtx + (1.0 if e == 1 else 0.0) * dty \
                        - d[e] * (d[0] * dtx + d[1] * dty)
                    v[e] += w[j] * me
            var_t /= wk
            for e in range(3):
                for c in range(3):
                    meat_r[p, e, c] += g[e] * g[c]
                    lat = s[e, 0] * s[0, c] + s[e, 1] * s[1, c]
                    vv = v[e] * v[c] / var_t if var_t > 1e-12 else 0.0
                    meat_q[p, e, c] += var_q * (lat + vv)


@numba.njit(cache=True)
def _overlap(m, wa, wb):
    """Overlap length of intervals of widths ``wa`` (centred 0) and ``wb`` (centred m)."""
    lo = max(-0.5 * wa, m - 0.5 * wb)
    hi = min(0.5 * wa, m + 0.5 * wb)
    return max(hi - lo, 0.0)


@numba.njit(cache=True, parallel=True)
def best_grid_offsets(ptr, u, xf, v, amp, pos, depth, lateral, so, cell, footprint, excess,
                      choice):
    """Set ``choice[p]`` to the offset of least misfit on a joint depth x lateral grid.

    The grid is every ``(lateral[ix], lateral[iy], depth[iz])``, row ``k = (iz n_l + ix) n_l
    + iy`` of :func:`plenopiv.particles.forward._grid_offsets` (n_l = len(lateral), odd;
    len(depth) odd): the zero offset is row K // 2, tried first and kept on ties. Pixels
    ``ptr[p]:ptr[p + 1]`` of ``u``, ``xf`` (P, 2), ``v`` (P,) belong to particle p; the misfit
    is that of :func:`plenopiv.particles.forward.refine_positions` with the amplitude
    ``amp[p]``. A pixel's overlap along x depends on the x offset and the depth only (along y
    likewise), so each depth computes ``2 n_l`` overlaps per pixel for its ``n_l²`` offsets.
    """
    nl = lateral.shape[0]
    nz = depth.shape[0]
    n_off = nz * nl * nl
    centre = n_off // 2
    for p in numba.prange(pos.shape[0]):
        a = amp[p]
        cap = excess * a
        cost = np.zeros(n_off)
        ox = np.empty(nl)
        oy = np.empty(nl)
        for iz in range(nz):
            t = (so + (pos[p, 2] + depth[iz])) / so
            wa = max(cell * abs(1.0 - t), 1e-9 * cell)
            wb = footprint * abs(t)
            base = iz * nl * nl
            for i in range(ptr[p], ptr[p + 1]):
                mx = u[i, 0] * (1.0 - t) + xf[i, 0] * t
                my = u[i, 1] * (1.0 - t) + xf[i, 1] * t
                for j in range(nl):
                    ox[j] = _overlap(mx - (pos[p, 0] + lateral[j]), wa, wb)
                    oy[j] = _overlap(my - (pos[p, 1] + lateral[j]), wa, wb)
                for jx in range(nl):
                    for jy in range(nl):
                        r = v[i] - a * (ox[jx] * oy[jy] / (wa * wa))
                        if r > 0.0:
                            r = min(r, cap)
                        cost[base + jx * nl + jy] += r * r
        best = np.inf
        for j in range(n_off):
            k = centre if j == 0 else (j - 1 if j <= centre else j)
            if cost[k] < best:
                best = cost[k]
                iz = k // (nl * nl)
                jx = (k // nl) % nl
                choice[p, 0] = lateral[jx]
                choice[p, 1] = lateral[k % nl]
                choice[p, 2] = depth[iz]


@numba.njit(cache=True, parallel=True)
def near_pixels(cptr, cand, rptr, u, xf, start, t, radius, margin, count_only, out_ptr, out,
                v, out_u, out_xf, out_v):
    """Rays (indices into the lenslet-sorted arrays) whose chief ray passes near a particle.

    Particle p's candidate lenslets are ``cand[cptr[p]:cptr[p + 1]]``; lenslet k's rays are
    ``rptr[k]:rptr[k + 1]`` of ``u``, ``xf`` (sorted by lenslet). A ray is kept when at the
    particle's depth (``t[p] = (S_o + Z)/S_o``) it passes within ``radius[p]`` of ``start[p]``
    along x and along y (a square beam). Only the rays of a lenslet within the aperture
    window of :func:`_window` are tested (``margin``: the pixels' edge-centroid offsets,
    metres). With ``count_only`` the kept rays per particle go to ``out_ptr[p]``; otherwise
    they are written to ``out[out_ptr[p]:out_ptr[p + 1]]`` in candidate then ray order (the
    NumPy twin: ``plenopiv.particles.forward._pixels_numpy``), and where ``out_v`` is not
    empty their ``u``, ``xf`` and values ``v`` (P,) to ``out_u``, ``out_xf``, ``out_v`` at
    the same places (the gather the refinement reads, while the rows are in cache).
    """
    gather = out_v.shape[0] > 0
    for p in numba.prange(start.shape[0]):
        tp = t[p]
        n = 0
        w = 0 if count_only else out_ptr[p]
        for c in range(cptr[p], cptr[p + 1]):
            k = cand[c]
            if rptr[k + 1] == rptr[k]:
                continue
            first, lo, lo_x, hi_x = _window(u, xf, rptr[k], rptr[k + 1], tp, start[p, 0],
                                            start[p, 1], radius[p], margin)
            for i in range(first, rptr[k + 1]):
                if u[i, 1] < lo:
                    break
                if u[i, 0] < lo_x or u[i, 0] > hi_x:
                    continue
                dx = abs(u[i, 0] * (1.0 - tp) + xf[i, 0] * tp - start[p, 0])
                dy = abs(u[i, 1] * (1.0 - tp) + xf[i, 1] * tp - start[p, 1])
                if max(dx, dy) <= radius[p]:
                    if count_only:
                        n += 1
                    else:
                        out[w] = i
                        if gather:
                            out_u[w, 0], out_u[w, 1] = u[i, 0], u[i, 1]
                            out_xf[w, 0], out_xf[w, 1] = xf[i, 0], xf[i, 1]
                            out_v[w] = v[i]
                        w += 1
        if count_only:
            out_ptr[p] = n


@numba.njit(cache=True)
def _overlap_grad(m, wa, wb):
    """:func:`_overlap` and its derivatives ``(o, do/dm, do/dwa, do/dwb)`` (0 where o = 0)."""
    if m + 0.5 * wb < 0.5 * wa:
        hi, hi_m, hi_a, hi_b = m + 0.5 * wb, 1.0, 0.0, 0.5
    else:
        hi, hi_m, hi_a, hi_b = 0.5 * wa, 0.0, 0.5, 0.0
    if m - 0.5 * wb > -0.5 * wa:
        lo, lo_m, lo_a, lo_b = m - 0.5 * wb, 1.0, 0.0, -0.5
    else:
        lo, lo_m, lo_a, lo_b = -0.5 * wa, 0.0, -0.5, 0.0
    if hi - lo <= 0.0:
        return 0.0, 0.0, 0.0, 0.0
    return hi - lo, hi_m - lo_m, hi_a - lo_a, hi_b - lo_b


@numba.njit(cache=True)
def _misfit_sums(i0, i1, u, xf, v, a, cap, px, py, pz, so, cell, footprint, sx, sz, h, g):
    """Misfit of pixels ``i0:i1`` for a particle at (px, py, pz) with amplitude a.

    Returns the one-sided misfit and fills the Gauss-Newton sums ``h = J^T J`` (3, 3) and
    ``g = J^T r`` (3,) of the residuals ``r = v - a f`` in the scaled parameters
    ``(x / sx, y / sx, z / sz)``; a capped residual (r > cap) has no derivative.
    """
    t = (so + pz) / so
    s = 1.0 - t
    wa = cell * abs(s)
    dwa = 0.0
    if wa > 1e-9 * cell:
        dwa = cell / so if pz > 0.0 else -cell / so
    else:
        wa = 1e-9 * cell
    wb = footprint * abs(t)
    dwb = footprint / so if t > 0.0 else -footprint / so
    inv = 1.0 / (wa * wa)
    h[:, :] = 0.0
    g[:] = 0.0
    cost = 0.0
    for i in range(i0, i1):
        mx = u[i, 0] * s + xf[i, 0] * t - px
        ox, oxm, oxa, oxb = _overlap_grad(mx, wa, wb)
        if ox == 0.0:
            # predicted dark (f = 0): r = v, no derivative (all terms below vanish)
            r = v[i]
            cost += cap * cap if r > cap else r * r
            continue
        my = u[i, 1] * s + xf[i, 1] * t - py
        oy, oym, oya, oyb = _overlap_grad(my, wa, wb)
        f = ox * oy * inv
        r = v[i] - a * f
        if r > cap:
            cost += cap * cap
            continue
        cost += r * r
        if oy == 0.0:
            continue
        dox = oxm * (xf[i, 0] - u[i, 0]) / so + oxa * dwa + oxb * dwb
        doy = oym * (xf[i, 1] - u[i, 1]) / so + oya * dwa + oyb * dwb
        j0 = a * oxm * oy * inv * sx
        j1 = a * ox * oym * inv * sx
        j2 = -a * ((dox * oy + ox * doy) * inv - 2.0 * f * dwa / wa) * sz
        g[0] += j0 * r
        g[1] += j1 * r
        g[2] += j2 * r
        h[0, 0] += j0 * j0
        h[0, 1] += j0 * j1
        h[0, 2] += j0 * j2
        h[1, 1] += j1 * j1
        h[1, 2] += j1 * j2
        h[2, 2] += j2 * j2
    h[1, 0] = h[0, 1]
    h[2, 0] = h[0, 2]
    h[2, 1] = h[1, 2]
    return cost


@numba.njit(cache=True)
def _damped_step(h, g, lam, step):
    """Solve ``(h + lam diag(h)) step = -g`` by Cramer's rule; False when singular."""
    a = np.empty((3, 3))
    for e in range(3):
        for c in range(3):
            a[e, c] = h[e, c] + (lam * h[e, c] if e == c else 0.0)
    det = (a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
           - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
           + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]))
    if not (abs(det) > 0.0) or not math.isfinite(det):
        return False
    b0, b1, b2 = -g[0], -g[1], -g[2]
    step[0] = (b0 * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
               - a[0, 1] * (b1 * a[2, 2] - a[1, 2] * b2)
               + a[0, 2] * (b1 * a[2, 1] - a[1, 1] * b2)) / det
    step[1] = (a[0, 0] * (b1 * a[2, 2] - a[1, 2] * b2)
               - b0 * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
               + a[0, 2] * (a[1, 0] * b2 - b1 * a[2, 0])) / det
    step[2] = (a[0, 0] * (a[1, 1] * b2 - b1 * a[2, 1])
               - a[0, 1] * (a[1, 0] * b2 - b1 * a[2, 0])
               + b0 * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])) / det
    return True


@numba.njit(cache=True)
def _descend(i0, i1, u, xf, v, a, cap, sx0, sy0, sz0, so, cell, footprint, sx, sz, lo, hi,
             iterations, out):
    """One Levenberg-Marquardt descent of :func:`local_fit`, returning its misfit.

    From ``(sx0, sy0, sz0)`` within the box ``lo``-``hi`` (3,), metres; the end point goes
    to ``out`` (3,).
    """
    h = np.empty((3, 3))
    g = np.empty(3)
    hn = np.empty((3, 3))
    gn = np.empty(3)
    step = np.empty(3)
    x, y, z = sx0, sy0, sz0
    cost = _misfit_sums(i0, i1, u, xf, v, a, cap, x, y, z, so, cell, footprint, sx, sz, h, g)
    lam = 1e-3
    for _ in range(iterations):
        if a <= 0.0 or not _damped_step(h, g, lam, step):
            break
        for e in range(3):
            step[e] = min(max(step[e], -1.0), 1.0)
        nx = min(max(x + step[0] * sx, lo[0]), hi[0])
        ny = min(max(y + step[1] * sx, lo[1]), hi[1])
        nz = min(max(z + step[2] * sz, lo[2]), hi[2])
        c = _misfit_sums(i0, i1, u, xf, v, a, cap, nx, ny, nz, so, cell, footprint, sx, sz,
                         hn, gn)
        if c < cost:
            x, y, z, cost = nx, ny, nz, c
            h[:, :] = hn
            g[:] = gn
            lam = max(lam / 3.0, 1e-9)
            if max(abs(step[0]), abs(step[1]), abs(step[2])) < 1e-3:
                break
        else:
            lam *= 4.0
            if lam > 1e6:
                break
    out[0], out[1], out[2] = x, y, z
    return cost


@numba.njit(cache=True, parallel=True)
def local_fit(ptr, u, xf, v, amp, start, so, cell, footprint, excess, sx, sz, bound_x,
              bound_z, offsets, iterations, pos):
    """Levenberg-Marquardt on the one-sided misfit of each particle, from ``start``.

    Pixels ``ptr[p]:ptr[p + 1]`` belong to particle p (amplitude ``amp[p]``); parameters are
    scaled by ``sx`` (lateral) and ``sz`` (depth), metres. From each of ``start[p] + (0, 0,
    offsets[k])`` (metres): a step is taken when it lowers the misfit (damping /3, and the
    descent ends once a step is below 1e-3 scale units), refused otherwise (damping x4, the
    descent ends beyond 1e6); each step is clipped to one scale unit per axis and the
    position to ``start +- (bound_x, bound_x, bound_z)``. The end of least misfit (the first
    on ties) goes to ``pos`` (N, 3). The NumPy twin is ``plenopiv.particles.forward._local_fit``.
    """
    for p in numba.prange(start.shape[0]):
        lo = np.empty(3)
        hi = np.empty(3)
        end = np.empty(3)
        lo[0], hi[0] = start[p, 0] - bound_x, start[p, 0] + bound_x
        lo[1], hi[1] = start[p, 1] - bound_x, start[p, 1] + bound_x
        lo[2], hi[2] = start[p, 2] - bound_z, start[p, 2] + bound_z
        a = amp[p]
        best = np.inf
        pos[p, 0], pos[p, 1], pos[p, 2] = start[p, 0], start[p, 1], start[p, 2]
        for k in range(offsets.shape[0]):
            z0 = min(max(start[p, 2] + offsets[k], lo[2]), hi[2])
            c = _descend(ptr[p], ptr[p + 1], u, xf, v, a, excess * a, start[p, 0],
                         start[p, 1], z0, so, cell, footprint, sx, sz, lo, hi, iterations, end)
            if c < best:
                best = c
                pos[p, 0], pos[p, 1], pos[p, 2] = end[0], end[1], end[2]


@numba.njit(cache=True)
def _select_kth(a, n, k):
    """The k-th smallest of ``a[:n]`` (0-based), reordering ``a[:n]`` in place (quickselect)."""
    lo, hi = 0, n - 1
    while lo < hi:
        pivot = a[(lo + hi) // 2]
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return a[k]
    return a[k]


@numba.njit(cache=True, parallel=True)
def amplitude_at(ptr, u, xf, v, pos, so, cell, footprint, out):
    """Set ``out[p]`` to particle p's amplitude at ``pos[p]`` (pixels ``ptr[p]:ptr[p + 1]``).

    One pass per particle: each pixel's :func:`plenopiv.particles.forward.beam_fraction` f
    and, where f >= 0.5, its ratio ``v / f``; ``out[p]`` is their upper median (element
    ``n // 2`` of the n sorted ratios), 0 when none or negative. The particles run in 64
    blocks, each with one buffer for its ratios. The NumPy twin is
    ``plenopiv.particles.forward._amplitude_at``.
    """
    n_p = out.shape[0]
    blocks = min(n_p, 64)
    for c in numba.prange(blocks):
        p0, p1 = c * n_p // blocks, (c + 1) * n_p // blocks
        most = 1
        for p in range(p0, p1):
            most = max(most, ptr[p + 1] - ptr[p])
        ratio = np.empty(most)
        for p in range(p0, p1):
            t = (so + pos[p, 2]) / so
            wa = max(cell * abs(1.0 - t), 1e-9 * cell)
            wb = footprint * abs(t)
            n = 0
            for i in range(ptr[p], ptr[p + 1]):
                ox = _overlap(u[i, 0] * (1.0 - t) + xf[i, 0] * t - pos[p, 0], wa, wb)
                oy = _overlap(u[i, 1] * (1.0 - t) + xf[i, 1] * t - pos[p, 1], wa, wb)
                f = ox * oy / (wa * wa)
                if f >= 0.5:
                    ratio[n] = v[i] / f
                    n += 1
            out[p] = max(_select_kth(ratio, n, n // 2), 0.0) if n else 0.0
