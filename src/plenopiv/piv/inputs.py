"""Checks of the inputs of :func:`plenopiv.piv.correlate_volumes` and its thread control."""

from __future__ import annotations

import contextlib
import os

import numba
import numpy as np

from plenopiv.errors import PIVError
from plenopiv.piv._kernels import ENGINES


def _check_volumes(volume_a, volume_b):
    arrays = []
    for name, vol in (("volume_a", volume_a), ("volume_b", volume_b)):
        a = np.asarray(vol)
        if a.ndim != 3:
            raise PIVError(
                f"{name} has {a.ndim} dimensions (shape {a.shape}): expected a [z, y, x] volume"
            )
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise PIVError(f"{name} has dtype {a.dtype}: expected real numbers (float32 preferred)")
        a = np.ascontiguousarray(a, dtype=np.float32)
        bad = ~np.isfinite(a)
        if bad.any():
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            raise PIVError(
                f"{name} holds {int(bad.sum())} non-finite voxels (first at [z, y, x] = {first}): "
                "expected finite intensities"
            )
        arrays.append(a)
    if arrays[0].shape != arrays[1].shape:
        raise PIVError(
            f"volume_a has shape {arrays[0].shape} and volume_b {arrays[1].shape}: "
            "expected two volumes of the same [z, y, x] grid"
        )
    return arrays


def _grid_geometry(grid, shape):
    """Return ``origin (x, y, z)`` and ``voxel (dx, dy, dz)`` in metres from ``grid``.

    ``grid`` is a :class:`plenopiv.camera.grid.VolumeGrid` (attributes ``origin``, ``voxel``,
    ``shape``) or any object with ``origin`` and ``voxel_size`` (and optionally ``shape``).
    """
    name = "voxel_size" if hasattr(grid, "voxel_size") else "voxel"
    if not (hasattr(grid, "origin") and hasattr(grid, name)):
        raise PIVError(
            f"grid = {grid!r}: expected a VolumeGrid, or an object with attributes origin "
            "(x, y, z) and voxel_size (dx, dy, dz), in metres"
        )
    edge = getattr(grid, name)
    try:
        origin = np.asarray(grid.origin, dtype=float)
        voxel = np.broadcast_to(np.asarray(edge, dtype=float), (3,)).copy()
    except (TypeError, ValueError):
        origin = voxel = np.full(3, np.nan)
        if np.shape(grid.origin) != (3,):
            origin = np.zeros(0)
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise PIVError(f"grid.origin = {grid.origin!r}: expected three finite metres (x, y, z)")
    if not (np.all(np.isfinite(voxel)) and np.all(voxel > 0)):
        raise PIVError(f"grid.{name} = {edge!r}: expected (dx, dy, dz) > 0 metres")
    grid_shape = getattr(grid, "shape", None)
    if grid_shape is not None and tuple(int(s) for s in grid_shape) != tuple(shape):
        raise PIVError(
            f"grid.shape = {tuple(grid_shape)} but the volumes have shape {tuple(shape)}: "
            "expected the grid the volumes were reconstructed on"
        )
    return origin, voxel


def _check_windows(settings, shape):
    for k, window in enumerate(settings.windows):
        too_big = [
            f"{axis}: {w} > {n}" for axis, w, n in zip("zyx", window, shape, strict=True) if w > n
        ]
        if too_big:
            raise PIVError(
                f"settings.windows[{k}] = {window} voxels is larger than the volume "
                f"{tuple(shape)} ({', '.join(too_big)}): expected windows that fit the volume"
            )


def _resolve_workers(workers):
    if workers is None:
        return os.cpu_count() or 1
    if not isinstance(workers, (int, np.integer)) or isinstance(workers, bool) or workers < 1:
        raise ValueError(f"workers = {workers!r}: expected None (all cores) or an int >= 1")
    return int(workers)


@contextlib.contextmanager
def _numba_threads(workers):
    """Run the numba kernels on at most ``workers`` threads, restoring the previous count."""
    previous = numba.get_num_threads()
    numba.set_num_threads(max(1, min(workers, numba.config.NUMBA_NUM_THREADS)))
    try:
        yield
    finally:
        numba.set_num_threads(previous)

def _check_mask(mask, shape):
    """Return the volume mask as a bool array of ``shape`` (None if no voxel is masked)."""
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise PIVError(
            f"mask has shape {m.shape}: expected the volumes' [z, y, x] shape {tuple(shape)}"
        )
    if m.dtype != bool:
        if not (np.issubdtype(m.dtype, np.integer) and np.isin(m, (0, 1)).all()):
            raise PIVError(f"mask has dtype {m.dtype}: expected bool (True = masked voxel)")
        m = m.astype(bool)
    return m if m.any() else None


def _check_engine(engine):
    if engine not in ENGINES:
        raise ValueError(f"engine = {engine!r}: expected one of {tuple(ENGINES)}")
    return ENGINES[engine]
