"""Kernel of the normalised median test: neighbour medians of a vector field.

``neighbour_median`` gives, for every vector of a field, the median of its usable 3x3x3
neighbours (centre excluded) and the median of those neighbours' absolute residuals: the two
ingredients of the normalised median test (docs/methods.md#outlier-test).
"""

from __future__ import annotations

import warnings

import numba
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from plenopiv._median import small_median


@numba.njit(cache=True)
def neighbour_median(field, usable):
    ncomp, nz, ny, nx = field.shape
    median = np.full(field.shape, np.nan)
    residual = np.full(field.shape, np.nan)
    for flat in range(nz * ny * nx):
        i = flat // (ny * nx)
        j = (flat // nx) % ny
        m = flat % nx
        values = np.empty(26)
        dev = np.empty(26)
        for c in range(ncomp):
            count = 0
            for di in range(-1, 2):
                ii = i + di
                if ii < 0 or ii >= nz:
                    continue
                for dj in range(-1, 2):
                    jj = j + dj
                    if jj < 0 or jj >= ny:
                        continue
                    for dm in range(-1, 2):
                        mm = m + dm
                        if mm < 0 or mm >= nx:
                            continue
                        if di == 0 and dj == 0 and dm == 0:
                            continue
                        if usable[ii, jj, mm]:
                            values[count] = field[c, ii, jj, mm]
                            count += 1
            if count == 0:
                continue
            med = small_median(values, count)
            for q in range(count):
                dev[q] = abs(values[q] - med)
            median[c, i, j, m] = med
            residual[c, i, j, m] = small_median(dev, count)
    return median, residual


def neighbour_median_numpy(field, usable):
    ncomp, nz, ny, nx = field.shape
    masked = np.where(usable[None], field, np.nan).astype(np.float64)
    padded = np.pad(masked, ((0, 0), (1, 1), (1, 1), (1, 1)), constant_values=np.nan)
    windows = sliding_window_view(padded, (3, 3, 3), axis=(1, 2, 3))
    neighbours = windows.reshape(ncomp, nz, ny, nx, 27).copy()
    neighbours[..., 13] = np.nan  # the centre of the 3x3x3 block
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # "All-NaN slice": no usable neighbour
        median = np.nanmedian(neighbours, axis=-1)
        residual = np.nanmedian(np.abs(neighbours - median[..., None]), axis=-1)
    return median, residual
