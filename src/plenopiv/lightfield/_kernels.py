"""Numba kernel of :mod:`plenopiv.lightfield` and its NumPy twin (``<kernel>_numpy``)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def lit_fraction(ux, uy, cell, radius, n):
    """Lit fraction of cell × cell squares centred at (ux, uy) inside a disc, centroid offsets.

    Parameters
    ----------
    ux, uy : (M,) float
        Cell centres on the aperture plane, metres.
    cell : float
        Cell width, metres.
    radius : float
        Radius of the aperture disc, metres.
    n : int
        Samples per side of a cell that the disc's edge crosses.

    Returns
    -------
    lit, sx, sy : (M,) float
        Fraction of each cell inside the disc, and the (x, y) offset of the centroid of its
        inside part from the cell centre, metres (0 for wholly lit or dark cells).
    """
    m = ux.shape[0]
    lit = np.empty(m)
    sx = np.zeros(m)
    sy = np.zeros(m)
    reach = cell * math.sqrt(0.5)
    r2 = radius * radius
    step = cell / n
    for i in range(m):
        d = math.hypot(ux[i], uy[i])
        if d + reach <= radius:
            lit[i] = 1.0
            continue
        if d - reach >= radius:
            lit[i] = 0.0
            continue
        count = 0
        ax = 0.0
        ay = 0.0
        for p in range(n):
            a = (p - (n - 1) / 2) * step
            for q in range(n):
                b = (q - (n - 1) / 2) * step
                if (ux[i] + a) ** 2 + (uy[i] + b) ** 2 <= r2:
                    count += 1
                    ax += a
                    ay += b
        lit[i] = count / (n * n)
        if count > 0:
            sx[i] = ax / count
            sy[i] = ay / count
    return lit, sx, sy


def lit_fraction_numpy(ux, uy, cell, radius, n):
    """NumPy twin of :func:`lit_fraction`: same arguments, same outputs.

    Only cells that the disc's edge crosses are sampled (n × n points); the others are wholly
    lit or wholly dark.
    """
    ux, uy = np.asarray(ux, float), np.asarray(uy, float)
    dist = np.hypot(ux, uy)
    reach = cell * math.sqrt(0.5)
    lit = (dist + reach <= radius).astype(float)
    sx = np.zeros(ux.shape)
    sy = np.zeros(ux.shape)
    edge = np.abs(dist - radius) < reach
    ex, ey = ux[edge], uy[edge]
    o = (np.arange(n) - (n - 1) / 2) * (cell / n)
    count = np.zeros(ex.shape)
    ax = np.zeros(ex.shape)
    ay = np.zeros(ex.shape)
    for a in o:
        for b in o:
            inside = (ex + a) ** 2 + (ey + b) ** 2 <= radius ** 2
            count += inside
            ax += a * inside
            ay += b * inside
    safe = np.maximum(count, 1)
    lit[edge] = count / (n * n)
    sx[edge] = ax / safe
    sy[edge] = ay / safe
    return lit, sx, sy
