"""Refocusing a light field on a synthetic lenslet plane at α S_i (thesis §2.3, Ng 2005).

Two methods: a bilinear splat of every ray onto an axis-centred grid, and a Fourier
shift-and-add of bilinear perspective views (:mod:`plenopiv.lightfield.views`) on the lenslet
lattice; :func:`refocus` explains when to use which.
"""

from __future__ import annotations

import math

import numpy as np

from plenopiv.errors import CalibrationError
from plenopiv.lightfield.rays import LightField
from plenopiv.lightfield.views import check_grid_index, view_sampler, views_linear

REFOCUS_METHODS = ("splat", "fourier")


def refocus(image, lf: LightField, alpha: float, *, pitch: float | None = None,
            shape_lenslets=None, method: str = "splat", grid_index=None) -> np.ndarray:
    """Refocused image on a synthetic lenslet plane at α S_i (thesis §2.3, Ng 2005).

    A ray through aperture point u and lenslet centre s meets the plane z = α S_i at
    s' = u + α (s - u); rescaled by 1/α (the magnification of the nominal plane is kept) it
    lands at ``s'/α = s + u (1/α - 1)`` on the lenslet plane. The refocused image is the
    average of the rays landing at each point.

    Parameters
    ----------
    image : ndarray, shape ``lf.shape``
        Recorded raw image (dark-subtracted and flat-fielded for real data). Rays whose value
        is not finite (NaN marks pixels to ignore) are left out.
    lf : LightField
    alpha : float
        α > 1 focuses in front of the nominal focal plane (nearer the camera), α < 1 behind it;
        α = 1 is the nominal focal plane. It must lie within ``lf.alpha_range``
        (:attr:`LightField.alpha_range`), else ValueError gives that range.
    pitch : float
        ``method="splat"`` only: output grid spacing on the lenslet plane, metres.
    shape_lenslets : (rows, cols)
        ``method="splat"`` only: output shape; the grid is centred on the optical axis.
    method : {"splat", "fourier"}
        ``"splat"`` (default): each ray's value is splatted bilinearly onto the axis-centred
        grid at ``s'/α`` and normalised by the splatted weight. ``"fourier"``: shift-and-add
        of perspective views on the lenslet lattice: views at aperture points u one cell
        apart (those whose cell lies wholly inside the aperture), each bilinearly sampled
        (``perspective_view(..., interpolation="linear")``), shifted by ``u (1/α - 1)`` with
        an exact Fourier (band-limited) shift and averaged, with the views' NaN masks shifted
        alongside to normalise. Needs ``grid_index``.
    grid_index : (N, 2) int
        ``method="fourier"`` only: lattice index of every calibration lenslet.

    Returns
    -------
    ndarray
        ``"splat"``: shape ``shape_lenslets``; ``"fourier"``: (lenslet rows, lenslet cols),
        indexed like :func:`perspective_view`. NaN where no ray lands (splat) or where fewer
        than half of the views cover the point (fourier).

    Notes
    -----
    Choosing a method. The splat resamples the rays onto a fixed grid, and how much that
    blurs depends on α: at α = 1 all rays of a lenslet land on one point (the integral
    image, resampled by the bilinear kernel according to where the lenslet centres fall on the
    grid), while at α ≠ 1 they spread over a disc of radius R|1/α - 1|. A sharpness measure
    evaluated on splatted images over α therefore has a kink at α = 1 and is pulled onto it,
    whatever the depth of the scene. The Fourier
    shift-and-add keeps every output sample on the lenslet lattice and shifts by band-limited
    (sinc) interpolation, which keeps each view's spectrum, so only the alignment of the
    views changes with α: use it for depth from focus (sharpness over α;
    docs/validation/letters.md). The views are zero-padded before the FFT (no wrap-around).
    Its output is at lenslet resolution; the splat can also be evaluated on finer grids.
    Shifts are converted to lattice units with the lattice basis fitted to the lenslet
    centres, so a rotated or anisotropic lattice is handled.
    """
    if not alpha > 0:
        raise ValueError(f"alpha = {alpha!r}: expected > 0")
    lo, hi = lf.alpha_range
    if not lo <= alpha <= hi:
        raise ValueError(
            f"alpha = {alpha!r} is outside the range this light field supports, "
            f"{lo:.4g} <= alpha <= {hi:.4g}: beyond it the rays from the aperture's edge move "
            "by more than half the lenslet array and the refocused image is empty "
            "(LightField.alpha_range)")
    if method not in REFOCUS_METHODS:
        raise ValueError(f"method = {method!r}: expected one of {REFOCUS_METHODS}")
    if method == "fourier":
        if grid_index is None:
            raise ValueError('method = "fourier" needs grid_index (the calibration\'s lattice '
                             "indices); pitch and shape_lenslets do not apply")
        if pitch is not None or shape_lenslets is not None:
            raise ValueError('method = "fourier" returns the image on the lenslet lattice: '
                             "leave pitch and shape_lenslets unset")
        return _refocus_fourier(image, lf, float(alpha), grid_index)
    if pitch is None or shape_lenslets is None:
        raise ValueError('method = "splat" needs pitch (metres) and shape_lenslets (rows, cols)')
    if not pitch > 0:
        raise ValueError(f"pitch = {pitch!r}: expected > 0 metres")
    return _refocus_splat(image, lf, alpha, pitch, shape_lenslets)


