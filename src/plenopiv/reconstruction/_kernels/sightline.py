"""Numba kernel of the sub-voxel line of sight (:mod:`plenopiv.reconstruction.sightline`).

One pass over a depth slab of refined cells gives per coarse voxel what the NumPy
expressions of :func:`pool_cells_numpy` give with a dozen temporary arrays of the refined
slab's size, for every volume.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def pool_cells(seen, dark, used, log_sum, kx, ky, best, ratio, has_used, used_sum, lit):
    """Pool the ``kx × ky`` cells of every voxel of one slab.

    Inputs are refined ``(nz, ny·ky, nx·kx)`` float32 sums per cell: ``seen`` (all rows),
    ``dark`` (dark rows), ``used`` (used rows) and ``log_sum`` (used rows' ln v). Per coarse
    voxel ``(nz, ny, nx)`` it writes: ``best``, the smallest ``dark / seen`` of its cells
    with ``seen > 0`` (inf if none); ``ratio``, the largest ``log_sum / used`` of its cells
    with ``used > 0`` and ``has_used``, whether there is one; ``used_sum``, the sum of
    ``used`` over its cells (float32); ``lit``, whether some cell has ``used - dark > 0``.
    All arithmetic in float32, as the NumPy twin. Serial: a parallel loop gains little on this
    pass and compiles about twice as long.
    """
    nz, fy, fx = seen.shape
    ny = fy // ky
    nx = fx // kx
    for z in range(nz):
        for iy in range(ny):
            for ix in range(nx):
                b = np.float32(np.inf)
                r = np.float32(-np.inf)
                h = False
                u = np.float32(0.0)
                lt = False
                for a in range(ky):
                    yy = iy * ky + a
                    for c in range(kx):
                        xx = ix * kx + c
                        s = seen[z, yy, xx]
                        dv = dark[z, yy, xx]
                        if s > 0:
                            f = dv / s
                            if f < b:
                                b = f
                        su = used[z, yy, xx]
                        if su > 0:
                            q = log_sum[z, yy, xx] / su
                            if not h or q > r:
                                r = q
                            h = True
                        u += su
                        if su - dv > 0:
                            lt = True
                best[z, iy, ix] = b
                ratio[z, iy, ix] = r
                has_used[z, iy, ix] = h
                used_sum[z, iy, ix] = u
                lit[z, iy, ix] = lt


def pool_cells_numpy(seen, dark, used, log_sum, kx, ky):
    """The plain-NumPy twin of :func:`pool_cells`: ``(best, ratio, has_used, used_sum, lit)``."""
    nz, fy, fx = seen.shape

    def cells(a):
        return a.reshape(nz, fy // ky, ky, fx // kx, kx)

    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        frac = np.where(seen > 0, dark / seen, np.float32(np.inf)).astype(np.float32)
        q = np.where(used > 0, log_sum / used, np.float32(-np.inf)).astype(np.float32)
    return (cells(frac).min(axis=(2, 4)), cells(q).max(axis=(2, 4)),
            cells(used > 0).any(axis=(2, 4)), cells(used).sum(axis=(2, 4), dtype=np.float32),
            cells(used - dark > 0).any(axis=(2, 4)))
