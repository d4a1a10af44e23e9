"""The particles each interrogation window holds: the evidence a vector rests on.

:func:`particle_table` counts a volume's particles per voxel (from its particle table, or,
for a bare volume, from its local maxima above :data:`PEAK_THRESHOLD` of its bright level)
as a summed-area table; :func:`window_counts` sums it over every window of a pass, each
window moved the way that pass moved it. See docs/methods.md#particles-per-window.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage

from plenopiv.conventions import world_to_voxel
from plenopiv.errors import PIVError

PEAK_THRESHOLD = 0.1
"""A bare volume's particle is a voxel that is the maximum of its 3x3x3 neighbourhood and
brighter than this fraction of the volume's bright level (the 99.9th percentile of its
positive voxels): the ``[particles] threshold`` default on the same reference."""


def _peak_voxels(volume):
    """Voxels ``(N, 3)`` ``(z, y, x)`` of a volume's local maxima above its peak threshold."""
    positive = volume[volume > 0]
    if not positive.size:
        return np.zeros((0, 3))
    level = PEAK_THRESHOLD * float(np.percentile(positive, 99.9))
    peak = (volume == scipy.ndimage.maximum_filter(volume, size=3, mode="constant")) & (
        volume > level)
    return np.argwhere(peak).astype(float)


def particle_table(shape, *, positions=None, origin=None, voxel=None, volume=None, mask=None,
                   index=None):
    """Summed-area table of a volume's particle count per voxel, ``(nz+1, ny+1, nx+1)`` int64.

    Parameters
    ----------
    shape : (nz, ny, nx)
        The volume's shape, voxels.
    positions : array_like, shape (N, 3), optional
        The particle table: ``(x, y, z)`` metres on the volume's grid (``origin`` and
        ``voxel``: the centre of voxel ``[0, 0, 0]`` and the voxel edge ``(dx, dy, dz)``, m).
        A particle counts in the voxel holding its position; one outside the volume, or in
        ``mask``, counts nowhere.
    volume : ndarray, shape ``shape``, optional
        Without ``positions``: the particles are the volume's local maxima above
        :data:`PEAK_THRESHOLD` of its bright level.
    mask : bool ndarray, shape ``shape``, optional
        Voxels outside the flow (True).
    index : (N, 3) int array, optional
        The particles' voxels already found (:func:`particle_voxels`), instead of the above.

    Returns
    -------
    ndarray
        ``t[z, y, x]``: the particles in voxels ``[:z, :y, :x]``.
    """
    shape = tuple(int(n) for n in shape)
    if index is None:
        index = particle_voxels(shape, positions=positions, origin=origin, voxel=voxel,
                                volume=volume)
    count = np.zeros(shape, dtype=np.int64)
    np.add.at(count, tuple(index.T), 1)
    if mask is not None:
        count[mask] = 0
    table = np.zeros(tuple(n + 1 for n in shape), dtype=np.int64)
    table[1:, 1:, 1:] = count.cumsum(0).cumsum(1).cumsum(2)
    return table


def particle_voxels(shape, *, positions=None, origin=None, voxel=None, volume=None):
    """The voxels ``(N, 3)`` ``(z, y, x)`` int64 holding the particles inside the volume.

    The arguments are :func:`particle_table`'s: the particle table's positions, or without
    them the volume's local maxima above its peak threshold.
    """
    if positions is not None:
        p = np.asarray(positions, dtype=float).reshape(-1, 3)
        if not np.all(np.isfinite(p)):
            raise PIVError(f"the particle table holds {int((~np.isfinite(p)).any(1).sum())} "
                           "positions that are NaN or infinite: expected finite metres")
        index = np.floor(world_to_voxel(p, origin, voxel) + 0.5)
    else:
        index = _peak_voxels(np.asarray(volume))
    inside = np.all((index >= 0) & (index < np.array(shape)), axis=1)
    return index[inside].astype(np.int64)


def capped(volume, index, fraction: float) -> np.ndarray:
    """``volume`` capped at ``fraction`` of the median value at its particles' voxels.

    ``index``: :func:`particle_voxels`. A volume without a particle at a positive voxel,
    or ``fraction`` 0, is returned as it is (intensity capping, docs/methods.md).
    """
    if fraction <= 0 or not len(index):
        return volume
    peaks = volume[tuple(np.asarray(index).T)]
    peaks = peaks[peaks > 0]
    if not peaks.size:
        return volume
    return np.minimum(volume, np.float32(fraction * float(np.median(peaks))))


def window_counts(table, layout, offset_vox=None):
    """Particles in every window of ``layout`` (flat, int64), each moved by ``offset_vox``.

    Parameters
    ----------
    table : ndarray
        :func:`particle_table` of the volume.
    layout : _Layout
        The pass's windows (:func:`plenopiv.piv.windows._window_layout`).
    offset_vox : ndarray, shape (n_windows, 3), optional
        Where each window lies in this volume relative to its place in the layout, voxels
        ``(z, y, x)``, rounded to whole voxels; None or NaN: not moved. The parts of a window
        beyond the volume hold no particles.
    """
    starts = layout.all_starts()
    if offset_vox is not None:
        starts = starts + np.rint(np.nan_to_num(np.asarray(offset_vox, float))).astype(np.int64)
    limit = np.array(table.shape) - 1
    lo = np.clip(starts, 0, limit)
    hi = np.clip(starts + np.array(layout.window), 0, limit)
    total = np.zeros(len(starts), dtype=np.int64)
    for corner in range(8):
        pick = [(corner >> axis) & 1 for axis in range(3)]
        idx = tuple(np.where(pick[axis], hi[:, axis], lo[:, axis]) for axis in range(3))
        total += (-1) ** (3 - sum(pick)) * table[idx]
    return total