def _refocus_splat(image, lf: LightField, alpha: float, pitch: float,
                   shape_lenslets) -> np.ndarray:
    """:func:`refocus` with ``method="splat"`` (arguments checked there).

    Each finite ray lands at ``s'/α`` on the lenslet plane; its value is spread bilinearly over
    the four nearest points of the axis-centred grid of spacing ``pitch`` (metres) and shape
    ``shape_lenslets``, and the sum is divided by the spread weight (NaN where none).
    """
    vals = lf.values(image).astype(float)
    # the aperture point u lives on the lens plane; at the lenslet plane the ray has moved
    # from u (z = 0) to s (z = S_i): at z = α S_i it is at u + α (s - u)
    sp = (lf.u + alpha * (lf.s - lf.u)) / alpha
    rows, cols = (int(v) for v in shape_lenslets)
    fin = np.isfinite(vals)
    sp, vals = sp[fin], vals[fin]
    fc = sp[:, 0] / pitch + (cols - 1) / 2
    fr = sp[:, 1] / pitch + (rows - 1) / 2
    n = (rows + 1) * (cols + 1)
    acc = np.zeros(n)
    wgt = np.zeros(n)
    r0, c0 = np.floor(fr).astype(int), np.floor(fc).astype(int)
    ar, ac = fr - r0, fc - c0
    for drr, dcc, w in ((0, 0, (1 - ar) * (1 - ac)), (0, 1, (1 - ar) * ac),
                        (1, 0, ar * (1 - ac)), (1, 1, ar * ac)):
        rr, cc = r0 + drr, c0 + dcc
        ok = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        idx = rr[ok] * (cols + 1) + cc[ok]
        acc += np.bincount(idx, (w * vals)[ok], minlength=n)
        wgt += np.bincount(idx, w[ok], minlength=n)
    out = np.where(wgt > 0, acc / np.where(wgt > 0, wgt, 1), np.nan)
    return out.reshape(rows + 1, cols + 1)[:rows, :cols]


def _lenslet_centres(lf: LightField, n_lenslets: int) -> np.ndarray:
    """Lenslet centre (x, y) metres of every lenslet from its rays; NaN without rays."""
    cnt = np.bincount(lf.lenslet, minlength=n_lenslets).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.stack([np.bincount(lf.lenslet, lf.s[:, i], minlength=n_lenslets) / cnt
                         for i in (0, 1)], axis=1)


def _aperture_samples(lf: LightField) -> np.ndarray:
    """Aperture points (x, y) metres one cell apart whose whole cell is inside the aperture."""
    n = int(math.floor(lf.aperture_radius / lf.cell))
    a = np.arange(-n, n + 1) * lf.cell
    ux, uy = np.meshgrid(a, a)
    ux, uy = ux.ravel(), uy.ravel()
    # the cell's farthest corner inside the disc
    keep = (np.abs(ux) + lf.cell / 2) ** 2 + (np.abs(uy) + lf.cell / 2) ** 2 \
        <= lf.aperture_radius ** 2
    if not keep.any():
        keep = np.hypot(ux, uy) == 0
    return np.stack([ux[keep], uy[keep]], axis=1)


def _refocus_fourier(image, lf: LightField, alpha: float, grid_index) -> np.ndarray:
    gi = check_grid_index(grid_index, lf)
    n_k = len(gi)
    shape = (int(gi[:, 0].max()) + 1, int(gi[:, 1].max()) + 1)
    # lattice basis (metres per index step) from the lenslet centres: s = o + i b_r + j b_c
    centres = _lenslet_centres(lf, n_k)
    have = np.isfinite(centres[:, 0])
    if have.sum() < 3:
        raise CalibrationError("refocus: fewer than 3 lenslets have rays; cannot fit the lattice")
    design = np.column_stack([np.ones(have.sum()), gi[have, 0], gi[have, 1]])
    coef, *_ = np.linalg.lstsq(design, centres[have], rcond=None)
    basis = np.stack([coef[1], coef[2]], axis=1)      # columns b_r, b_c; rows x, y
    us = _aperture_samples(lf)
    shifts = np.linalg.solve(basis, (us * (1.0 / alpha - 1.0)).T).T   # (n_u, 2) (d_row, d_col)
    pad = int(math.ceil(np.abs(shifts).max())) + 2
    big = (shape[0] + 2 * pad, shape[1] + 2 * pad)
    ky = np.fft.fftfreq(big[0])[None, :, None]
    kx = np.fft.fftfreq(big[1])[None, None, :]
    num = np.zeros(big, complex)
    den = np.zeros(big, complex)
    chunk = 64
    sampler = view_sampler(image, lf, n_k)
    for a in range(0, len(us), chunk):
        v = views_linear(image, lf, n_k, us[a:a + chunk], sampler)
        stack = np.zeros((len(v), *big))
        mask = np.zeros((len(v), *big))
        ok = np.isfinite(v)
        stack[:, pad + gi[:, 0], pad + gi[:, 1]] = np.where(ok, v, 0.0)
        mask[:, pad + gi[:, 0], pad + gi[:, 1]] = ok
        sh = shifts[a:a + chunk]
        phase = np.exp(-2j * np.pi * (ky * sh[:, 0, None, None] + kx * sh[:, 1, None, None]))
        num += (np.fft.fft2(stack) * phase).sum(axis=0)
        den += (np.fft.fft2(mask) * phase).sum(axis=0)
    num_r = np.fft.ifft2(num).real[pad:pad + shape[0], pad:pad + shape[1]]
    den_r = np.fft.ifft2(den).real[pad:pad + shape[0], pad:pad + shape[1]]
    cover = den_r >= 0.5 * len(us)
    return np.where(cover, num_r / np.where(cover, den_r, 1.0), np.nan)
