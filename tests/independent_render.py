"""A focal-point renderer written apart from plenopiv's ray tracer, for cross-checks.

Plain NumPy and deliberately different choices from :mod:`plenopiv.synthetic`: rays from a
Vogel (golden-angle) spiral over the stop, turned by a random angle per lenslet, to random
points of the lenslet's cell; the stop in the main-lens plane; Snell through the plate by
its own Newton solve; each ray splatted bilinearly onto the 4 nearest pixel centres; a
Gaussian PSF; scaled to 0.9 x 4095 counts with optional Poisson noise. It imports nothing
from plenopiv, so a calibration that holds on its images does not rest on one renderer.

:func:`disc_spot` renders one spot alone (a uniform disc, splatted or pixel-integrated), for
the phase-bias tests of the spot estimators and ``benchmarks/bench_spots.py``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def _slope_through_plate(rho, air, t, n):
    """tan(theta) in air of the ray crossing ``rho`` over ``air`` then ``t`` of glass."""
    if t == 0:
        return rho / air
    m = rho / (air + t / n)
    for _ in range(40):
        s = m / np.sqrt(1 + m * m)
        sg = s / n
        cg = np.sqrt(1 - sg * sg)
        f = air * m + t * sg / cg - rho
        d = air + t / n * (1 + m * m) ** -1.5 / cg ** 3
        m = m - f / d
    return m


def render(*, si_eff, rows=40, cols=60, shape=(700, 1040), pitch=125e-6, f_lenslet=500e-6,
           fbar=500e-6, pixel=7.4e-6, f_main=0.135, f_number=16.0, plate=None,
           back_side="physical", offset=(0.0, 0.0), rotation=0.0, jitter=0.0, rays=1024,
           psf=0.5, noise=False, seed=0, collimated=False):
    """Render a focal-point (or, ``collimated=True``, alignment) image.

    Returns ``(image, ray_mean_rc)``: the image (float64 without noise, else uint16 counts)
    and the mean ``(row, col)`` of each lenslet's rays, px. ``plate`` is ``(t, n)`` metres;
    ``si_eff`` is S_i,eff = l3 + t/n.
    """
    rng = np.random.default_rng(seed)
    t, n = (0.0, 1.0) if plate is None else plate
    air = si_eff - t / n
    r_stop = f_main / f_number / 2
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    s = (jj.ravel() - (cols - 1) / 2) * pitch + offset[0]
    tt = (ii.ravel() - (rows - 1) / 2) * pitch + offset[1]
    c, sn = np.cos(rotation), np.sin(rotation)
    cx, cy = c * s - sn * tt, sn * s + c * tt
    if jitter:
        cx = cx + rng.normal(0, jitter, cx.shape)
        cy = cy + rng.normal(0, jitter, cy.shape)
    n_l = cx.size
    img = np.zeros(shape)
    mean = np.zeros((n_l, 2))
    golden = np.pi * (3 - np.sqrt(5))
    k = np.arange(rays)
    rad = r_stop * np.sqrt((k + 0.5) / rays)
    for a in range(0, n_l, 200):
        b = min(a + 200, n_l)
        m_ = b - a
        phi = golden * k[None, :] + rng.uniform(0, 2 * np.pi, (m_, 1))
        px, py = rad[None, :] * np.cos(phi), rad[None, :] * np.sin(phi)
        ux = rng.uniform(-pitch / 2, pitch / 2, (m_, rays))
        uy = rng.uniform(-pitch / 2, pitch / 2, (m_, rays))
        hx = cx[a:b, None] + c * ux - sn * uy
        hy = cy[a:b, None] + sn * ux + c * uy
        if collimated:
            mx, my = np.zeros_like(hx), np.zeros_like(hy)
        else:
            rx, ry = hx - px, hy - py
            rho = np.hypot(rx, ry)
            m = _slope_through_plate(rho, air, t, n)
            if back_side == "thesis" and t > 0:
                sg = m / np.sqrt(1 + m * m) / n
                m = sg / np.sqrt(1 - sg * sg)
            mx, my = m * rx / rho, m * ry / rho
        mx = mx - (hx - cx[a:b, None]) / f_lenslet
        my = my - (hy - cy[a:b, None]) / f_lenslet
        col = (hx + fbar * mx) / pixel + (shape[1] - 1) / 2
        row = (hy + fbar * my) / pixel + (shape[0] - 1) / 2
        mean[a:b, 0] = row.mean(axis=1)
        mean[a:b, 1] = col.mean(axis=1)
        row, col = row.ravel(), col.ravel()
        r0, c0 = np.floor(row).astype(int), np.floor(col).astype(int)
        fr, fc = row - r0, col - c0
        for dr, dc, w in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc),
                          (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
            rr, cc = r0 + dr, c0 + dc
            ok = (rr >= 0) & (rr < shape[0]) & (cc >= 0) & (cc < shape[1])
            np.add.at(img, (rr[ok], cc[ok]), w[ok])
    if psf > 0:
        img = ndimage.gaussian_filter(img, psf, mode="constant", truncate=5.0)
    img *= 0.9 * 4095 / img.max()
    if noise:
        img = np.clip(rng.poisson(img), 0, 4095).astype(np.uint16)
    return img, mean


def disc_spot(centre, diameter, blur, splat, size=25, n=120):
    """One spot on a ``size`` x ``size`` px image: a uniform disc of ``n`` x ``n`` rays.

    Parameters
    ----------
    centre : array_like, shape (2,)
        Disc centre ``(row, col)``, px (pixel centres at whole numbers).
    diameter : float
        Disc diameter, px.
    blur : float
        Standard deviation of the Gaussian PSF before the pixels, px (0: none).
    splat : {"bilinear", "pixel"}
        ``"bilinear"``: each ray onto its 4 nearest pixel centres; ``"pixel"``: integrated
        over the pixel area (4 x 4 supersampling, then summed).

    Returns
    -------
    ndarray, shape (size, size)
        Light per pixel (rays, so the total is the number of rays inside the disc).
    """
    u = (np.arange(n) - (n - 1) / 2) / n * diameter
    y, x = np.meshgrid(u, u, indexing="ij")
    keep = x * x + y * y <= (diameter / 2) ** 2
    s = 1 if splat == "bilinear" else 4
    r = (y[keep] + centre[0] + 0.5) * s - 0.5
    c = (x[keep] + centre[1] + 0.5) * s - 0.5
    img = np.zeros((size * s, size * s))
    r0, c0 = np.floor(r).astype(int), np.floor(c).astype(int)
    fr, fc = r - r0, c - c0
    for dr, dc, w in ((0, 0, (1 - fr) * (1 - fc)), (0, 1, (1 - fr) * fc),
                      (1, 0, fr * (1 - fc)), (1, 1, fr * fc)):
        np.add.at(img, (r0 + dr, c0 + dc), w)
    if blur > 0:
        img = ndimage.gaussian_filter(img, blur * s, mode="constant", truncate=6.0)
    return img.reshape(size, s, size, s).sum(axis=(1, 3))
