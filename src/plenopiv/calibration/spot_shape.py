"""Spot centres from the spots' common shape: the mean spot as a template, fitted to each.

A white image's micro-images fill their cells: a flat plateau, bounded by soft edges that
touch the neighbours'. A thresholded centroid of such a cell barely moves with it (a window
inside a uniform plateau has its centroid at its own centre wherever it is), so its centre
comes from a few edge pixels and the noise. :func:`shape_refine` uses the whole cell
instead: the mean of all the spots, aligned on their current centres and made
point-symmetric, is the template T; each spot is fitted as ``a T(x - c) + b`` by
Gauss-Newton, which weighs every pixel by the template's gradient there (the edges), and the
template is rebuilt on the new centres. :func:`shape_uncertainty` gives the standard
error of any centre from the same fit's residual. Pixels are ``(row, col)``; lengths in px.
See docs/methods.md#focal-spots.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

# the template is sampled on bins this fine, px
_BIN_PX = 0.25
# passes of: the template from the current centres, one Gauss-Newton step per spot
_PASSES = 4
# a pixel is a spot's own when nearer its centre than any neighbour's by this much of the pitch
_OWN_MARGIN = 0.15
# a spot's fit moves it at most this fraction of the pitch; farther, it keeps its start
_MAX_MOVE_PITCH = 0.25


def fit_radius(pitch_px: float, spot_radius_px: float) -> float:
    """Radius of the pixels fitted around a spot, px.

    Its 99 % radius plus 1.5 px, at most half the pitch plus 1.5 px (a cell's own edges and
    no more of its neighbours').
    """
    r = spot_radius_px if np.isfinite(spot_radius_px) else 0.5 * pitch_px
    return float(min(r, 0.5 * pitch_px) + 1.5)


def _window(centres, radius, shape, pitch_px):
    """Each spot's own pixels: rows, cols (N, M) int and a mask (N, M) of those that count.

    A pixel counts when it lies in the image, within ``radius`` of the spot's centre, and
    nearer that centre than any neighbour's by ``_OWN_MARGIN`` of the pitch: where two
    micro-images touch, the light belongs to both edges and moves with each, so it is left
    to neither (with it, each centre is pulled towards its neighbours').
    """
    h = int(math.ceil(radius)) + 1
    dr, dc = np.mgrid[-h:h + 1, -h:h + 1]
    keep = np.hypot(dr, dc) <= radius + 1.5
    dr, dc = dr[keep], dc[keep]
    base = np.rint(centres).astype(np.int64)
    rows = base[:, :1] + dr[None, :]
    cols = base[:, 1:] + dc[None, :]
    ok = (rows >= 0) & (cols >= 0) & (rows < shape[0]) & (cols < shape[1])
    frac = (centres - base).astype(np.float32)
    u_r = dr[None, :].astype(np.float32) - frac[:, :1]
    u_c = dc[None, :].astype(np.float32) - frac[:, 1:]
    d0 = np.sqrt(u_r * u_r + u_c * u_c)
    ok &= d0 <= radius
    if len(centres) > 1:
        k = min(7, len(centres))      # the 4 (square) or 6 (hexagonal) that share an edge
        _, nb = cKDTree(centres).query(centres, k=k)
        reach = (d0 + np.float32(_OWN_MARGIN * pitch_px)) ** 2
        for j in range(1, k):
            off = (centres[nb[:, j]] - centres).astype(np.float32)
            ok &= reach <= (u_r - off[:, :1]) ** 2 + (u_c - off[:, 1:]) ** 2
    return np.clip(rows, 0, shape[0] - 1), np.clip(cols, 0, shape[1] - 1), ok


def _template(values, u_r, u_c, ok, extent):
    """The mean spot on bins of ``_BIN_PX`` over ``[-extent, extent]``, point-symmetric.

    Returns the template, its gradient (d/d row, d/d col) per bin, and the bin grid origin.
    Empty bins take the nearest filled value (the template is smooth on these scales).
    """
    n = int(math.ceil(extent / _BIN_PX))
    size = 2 * n + 1
    ir = np.rint(u_r[ok] / _BIN_PX).astype(np.int64) + n
    ic = np.rint(u_c[ok] / _BIN_PX).astype(np.int64) + n
    inside = (ir >= 0) & (ic >= 0) & (ir < size) & (ic < size)
    key = ir[inside] * size + ic[inside]
    total = np.bincount(key, weights=values[ok][inside], minlength=size * size)
    count = np.bincount(key, minlength=size * size).astype(np.float64)
    total, count = total.reshape(size, size), count.reshape(size, size)
    total, count = total + total[::-1, ::-1], count + count[::-1, ::-1]
    empty = count == 0
    mean = np.where(empty, 0.0, total / np.maximum(count, 1.0))
    if empty.any() and not empty.all():
        _, (nr, nc) = ndi.distance_transform_edt(empty, return_indices=True)
        mean = mean[nr, nc]
    mean = ndi.gaussian_filter(mean, 0.5, mode="nearest")    # the bins' own noise, 1/8 px
    g_r, g_c = np.gradient(mean, _BIN_PX)
    return mean, g_r, g_c, n


def _sample(grids, u_r, u_c, n, ok):
    """Bilinear values of template ``grids`` (a tuple) at offsets ``(u_r, u_c)`` px.

    Only where ``ok`` (0 elsewhere); offsets beyond the grids take their border values.
    """
    size = grids[0].shape[0]
    x = np.clip(u_r[ok] / _BIN_PX + n, 0, size - 1.000001)
    y = np.clip(u_c[ok] / _BIN_PX + n, 0, size - 1.000001)
    i0, j0 = x.astype(np.int64), y.astype(np.int64)
    fx, fy = x - i0, y - j0
    k00 = i0 * size + j0
    w00, w01 = (1 - fx) * (1 - fy), (1 - fx) * fy
    w10, w11 = fx * (1 - fy), fx * fy
    out = []
    for g in grids:
        f = g.ravel()
        full = np.zeros(ok.shape)
        full[ok] = (w00 * f[k00] + w01 * f[k00 + 1] + w10 * f[k00 + size]
                    + w11 * f[k00 + size + 1])
        out.append(full)
    return out


def _fit(values, t, g_r, g_c, ok):
    """Per spot: least squares of ``values ~ a t + b - a (g_r d_r + g_c d_c)``.

    Returns the shift ``(d_r, d_c)`` px (N, 2), its standard error per axis (N, 2), the
    amplitude ``a`` and the residual standard deviation.
    """
    w = ok.astype(np.float64)
    design = np.empty((t.shape[0], 4, t.shape[1]))
    design[:, 0], design[:, 1], design[:, 2], design[:, 3] = t * w, w, -g_r * w, -g_c * w
    y = values * w
    ata = design @ design.transpose(0, 2, 1)
    aty = (design @ y[..., None])[..., 0]
    det_ok = np.abs(np.linalg.det(ata)) > 1e-30
    ata[~det_ok] = np.eye(4)
    cov = np.linalg.inv(ata)
    sol = (cov @ aty[..., None])[..., 0]
    resid = y - (sol[:, None, :] @ design)[:, 0]
    dof = np.maximum(w.sum(axis=1) - 4.0, 1.0)
    s2 = np.sum(resid * resid, axis=1) / dof
    a = sol[:, 0]
    safe_a = np.where(np.abs(a) > 0, a, np.nan)
    shift = sol[:, 2:] / safe_a[:, None]
    # a near-singular system can round a variance below zero: no standard error then
    var = np.stack([cov[:, 2, 2], cov[:, 3, 3]], axis=1) * s2[:, None]
    std = np.sqrt(np.where(var >= 0, var, np.nan)) / np.abs(safe_a)[:, None]
    shift[~det_ok] = np.nan
    std[~det_ok] = np.nan
    return shift, std, a, np.sqrt(s2)


def shape_refine(work, centres, pitch_px: float, radius_px: float, *, use=None):
    """Refine spot centres by fitting the spots' mean shape to each; and their standard errors.

    Parameters
    ----------
    work : ndarray, shape (R, C)
        Background-subtracted image.
    centres : ndarray, shape (N, 2)
        First centres ``(row, col)`` px (a thresholded centroid's).
    pitch_px : float
        Lenslet pitch, px.
    radius_px : float
        Radius of the pixels fitted around each centre, px (:func:`fit_radius`).
    use : ndarray of bool, shape (N,), optional
        The spots that build the template (complete, clean ones); default all.

    Returns
    -------
    centres : ndarray, shape (N, 2)
        Refined centres ``(row, col)`` px; a spot whose fit fails or moves it more than a
        quarter pitch keeps its first centre.
    std : ndarray, shape (N, 2)
        Standard error of each centre per axis, px (NaN where the fit failed).

    Notes
    -----
    Four passes of: the template from the spots of ``use`` aligned on their current centres
    (point-symmetrised: its centre is the spots' centre of symmetry), then one Gauss-Newton
    step per spot; each spot's pixels are its own
    (:func:`_window`). The standard error is
    the least-squares one, the residual variance of the spot's own fit times the inverse
    normal matrix: it holds the noise and whatever of the spot differs from the mean shape.
    """
    img = np.asarray(work, dtype=np.float64)
    start = np.asarray(centres, dtype=np.float64)
    c = start.copy()
    use = np.ones(len(c), bool) if use is None else np.asarray(use, bool)
    std = np.full(c.shape, np.nan)
    if len(c) == 0:
        return c, std
    for _ in range(_PASSES):
        rows, cols, ok = _window(c, radius_px, img.shape, pitch_px)
        values = img[rows, cols]
        u_r, u_c = rows - c[:, :1], cols - c[:, 1:]
        tpl = _template(values[use], u_r[use], u_c[use], ok[use], radius_px + 1.0)
        t, g_r, g_c = _sample(tpl[:3], u_r, u_c, tpl[3], ok)
        shift, std, a, _ = _fit(values, t, g_r, g_c, ok)
        good = np.all(np.isfinite(shift), axis=1) & (a > 0)
        c[good] += shift[good]
        moved = np.hypot(*(c - start).T)
        bad = ~(np.all(np.isfinite(c), axis=1) & (moved < _MAX_MOVE_PITCH * pitch_px))
        c[bad] = start[bad]
    return c, std


def shape_uncertainty(work, centres, pitch_px: float, radius_px: float, *, use=None):
    """Standard error per axis (N, 2) px of given centres, from the mean-shape fit's residual.

    The centres are not moved: the template is built on them and each spot's fit is
    evaluated there (:func:`shape_refine` for the details). Also returns each fit's residual
    standard deviation per pixel (N,), image units: the noise about the spot.
    """
    img = np.asarray(work, dtype=np.float64)
    c = np.asarray(centres, dtype=np.float64)
    if len(c) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    use = np.ones(len(c), bool) if use is None else np.asarray(use, bool)
    rows, cols, ok = _window(c, radius_px, img.shape, pitch_px)
    values = img[rows, cols]
    u_r, u_c = rows - c[:, :1], cols - c[:, 1:]
    tpl = _template(values[use], u_r[use], u_c[use], ok[use], radius_px + 1.0)
    t, g_r, g_c = _sample(tpl[:3], u_r, u_c, tpl[3], ok)
    _, std, _, noise = _fit(values, t, g_r, g_c, ok)
    return std, noise
