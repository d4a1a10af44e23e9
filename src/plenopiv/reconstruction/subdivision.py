"""The way back from a reconstruction's working grid to the volume's grid.

A reconstruction on a ``[volume]`` grid runs on voxels ``ky × kx`` times finer laterally
(:func:`plenopiv.reconstruction.choose.lateral_subdivision`); :func:`merge_subdivided` returns
its volume to the ``[volume]`` grid, :func:`subdivision_of` finds the subdivision of given
weights.
"""

from __future__ import annotations

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction.choose import subdivided_grid

__all__ = ["merge_subdivided", "subdivision_of"]



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



def subdivision_of(work: VolumeGrid, grid: VolumeGrid) -> tuple[int, int]:
    """``(ky, kx)`` when ``work`` is ``grid`` subdivided laterally, else ReconstructionError."""
    nz, ny, nx = grid.shape
    wz, wy, wx = work.shape
    if wz == nz and wy % ny == 0 and wx % nx == 0:
        ky, kx = wy // ny, wx // nx
        expect = subdivided_grid(grid, ky, kx)
        scale = max(grid.voxel)
        if (np.allclose(expect.origin, work.origin, rtol=0, atol=1e-9 * scale)
                and np.allclose(expect.voxel, work.voxel, rtol=1e-9, atol=0)):
            return ky, kx
    raise ReconstructionError("the given weights were built for another volume grid (neither "
                              "the volume's grid nor a lateral subdivision of it)")

