"""Particles that merged in the volume, told apart by their rays.

Two particles closer than about a resolution cell make one peak in the volume, twice as
bright as a single particle. :func:`split_bright` seeds the ray-bundle fit of each peak
whose rays carry ``factor`` times the median light near its depth with two points, either
side of the peak along the long axis of its blob, and keeps the two where the rays part them by a
plausible distance (:data:`PARTED_CELLS`); otherwise the peak stays one particle at its
single fit. Effective coordinates, metres. See docs/methods.md#merged-particles.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.lightfield import LightField
from plenopiv.particles.bundle import PARTICLE_BUNDLE, BundleSettings, bundle_positions

__all__ = ["PARTED_CELLS", "REFERENCE_CELLS", "REFERENCE_MIN_PARTICLES", "SEED_OFFSET_CELLS",
           "SplitParticles", "blob_axes", "reference_brightness", "split_bright"]

#: Distance of each of the two seeds from the peak, in resolution cells along the blob's axis.
SEED_OFFSET_CELLS = 0.7

#: The two fits are kept as two particles where they end this far apart (resolution cells,
#: the cell's semi-axes as unit): nearer, both seeds found the same particle; farther, one
#: ran off to a neighbour's light. Chosen with ``split_brighter`` = 1.3 on seeds 7, 11 and 13
#: of docs/validation/merged_particles.md's set-up (the page's seeds are held out), at 0.3
#: particles per lenslet equally bright / with a brightness spread of 0.3: detection 0.954
#: with 1.1 % ghosts / 0.948 with 2.1 %; factor 1.4: 0.947, 0.5 % / 0.939, 1.7 %; factor 1.4
#: and 0.3-2.0 cells: 0.955, 0.6 % / 0.946, 4.1 %; factor 1.4 and 0.6-2.0: 0.943, 0.5 % /
#: 0.936, 1.1 %.
PARTED_CELLS = (0.5, 2.0)

#: The light a peak is compared with: the median of the particles within this many depth
#: cells of its depth (where the light a particle sends through the aperture varies with
#: depth, e.g. at the edge of the field), or of all where fewer than
#: :data:`REFERENCE_MIN_PARTICLES` are that near.
REFERENCE_CELLS = 1.5
REFERENCE_MIN_PARTICLES = 8

#: Voxels ``(z, y, x)`` each side of the peak from which its blob's axis is measured.
BLOB_REACH_VOX = (2, 1, 1)


class SplitParticles(NamedTuple):
    """Particles after :func:`split_bright`: the N found, then one more for each split.

    position : (M, 3) float64, effective metres. source : (M,) int64, the found particle each
    stands for. split : (M,) bool, True for both halves of a split particle.
    """

    position: np.ndarray
    source: np.ndarray
    split: np.ndarray


def blob_axes(volume, grid: VolumeGrid, centres, cell) -> np.ndarray:
    """Unit vector ``(x, y, z)`` of the longest axis of each particle's blob, in cell units.

    The intensity-weighted covariance of the voxels within :data:`BLOB_REACH_VOX` of the
    voxel holding each centre (above a tenth of the block's maximum), with lengths measured in
    resolution cells ``cell = (lateral, lateral, depth)`` metres. ``centres``: (N, 3), metres.
    """
    vol = np.asarray(volume)
    centres = np.asarray(centres, float).reshape(-1, 3)
    voxel, origin = np.asarray(grid.voxel, float), np.asarray(grid.origin, float)
    centre_vox = np.rint((centres - origin) / voxel).astype(np.int64)      # x, y, z
    steps = [np.arange(-r, r + 1) for r in BLOB_REACH_VOX]                 # z, y, x
    dz, dy, dx = (a.ravel() for a in np.meshgrid(*steps, indexing="ij"))
    offsets = np.column_stack([dx, dy, dz])
    idx = centre_vox[:, None, :] + offsets[None, :, :]                     # (N, K, 3)
    inside = np.all((idx >= 0) & (idx < np.array(grid.shape[::-1])), axis=2)
    idx = np.clip(idx, 0, np.array(grid.shape[::-1]) - 1)
    w = np.where(inside, vol[idx[..., 2], idx[..., 1], idx[..., 0]], 0.0).astype(float)
    w = np.maximum(w - 0.1 * w.max(axis=1, keepdims=True), 0.0)
    at = offsets * voxel / np.asarray(cell, float)                        # cells
    total = np.maximum(w.sum(axis=1), 1e-300)
    mean = w @ at / total[:, None]
    d = at[None, :, :] - mean[:, None, :]
    cov = np.einsum("nk,nki,nkj->nij", w, d, d) / total[:, None, None]
    axis = np.linalg.eigh(cov)[1][:, :, -1]
    return axis


def reference_brightness(depth, brightness, depth_cell: float) -> np.ndarray:
    """The median brightness of the particles near each one's depth (:data:`REFERENCE_CELLS`).

    ``depth``: (N,) metres; ``brightness``: (N,); ``depth_cell``: metres. Computed on bins of
    one depth cell: each bin takes the median of the particles in it and the bins within
    :data:`REFERENCE_CELLS` (rounded up) of it; bins holding fewer than
    :data:`REFERENCE_MIN_PARTICLES` take the median of all.
    """
    depth, brightness = np.asarray(depth, float), np.asarray(brightness, float)
    everywhere = float(np.median(brightness))
    bins = np.floor((depth - depth.min()) / depth_cell).astype(np.int64)
    reach = int(np.ceil(REFERENCE_CELLS))
    order = np.argsort(bins, kind="stable")
    edges = np.searchsorted(bins[order], np.arange(bins.max() + 2))
    per_bin = np.full(bins.max() + 1, everywhere)
    for k in range(len(per_bin)):
        near = brightness[order[edges[max(k - reach, 0)]:edges[min(k + reach + 1,
                                                                   len(edges) - 1)]]]
        if len(near) >= REFERENCE_MIN_PARTICLES:
            per_bin[k] = np.median(near)
    return per_bin[bins]


def split_bright(lf: LightField, image, centroids, positions, brightness, light, *,
                 factor: float, cell, volume, grid: VolumeGrid,
                 settings: BundleSettings = PARTICLE_BUNDLE) -> SplitParticles:
    """Fit the peaks brighter than ``factor`` times the median as two particles each.

    A peak stays two particles where the rays part its two fits by :data:`PARTED_CELLS`.

    Parameters
    ----------
    lf : LightField
        The lit rays of the image (:func:`~plenopiv.particles.bundle.lit_rays`).
    image : ndarray
        The raw image of ``lf``'s sensor.
    centroids, positions : (N, 3) array_like
        The volume's centroids and the single ray-bundle fits, effective metres.
    brightness : (N,) array_like
        The volume's integrated intensity of each particle (the fits' shares of the rays).
    light : (N,) array_like
        The image's light each single fit gathered
        (:attr:`~plenopiv.particles.bundle.BundlePositions.light`).
    factor : float
        Peaks whose ``light`` is at least this many times the median near their depth
        (:func:`reference_brightness`) are tried (> 1). The rays' light of two particles in
        one peak is twice a single's wherever they lie; the volume's intensity of a pair
        behind one another in depth is only 1.2-1.4 times.
    cell : (3,) array_like
        Resolution cell ``(lateral, lateral, depth)``, metres: the unit of the seeds'
        offset (:data:`SEED_OFFSET_CELLS`) and of the parting (:data:`PARTED_CELLS`).
    volume, grid : the reconstructed volume ``[z, y, x]`` and its grid (the blobs' axes).
    settings : BundleSettings
        Of the fit (default :data:`~plenopiv.particles.bundle.PARTICLE_BUNDLE`).

    Notes
    -----
    One fit serves every tried peak: its two seeds share the rays with each other and with
    all other particles, held at their single fits' brightness. The halves take half the
    peak's brightness.
    """
    centroids = np.asarray(centroids, float).reshape(-1, 3)
    positions = np.asarray(positions, float).reshape(-1, 3)
    brightness = np.asarray(brightness, float).reshape(-1)
    light = np.asarray(light, float).reshape(-1)
    n = len(positions)
    none = SplitParticles(positions, np.arange(n), np.zeros(n, bool))
    if n == 0:
        return none
    cell = np.asarray(cell, float)
    reference = reference_brightness(positions[:, 2], light, float(cell[2]))
    tried = np.flatnonzero(light >= factor * reference)
    if len(tried) == 0:
        return none
    step = SEED_OFFSET_CELLS * blob_axes(volume, grid, centroids[tried], cell) * cell
    rest = np.setdiff1d(np.arange(n), tried)
    seeds = np.concatenate([positions[rest], centroids[tried] + step, centroids[tried] - step])
    half = 0.5 * brightness[tried]
    fit = bundle_positions(lf, image, seeds, settings=settings, depth_cell=float(cell[2]),
                           brightness=np.concatenate([brightness[rest], half, half]))
    m, k = len(rest), len(tried)
    a, b = fit.position[m:m + k], fit.position[m + k:]
    apart = np.linalg.norm((a - b) / cell, axis=1)
    keep = (fit.converged[m:m + k] & fit.converged[m + k:]
            & (apart >= PARTED_CELLS[0]) & (apart <= PARTED_CELLS[1]))
    out = positions.copy()
    out[tried[keep]] = a[keep]
    split = np.zeros(n + int(keep.sum()), bool)
    split[tried[keep]] = True
    split[n:] = True
    return SplitParticles(np.concatenate([out, b[keep]]),
                          np.concatenate([np.arange(n), tried[keep]]), split)
