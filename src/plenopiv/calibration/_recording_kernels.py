"""Numba kernel of the recording check's model image, with its plain-NumPy twin.

:func:`plenopiv.calibration.recording.check_recording` correlates the recording with soft
discs at the calibration's micro-images; :func:`soft_discs` draws them, one spot at a time,
and :func:`soft_discs_numpy` computes the same image with vectorised NumPy, one offset from the
spots' centres at a time, for the tests. Pixels are ``(row, col)``.
"""

from __future__ import annotations

import math

import numba
import numpy as np


def _reach(radius: float, edge: float) -> int:
    """Half the side of the square of pixels drawn about each disc's centre."""
    return int(math.ceil(radius + 3.0 * edge))


@numba.njit(cache=True)
def _discs_kernel(n_rows, n_cols, base, frac, radius, edge, h):
    out = np.zeros((n_rows, n_cols))
    for k in range(base.shape[0]):
        for a in range(-h, h + 1):
            r = base[k, 0] + a
            if r < 0 or r >= n_rows:
                continue
            for b in range(-h, h + 1):
                c = base[k, 1] + b
                if c < 0 or c >= n_cols:
                    continue
                dist = math.hypot(a - frac[k, 0], b - frac[k, 1])
                out[r, c] += 0.5 * (1.0 - math.tanh((dist - radius) / edge))
    return out


def soft_discs(shape, spots, radius: float, edge: float) -> np.ndarray:
    """Soft discs of ``radius`` px with an edge of ``edge`` px at ``spots`` (N, 2), (R, C).

    Each disc is ``(1 - tanh((d - radius) / edge)) / 2`` at the distance ``d`` of a pixel from
    its spot, drawn on the pixels within :func:`_reach` of the spot's nearest pixel.
    """
    spots = np.ascontiguousarray(spots, dtype=np.float64)
    base = np.rint(spots).astype(np.int64)
    return _discs_kernel(int(shape[0]), int(shape[1]), base, spots - base, float(radius),
                         float(edge), _reach(radius, edge))


def soft_discs_numpy(shape, spots, radius: float, edge: float) -> np.ndarray:
    """The NumPy twin of :func:`soft_discs`."""
    out = np.zeros(shape)
    h = _reach(radius, edge)
    spots = np.asarray(spots, dtype=np.float64)
    base = np.rint(spots).astype(np.int64)
    frac = spots - base
    for a in range(-h, h + 1):
        for b in range(-h, h + 1):
            r, c = base[:, 0] + a, base[:, 1] + b
            ok = (r >= 0) & (c >= 0) & (r < shape[0]) & (c < shape[1])
            dist = np.hypot(a - frac[ok, 0], b - frac[ok, 1])
            np.add.at(out, (r[ok], c[ok]), 0.5 * (1.0 - np.tanh((dist - radius) / edge)))
    return out
