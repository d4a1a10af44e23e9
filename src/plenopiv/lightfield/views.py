"""Perspective (sub-aperture) views of a light field: one value per lenslet for one aperture point.

Every lenslet sees aperture point u through the sensor point ``x = x_c - u f̄/S_i`` (x_c its focal
spot, :mod:`plenopiv.lightfield.rays`); a view gathers that point of every lenslet on the
lenslet lattice (``Calibration.grid_index``).
"""

from __future__ import annotations

import numpy as np

from plenopiv.errors import CalibrationError
from plenopiv.lightfield.rays import LightField

PERSPECTIVE_INTERPOLATIONS = ("nearest", "linear")


def perspective_view(image, lf: LightField, grid_index, u=(0.0, 0.0), *,
                     interpolation: str = "nearest") -> np.ndarray:
    """Return the sub-aperture image seen through aperture point ``u`` (metres).

    Parameters
    ----------
    image : ndarray, shape ``lf.shape``
        Recorded (ideally dark-subtracted and flat-fielded) raw image.
    lf : LightField
    grid_index : (N, 2) int
        Lattice index ``(row, col)`` of every calibration lenslet (``Calibration.grid_index``).
    u : (2,) float
        Aperture-plane point ``(x, y)``, metres (``(0, 0)``: the pupil centre, the central view).
    interpolation : {"nearest", "linear"}
        ``"nearest"`` (default): for each lenslet, the value of its pixel whose aperture position
        is nearest to ``u`` (within 0.75 of a cell); lenslets with none are NaN.
        ``"linear"``: the image bilinearly interpolated at the exact sensor point that sees ``u``
        through the lenslet, ``x = x_c - u f̄/S_i`` (x_c its focal spot); NaN where one of the
        four pixels is not a lit pixel of that lenslet. Every lenslet then sees exactly the same
        aperture point, so views at nearby ``u`` differ only by parallax (what disparity
        measurements and :func:`~plenopiv.lightfield.refocus` with ``method="fourier"`` need).

    Returns
    -------
    ndarray, shape (lenslet rows, lenslet cols)
        Indexed by ``grid_index``; float64, NaN where a lenslet has no value.
    """
    if interpolation not in PERSPECTIVE_INTERPOLATIONS:
        raise ValueError(f"interpolation = {interpolation!r}: expected one of "
                         f"{PERSPECTIVE_INTERPOLATIONS}")
    gi = check_grid_index(grid_index, lf)
    out = np.full((gi[:, 0].max() + 1, gi[:, 1].max() + 1), np.nan)
    if interpolation == "linear":
        vals = views_linear(image, lf, len(gi), np.asarray(u, float).reshape(1, 2))[0]
        out[gi[:, 0], gi[:, 1]] = vals
        return out
    vals = lf.values(image).astype(float)
    d2 = ((lf.u - np.asarray(u, float)) ** 2).sum(axis=1)
    ok = np.flatnonzero(d2 <= (0.75 * lf.cell) ** 2)
    k = lf.lenslet[ok]
    # nearest ray of each lenslet; lexsort is stable, so ties keep the lowest pixel index
    order = np.lexsort((d2[ok], k))
    first = np.ones(len(order), bool)
    first[1:] = k[order][1:] != k[order][:-1]
    sel = ok[order[first]]
    kk = lf.lenslet[sel]
    out[gi[kk, 0], gi[kk, 1]] = vals[sel]
    return out


def check_grid_index(grid_index, lf: LightField) -> np.ndarray:
    """``grid_index`` as an (N, 2) int array, checked against the light field's lenslets."""
    gi = np.asarray(grid_index)
    if gi.ndim != 2 or gi.shape[1] != 2 or len(gi) == 0:
        raise ValueError(f"grid_index has shape {gi.shape}: expected (N, 2) lattice indices")
    gi = gi.astype(int)
    if gi.min() < 0:
        raise ValueError("grid_index holds negative indices: expected lattice indices >= 0")
    if lf.n_rays and lf.lenslet.max() >= len(gi):
        raise ValueError(f"grid_index has {len(gi)} rows but the light field has lenslet "
                         f"{int(lf.lenslet.max())}: pass the calibration's grid_index")
    return gi


