"""The way back from a reconstruction's working grid to the volume's grid.

A reconstruction on a ``[volume]`` grid runs on voxels ``ky × kx`` times finer laterally
(:func:`plenopiv.reconstruction.choose.lateral_subdivision`) and slices ``kz`` times deeper
(:func:`plenopiv.reconstruction.choose.depth_binning`); :func:`merge_subdivided` and
:func:`unbin_depth` return its volume to the ``[volume]`` grid, :func:`working_factors` finds
the factors of given weights, :func:`to_volume_grid` applies both.
"""

from __future__ import annotations

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction.choose import subdivided_grid

__all__ = ["merge_subdivided", "to_volume_grid", "unbin_depth", "working_factors"]



def merge_subdivided(volume, ky: int, kx: int, *, kernel: str = "gaussian") -> np.ndarray:
    """A volume of laterally subdivided voxels back on the grid it subdivides, float32.

    ``volume`` is ``(nz, ny * ky, nx * kx)`` (:func:`subdivided_grid`). ``"box"`` sums each
    voxel's ``ky × kx`` working voxels. ``"gaussian"`` weights the working volume by a
    Gaussian of σ = half a voxel (``k/2`` working voxels) about each voxel's centre (linear
    between the two middle working voxels for an even k), scaled by ``ky kx`` so that the
    total is kept: a particle narrower than a voxel then spreads over its neighbours in the
    ratio of where it lies inside the voxel, which the box sum loses (the peak locking of
    voxels a lenslet footprint wide: docs/validation/vortex.md). The samples of a Gaussian
    of half a voxel sum to 1 within ±1.4 % per axis (2 exp(-π²/2)), a ripple of a particle's
    merged intensity with its position inside the voxel.
    """
    import scipy.ndimage

    v = np.asarray(volume, dtype=np.float32)
    nz, wy, wx = v.shape
    if wy % ky or wx % kx:
        raise ValueError(f"volume of shape {v.shape} is not subdivided by ({ky}, {kx})")
    if kernel == "box":
        return v.reshape(nz, wy // ky, ky, wx // kx, kx).sum(axis=(2, 4), dtype=np.float32)
    if kernel != "gaussian":
        raise ValueError(f"kernel = {kernel!r}: expected 'gaussian' or 'box'")
    for axis, k in ((1, ky), (2, kx)):
        if k == 1:
            continue
        f = scipy.ndimage.gaussian_filter1d(v, 0.5 * k, axis=axis, mode="constant")
        take = [slice(None)] * 3
        take[axis] = slice(k // 2, None, k)
        sampled = f[tuple(take)]
        if k % 2 == 0:             # the centre lies between two working voxels
            take[axis] = slice(k // 2 - 1, None, k)
            sampled = 0.5 * (sampled + f[tuple(take)])
        v = (sampled * k).astype(np.float32)
    return v



def unbin_depth(volume, kz: int, grid: VolumeGrid) -> np.ndarray:
    """A volume on depth slices ``kz`` times as deep resampled onto ``grid``'s slices, float32.

    ``volume`` is ``(ceil(nz / kz), ny, nx)`` on ``subdivided_grid(grid, 1, 1, kz)``'s
    slices. Each of the grid's slices takes the cubic interpolating spline through the
    working slices at its depth (linear through fewer than four; held at the outer working
    slices beyond them), divided by ``kz`` so that the total is kept (a working voxel holds
    the light of ``kz`` of the grid's); the spline's undershoot beside a peak is clipped at
    zero. A particle's depth profile, about a depth cell long and sampled by at least three
    working slices, is kept with its centre (unlike a piecewise-linear resampling, whose
    peaks all lie on working slices).
    """
    from scipy.interpolate import make_interp_spline

    v = np.asarray(volume, dtype=np.float32)
    nz = grid.shape[0]
    wz = v.shape[0]
    if kz == 1:
        return v
    if wz != -(-nz // kz) or v.shape[1:] != tuple(grid.shape[1:]):
        raise ValueError(f"volume of shape {v.shape} is not {grid.shape} binned by {kz} "
                         "in depth")
    # positions of the grid's slice centres in working slices
    at = (np.arange(nz) - 0.5 * (nz - 1)) / kz + 0.5 * (wz - 1)
    at = np.clip(at, 0.0, wz - 1.0)
    if wz == 1:
        return np.repeat(v / np.float32(kz), nz, axis=0)
    spline = make_interp_spline(np.arange(wz, dtype=float), v.reshape(wz, -1),
                                k=min(3, wz - 1), axis=0)
    out = np.empty((nz, v.shape[1] * v.shape[2]), np.float32)
    for i0 in range(0, nz, 16):        # a few slices at a time: float64 work arrays stay small
        out[i0:i0 + 16] = spline(at[i0:i0 + 16])
    np.maximum(out, 0.0, out=out)
    out *= np.float32(1.0 / kz)
    return out.reshape(grid.shape)


def to_volume_grid(volume, work: VolumeGrid, grid: VolumeGrid, *,
                   kernel: str = "gaussian") -> np.ndarray:
    """The working grid's volume on ``grid``: laterally merged, then resampled in depth."""
    kz, ky, kx = working_factors(work, grid)
    v = np.asarray(volume, dtype=np.float32).reshape(work.shape)
    if ky > 1 or kx > 1:
        v = merge_subdivided(v, ky, kx, kernel=kernel)
    return unbin_depth(v, kz, grid) if kz > 1 else v


def working_factors(work: VolumeGrid, grid: VolumeGrid) -> tuple[int, int, int]:
    """``(kz, ky, kx)`` when ``work`` is ``subdivided_grid(grid, ky, kx, kz)``.

    ReconstructionError otherwise: weights built for another grid.
    """
    nz, ny, nx = grid.shape
    wz, wy, wx = work.shape
    kz = int(round(float(work.voxel[2]) / float(grid.voxel[2])))
    if kz >= 1 and wz == -(-nz // kz) and wy % ny == 0 and wx % nx == 0:
        ky, kx = wy // ny, wx // nx
        expect = subdivided_grid(grid, ky, kx, kz)
        scale = max(grid.voxel)
        if (np.allclose(expect.origin, work.origin, rtol=0, atol=1e-9 * scale)
                and np.allclose(expect.voxel, work.voxel, rtol=1e-9, atol=0)):
            return kz, ky, kx
    raise ReconstructionError("the given weights were built for another volume grid (neither "
                              "the volume's grid nor a lateral subdivision or depth binning "
                              "of it)")

