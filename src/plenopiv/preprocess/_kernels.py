"""Numba kernels of :mod:`plenopiv.preprocess` and their NumPy twins (``<kernel>_numpy``).

Both kernels work on whole sensor images (16 Mpx for the Auburn camera) in one pass:
:func:`label_micro_images` assigns every pixel to its nearest micro-image centre,
:func:`neighbour_stats` summarises a pixel's neighbours that lie in its own micro-image.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from plenopiv._median import small_median


@njit(cache=True)
def label_micro_images(centres, base, half, reach2, label, dist2):
    """Label each pixel with its nearest micro-image centre, in place.

    Parameters
    ----------
    centres : (N, 2) float64
        Micro-image centres (row, col), pixels.
    base : (N, 2) int64
        The pixel nearest each centre (``floor(centre + 0.5)``): the middle of its search box.
    half : int
        Half-width of the square searched about each centre, pixels.
    reach2 : float
        Largest squared distance of a pixel from its centre, px²; farther pixels stay
        unlabelled.
    label : (rows, cols) int32
        Filled with the index of the nearest centre (start at -1: none).
    dist2 : (rows, cols) float64
        Filled with the squared distance to it, px² (start at +inf).

    Notes
    -----
    Lenslets are visited in order and a pixel changes hands only to a strictly nearer centre,
    so a pixel equidistant from two centres keeps the first.
    """
    n_rows, n_cols = label.shape
    for k in range(centres.shape[0]):
        r0 = centres[k, 0]
        c0 = centres[k, 1]
        for r in range(max(base[k, 0] - half, 0), min(base[k, 0] + half + 1, n_rows)):
            dr = r - r0
            for c in range(max(base[k, 1] - half, 0), min(base[k, 1] + half + 1, n_cols)):
                dc = c - c0
                d2 = dr * dr + dc * dc
                if d2 <= reach2 and d2 < dist2[r, c]:
                    dist2[r, c] = d2
                    label[r, c] = k


def label_micro_images_numpy(centres, base, half, reach2, label, dist2):
    """NumPy twin of :func:`label_micro_images`: same arguments, the same labels in place."""
    n_rows, n_cols = label.shape
    for k in range(centres.shape[0]):
        r_lo, r_hi = max(base[k, 0] - half, 0), min(base[k, 0] + half + 1, n_rows)
        c_lo, c_hi = max(base[k, 1] - half, 0), min(base[k, 1] + half + 1, n_cols)
        if r_lo >= r_hi or c_lo >= c_hi:
            continue
        dr = np.arange(r_lo, r_hi)[:, None] - centres[k, 0]
        dc = np.arange(c_lo, c_hi)[None, :] - centres[k, 1]
        d2 = dr * dr + dc * dc
        box = (slice(r_lo, r_hi), slice(c_lo, c_hi))
        nearer = (d2 <= reach2) & (d2 < dist2[box])
        dist2[box] = np.where(nearer, d2, dist2[box])
        label[box] = np.where(nearer, k, label[box])


@njit(cache=True, nogil=True)
def neighbour_stats(image, label, use, which, radius, maximum, median, count, lo, hi):
    """Largest value, median and number of a pixel's neighbours in its own micro-image.

    For every pixel of rows ``lo`` to ``hi - 1`` where ``which`` is true: the pixels within
    ``radius`` (a square, the pixel itself left out) that carry the same ``label`` and where
    ``use`` is true. Writes ``maximum``, ``median`` (NaN where there are none) and ``count``.

    Parameters
    ----------
    image : (rows, cols) float64
    label : (rows, cols) int32
        Micro-image of each pixel (any integer; -1 is a label like the others).
    use : (rows, cols) bool
        Pixels that may serve as neighbours (known bad pixels left out).
    which : (rows, cols) bool
        Pixels whose neighbours are summarised.
    radius : int
        Half-width of the neighbourhood, pixels.
    maximum, median : (rows, cols) float64
        Outputs (left as they are where ``which`` is false).
    count : (rows, cols) int32
        Output.
    lo, hi : int
        Rows to do (:func:`plenopiv._threads.run_slices`).
    """
    n_rows, n_cols = image.shape
    w = 2 * radius + 1
    buf = np.empty(w * w)
    for r in range(lo, hi):
        for c in range(n_cols):
            if not which[r, c]:
                continue
            lab = label[r, c]
            n = 0
            top = -math.inf
            for rr in range(max(r - radius, 0), min(r + radius + 1, n_rows)):
                for cc in range(max(c - radius, 0), min(c + radius + 1, n_cols)):
                    if rr == r and cc == c:
                        continue
                    if not use[rr, cc] or label[rr, cc] != lab:
                        continue
                    v = image[rr, cc]
                    buf[n] = v
                    n += 1
                    if v > top:
                        top = v
            count[r, c] = n
            if n == 0:
                maximum[r, c] = math.nan
                median[r, c] = math.nan
                continue
            maximum[r, c] = top
            median[r, c] = small_median(buf, n)     # no array per pixel


def neighbour_stats_numpy(image, label, use, which, radius, maximum, median, count, lo, hi):
    """NumPy twin of :func:`neighbour_stats`: same arguments, same outputs in place."""
    img = image
    n_rows, n_cols = img.shape
    offsets = [(a, b) for a in range(-radius, radius + 1) for b in range(-radius, radius + 1)
               if (a, b) != (0, 0)]
    rows = np.arange(lo, hi)
    cols = np.arange(n_cols)
    rr0, cc0 = np.meshgrid(rows, cols, indexing="ij")
    values = np.full((len(offsets),) + rr0.shape, np.nan)
    for i, (a, b) in enumerate(offsets):
        rr, cc = rr0 + a, cc0 + b
        inside = (rr >= 0) & (rr < n_rows) & (cc >= 0) & (cc < n_cols)
        rc, ccc = np.clip(rr, 0, n_rows - 1), np.clip(cc, 0, n_cols - 1)
        ok = inside & use[rc, ccc] & (label[rc, ccc] == label[rr0, cc0])
        values[i] = np.where(ok, img[rc, ccc], np.nan)
    sel = which[lo:hi]
    n = np.sum(np.isfinite(values), axis=0).astype(np.int32)
    some = sel & (n > 0)
    with np.errstate(all="ignore"):
        top = np.max(np.where(np.isfinite(values), values, -np.inf), axis=0)
        mid = np.sort(values, axis=0)           # NaN last
    k = np.maximum(n, 1)
    lower = np.take_along_axis(mid, ((k - 1) // 2)[None], axis=0)[0]
    upper = np.take_along_axis(mid, (k // 2)[None], axis=0)[0]
    med = np.where(k % 2 == 1, lower, 0.5 * (lower + upper))
    count[lo:hi][sel] = n[sel]
    maximum[lo:hi][sel] = np.where(some, top, np.nan)[sel]
    median[lo:hi][sel] = np.where(some, med, np.nan)[sel]