def _lenslet_spots_px(lf: LightField, n_lenslets: int) -> np.ndarray:
    """Recover every lenslet's focal spot (row, col), px, from its rays.

    NaN for a lenslet without a wholly lit pixel. Every ray satisfies
    ``u = -(x - x_c) S_i/f̄`` with the cell ``p_p S_i/f̄``, so ``x_c = x + u / cell`` in pixels.
    """
    # only wholly lit pixels: a pixel cut by the aperture edge has its ray moved to the
    # centroid of the lit part of its cell, so its u no longer marks the pixel centre
    full = np.flatnonzero(lf.lit >= 1.0 - 1e-9)
    rows, cols = np.divmod(lf.pixel[full], lf.shape[1])
    r = rows + lf.u[full, 1] / lf.cell
    c = cols + lf.u[full, 0] / lf.cell
    k = lf.lenslet[full]
    cnt = np.bincount(k, minlength=n_lenslets).astype(float)
    with np.errstate(invalid="ignore", divide="ignore"):
        sr = np.bincount(k, r, minlength=n_lenslets) / cnt
        sc = np.bincount(k, c, minlength=n_lenslets) / cnt
    return np.stack([sr, sc], axis=1)


def view_sampler(image, lf: LightField, n_lenslets: int):
    """Prepare :func:`views_linear`: the flat image, pixel owners and focal spots.

    Returns the image as a flat float array, the lenslet of every pixel (-1: none) and every
    lenslet's focal spot (row, col), px.
    """
    img = np.asarray(image)
    if img.shape != tuple(lf.shape):
        raise CalibrationError(f"image is {img.shape}, the calibration's sensor is "
                               f"{tuple(lf.shape)}")
    flat = img.reshape(-1).astype(float)
    owner = np.full(flat.size, -1, np.int64)
    owner[lf.pixel] = lf.lenslet
    return flat, owner, _lenslet_spots_px(lf, n_lenslets)


def views_linear(image, lf: LightField, n_lenslets: int, us, sampler=None) -> np.ndarray:
    """Bilinear views: value of every lenslet (columns) at every aperture point ``us`` (rows).

    NaN where one of the four pixels around the sampled point is not a lit pixel of that
    lenslet (or its value is not finite). ``sampler`` is :func:`view_sampler`'s result,
    to reuse it over many calls.
    """
    flat, owner, spots = sampler or view_sampler(image, lf, n_lenslets)
    us = np.asarray(us, float).reshape(-1, 2)
    r = spots[None, :, 0] - us[:, None, 1] / lf.cell
    c = spots[None, :, 1] - us[:, None, 0] / lf.cell
    good = np.isfinite(r) & np.isfinite(c)
    r0 = np.floor(np.where(good, r, 0)).astype(np.int64)
    c0 = np.floor(np.where(good, c, 0)).astype(np.int64)
    ar, ac = r - r0, c - c0
    k = np.broadcast_to(np.arange(n_lenslets), r.shape)
    out = np.zeros(r.shape)
    n_rows, n_cols = lf.shape
    for dr, dc, w in ((0, 0, (1 - ar) * (1 - ac)), (0, 1, (1 - ar) * ac),
                      (1, 0, ar * (1 - ac)), (1, 1, ar * ac)):
        rr, cc = r0 + dr, c0 + dc
        inside = good & (rr >= 0) & (rr < n_rows) & (cc >= 0) & (cc < n_cols)
        idx = np.where(inside, rr * n_cols + cc, 0)
        good &= inside & (owner[idx] == k)
        out += w * flat[idx]
    out[~(good & np.isfinite(out))] = np.nan
    return out
