"""Numba kernel of :mod:`plenopiv.lightfield` (its NumPy twin is ``lightfield._lit_fraction``)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def lit_fraction(ux, uy, cell, radius, n):
    """Lit fraction of each cell × cell square centred at (ux, uy) inside a disc.

    The disc has radius ``radius``; also returns the centroid offset of the lit part (n × n
    samples where the edge crosses the cell). Serial: compiling the parallel loop costs
    more than the loop itself takes on a camera's lenslets.
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
