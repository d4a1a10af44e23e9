"""The true volume of known particles, against which a reconstruction's quality Q is measured."""

from __future__ import annotations

import numpy as np

from plenopiv.camera.grid import VolumeGrid


def gaussian_truth_volume(grid: VolumeGrid, positions, intensities=None, *,
                          sigma_vox=(1.0, 1.0, 1.0)) -> np.ndarray:
    """The true volume for Q: a Gaussian blob (σ in voxels, z y x) per particle, float32.

    ``positions`` are (x, y, z) in the grid's (effective) coordinates, metres.
    """
    from plenopiv.conventions import world_to_voxel

    vol = np.zeros(grid.shape, np.float32)
    p = world_to_voxel(np.asarray(positions, float), grid.origin, grid.voxel)
    w = np.ones(len(p)) if intensities is None else np.asarray(intensities, float)
    s = np.asarray(sigma_vox, float)
    r = np.ceil(3 * s).astype(int)
    for (cz, cy, cx), wi in zip(p, w, strict=True):
        lo = np.maximum(np.floor([cz, cy, cx]).astype(int) - r, 0)
        hi = np.minimum(np.floor([cz, cy, cx]).astype(int) + r + 2, grid.shape)
        if np.any(hi <= lo):
            continue
        zz, yy, xx = np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi, strict=True)),
                                 indexing="ij")
        g = np.exp(-0.5 * (((zz - cz) / s[0]) ** 2 + ((yy - cy) / s[1]) ** 2
                           + ((xx - cx) / s[2]) ** 2))
        vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] += (wi * g).astype(np.float32)
    return vol

