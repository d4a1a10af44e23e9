"""Plain-NumPy twins of the ray-tracer kernels in :mod:`._kernels`, used by the tests.

Written for clarity, vectorised over rays, with the same inputs and outputs as the kernels.
"""

from __future__ import annotations

import numpy as np

from plenopiv.synthetic import _kernels as K


def radial_solve(rho, air, thick, n):
    """NumPy twin of :func:`._kernels.radial_solve` (vectorised over ``rho``)."""
    rho = np.asarray(rho, dtype=float)
    if thick == 0.0:
        return rho / air
    m = rho / (air + thick / n)
    for _ in range(40):
        s = m / np.sqrt(1 + m * m)
        sg = s / n
        cg = np.sqrt(1 - sg * sg)
        f = air * m + thick * sg / cg - rho
        d = air + thick / n * (1 + m * m) ** -1.5 / cg ** 3
        m = m - f / d
    return m


def lenslet_at(x, y, g):
    """NumPy twin of :func:`._kernels.lenslet_at`: nearest centre of a padded lattice, by
    brute force; a point whose nearest centre is a virtual (padding) lenslet hits none.
    """
    x, y = np.atleast_1d(x).astype(float), np.atleast_1d(y).astype(float)
    rows, cols = int(g[K.G_ROWS]), int(g[K.G_COLS])
    p, rs = g[K.G_PITCH], g[K.G_ROWSP]
    r, c = np.meshgrid(np.arange(-2, rows + 2), np.arange(-2, cols + 2), indexing="ij")
    r, c = r.ravel(), c.ravel()
    shift = (0.5 * (r % 2) - g[K.G_HEXSHIFT]) if g[K.G_HEX] > 0.5 else 0.0
    su = (c - (cols - 1) / 2 + shift) * p + g[K.G_OFFS]
    sv = (r - (rows - 1) / 2) * rs + g[K.G_OFFT]
    cs, sn = g[K.G_COSG], g[K.G_SING]
    cx, cy = cs * su - sn * sv, sn * su + cs * sv
    d2 = (x[:, None] - cx[None]) ** 2 + (y[:, None] - cy[None]) ** 2
    j = np.argmin(d2, axis=1)
    real = (r[j] >= 0) & (r[j] < rows) & (c[j] >= 0) & (c[j] < cols)
    k = np.where(real, r[j] * cols + c[j], -1)
    return k, cx[j], cy[j]


def through_lenslet(hx, hy, d, cx, cy, g):
    """NumPy twin of :func:`._kernels.through_lenslet`; ``d`` is (N, 3) unit directions."""
    n = g[K.G_N]
    if g[K.G_THESIS] < 0.5 and g[K.G_T] > 0:
        a = n * d[:, :2]
        az = np.sqrt(1 - (a ** 2).sum(axis=1))
        m = a / az[:, None]
    else:
        m = d[:, :2] / d[:, 2:3]
    m = m - np.stack([hx - cx, hy - cy], axis=1) / g[K.G_FL]
    return np.stack([hx, hy], axis=1) + g[K.G_FBAR] * m


def trace_image_rays(x0, y0, z0, mx, my, g):
    """NumPy twin of :func:`._kernels.trace_image_rays`, built from 3-D vector Snell."""
    o = np.stack([x0, y0, z0], axis=1).astype(float)
    d = np.stack([mx, my, np.ones_like(mx)], axis=1).astype(float)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, n = g[K.G_T], g[K.G_N]
    z_front = g[K.G_L3] if t > 0 else g[K.G_ZMLA]
    h = o + d * ((z_front - o[:, 2]) / d[:, 2])[:, None]
    if t > 0:
        d = snell(d, np.array([0.0, 0.0, 1.0]), 1.0, n)
        h = h + d * (t / d[:, 2])[:, None]
    k, cx, cy = lenslet_at(h[:, 0], h[:, 1], g)
    s = through_lenslet(h[:, 0], h[:, 1], d, cx, cy, g)
    return k, s[:, 0], s[:, 1]


def snell(d, normal, n1, n2):
    """Vector Snell refraction of unit directions ``d`` (N, 3) at a plane with unit ``normal``.

    ``t = (n1/n2) d + ((n1/n2) cos i - cos t) normal`` with ``cos i = d·normal``.
    """
    r = n1 / n2
    cos_i = d @ normal
    cos_t = np.sqrt(1 - r * r * (1 - cos_i ** 2))
    return r * d + (cos_t - r * cos_i)[:, None] * normal[None, :]


def splat(shape, sx, sy, w, g):
    """NumPy twin of :func:`._kernels.splat` for many points: returns the image."""
    img = np.zeros(shape)
    col = sx / g[K.G_PIX] + (g[K.G_NCOLS] - 1) / 2 + g[K.G_SHIFTC]
    row = sy / g[K.G_PIX] + (g[K.G_NROWS] - 1) / 2 + g[K.G_SHIFTR]
    w = np.broadcast_to(np.asarray(w, float), np.shape(sx))
    if g[K.G_SPLAT] > 0.5:
        rr, cc = np.floor(row + 0.5).astype(int), np.floor(col + 0.5).astype(int)
        ok = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        np.add.at(img, (rr[ok], cc[ok]), w[ok])
        return img
    r0, c0 = np.floor(row).astype(int), np.floor(col).astype(int)
    fr, fc = row - r0, col - c0
    for dr, dc, ww in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc),
                       (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
        rr, cc = r0 + dr, c0 + dc
        ok = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
        np.add.at(img, (rr[ok], cc[ok]), (w * ww)[ok])
    return img


def object_rays_to_lens(sources, lens_points, g):
    """NumPy twin of :func:`._kernels.object_rays_to_lens` (exact Snell at the interface)."""
    p = np.asarray(sources, float)
    lpt = np.asarray(lens_points, float)
    r = lpt - p[:, :2]
    z = -p[:, 2]
    m = r / z[:, None]
    if g[K.G_HASEXT] > 0.5:
        behind = p[:, 2] < g[K.G_ZINT]
        rho = np.hypot(r[:, 0], r[:, 1])
        mm = np.array([radial_solve(rh, -g[K.G_ZINT], g[K.G_ZINT] - pz, g[K.G_NEXT])
                       for rh, pz in zip(rho, p[:, 2], strict=True)])
        with np.errstate(invalid="ignore", divide="ignore"):
            mr = np.where(rho[:, None] > 0, mm[:, None] * r / np.where(rho > 0, rho, 1)[:, None],
                          0.0)
        m = np.where(behind[:, None], mr, m)
    return m
