"""Window layout of a pass, interpolation of a vector field, and deformation of a volume.

Positions are voxels in the volume's index order ``(z, y, x)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

_SPLINE_PAD = 12
"""Zero voxels added around a volume before its B-spline prefilter (as scipy.ndimage does)."""

_DEFORM_CHUNK_VOXELS = 2**20
"""Voxels resampled per call of ``scipy.ndimage.map_coordinates`` (bounds its coordinate array)."""

@dataclass(frozen=True)
class _Layout:
    """Window grid of one pass: start voxel and centre (voxels) per axis, ``(z, y, x)``."""

    window: tuple
    starts: tuple  # three 1-D int arrays
    centres: tuple  # three 1-D float arrays

    @property
    def shape(self):
        return tuple(s.size for s in self.starts)

    def all_starts(self):
        zz, yy, xx = np.meshgrid(*self.starts, indexing="ij")
        return np.stack([zz.ravel(), yy.ravel(), xx.ravel()], axis=1).astype(np.int64)


def _window_layout(shape, window, overlap):
    """Place windows with the given overlap, centred in the volume."""
    starts, centres = [], []
    for n, w in zip(shape, window, strict=True):
        step = max(1, round(w * (1.0 - overlap)))
        count = (n - w) // step + 1
        first = (n - ((count - 1) * step + w)) // 2
        s = first + step * np.arange(count)
        starts.append(s.astype(np.int64))
        centres.append(s + (w - 1) / 2.0)
    return _Layout(tuple(window), tuple(starts), tuple(centres))


def _lerp_axis(values, axis, source, target):
    """Linear interpolation of ``values`` along ``axis`` from ``source`` to ``target`` positions.

    ``source`` is evenly spaced. Beyond its ends the end segments are extended (linear
    extrapolation), so that a linear flow stays linear up to the volume's border.
    """
    n = source.size
    if n == 1:
        return np.repeat(values, target.size, axis=axis)
    pos = (np.asarray(target, dtype=float) - source[0]) / (source[1] - source[0])
    i0 = np.clip(np.floor(pos).astype(np.int64), 0, n - 2)
    t = (pos - i0).astype(values.dtype)
    shape = [1] * values.ndim
    shape[axis] = target.size
    t = t.reshape(shape)
    return np.take(values, i0, axis=axis) * (1 - t) + np.take(values, i0 + 1, axis=axis) * t


def _interpolate_field(field_vox, source, target):
    """Trilinearly interpolate a ``(3, nz, ny, nx)`` field from grid ``source`` to ``target``.

    ``source`` and ``target`` are triples of 1-D voxel positions ``(z, y, x)``; ``source`` is
    evenly spaced per axis. The field is interpolated linearly along one axis after the other,
    which on a regular grid is exactly trilinear, and extrapolated linearly beyond it.
    """
    out = field_vox
    for axis in (3, 2, 1):
        out = _lerp_axis(out, axis, source[axis - 1], target[axis - 1])
    return out

def _centre_mask(mask, layout):
    """True for the windows of ``layout`` whose centre lies in ``mask`` (flat, (n,))."""
    n = math.prod(layout.shape)
    if mask is None:
        return np.zeros(n, dtype=bool)
    zz, yy, xx = np.meshgrid(*layout.centres, indexing="ij")
    coords = np.stack([zz.ravel(), yy.ravel(), xx.ravel()])
    inside = scipy.ndimage.map_coordinates(
        mask.astype(np.float32), coords, order=1, mode="nearest", prefilter=False
    )
    return inside >= 0.5

def _spline_coefficients(volume, order):
    """Return the B-spline coefficients of ``volume``, taken as zero outside it.

    The coefficients live on a grid padded by ``_SPLINE_PAD`` voxels per side (they decay by
    a factor 0.27 per voxel for order 3, so the padding makes the zero border exact to float32).
    """
    padded = np.pad(volume, _SPLINE_PAD, mode="constant")
    return scipy.ndimage.spline_filter(padded, order=order, output=np.float32, mode="mirror")


def _deform(volume, field_vox, factor, order, kernels, coeffs=None):
    """Sample ``volume`` at ``p + factor * field_vox(p)`` for every voxel ``p`` (zero outside).

    Order 1 interpolates ``volume`` trilinearly; higher orders evaluate the B-spline whose
    coefficients ``coeffs`` come from :func:`_spline_coefficients`.
    """
    if order == 1:
        return kernels.deform_trilinear(volume, field_vox, factor)
    if order == 3:
        return kernels.deform_cubic(coeffs, field_vox, factor, _SPLINE_PAD)
    out = np.empty_like(volume)
    nz, ny, nx = volume.shape
    slab = max(1, _DEFORM_CHUNK_VOXELS // (ny * nx))
    iy, ix = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    for z0 in range(0, nz, slab):
        z1 = min(nz, z0 + slab)
        iz = np.arange(z0, z1, dtype=np.float64)[:, None, None]
        coords = np.empty((3, z1 - z0, ny, nx))
        coords[0] = iz + _SPLINE_PAD + factor * field_vox[0, z0:z1]
        coords[1] = iy + _SPLINE_PAD + factor * field_vox[1, z0:z1]
        coords[2] = ix + _SPLINE_PAD + factor * field_vox[2, z0:z1]
        out[z0:z1] = scipy.ndimage.map_coordinates(
            coeffs, coords, order=order, mode="grid-constant", cval=0.0, prefilter=False
        )
    return out
