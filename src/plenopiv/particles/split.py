"""Particles that merged in the volume, told apart by their rays.

Two particles closer than about a resolution cell make one peak in the volume, twice as
bright as a single particle. :func:`split_bright` seeds the ray-bundle fit of each peak
whose rays carry ``factor`` times the median light near its depth with two points, either
side of the peak along the long axis of its blob, and keeps the two where the rays part them
by a plausible distance (:data:`PARTED_CELLS`); where the two fits meet but the rays carry
the light of two, a mixture of lines along the depth parts them (:func:`mixture_pairs`).
Otherwise the peak stays one particle at its single fit. Effective coordinates, metres. See
docs/methods.md#merged-particles.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.lightfield import LightField
from plenopiv.particles.bundle import (
    PARTICLE_BUNDLE,
    BundleSettings,
    RayTable,
    _half_beam,
    _select_rays,
    bundle_positions,
    closest_points,
    ray_lines,
    ray_table,
    ray_weights,
)

__all__ = ["MIXTURE_LIGHT", "PARTED_CELLS", "REFERENCE_CELLS", "REFERENCE_MIN_PARTICLES",
           "SEED_OFFSET_CELLS", "SplitParticles", "blob_axes", "mixture_pairs",
           "reference_brightness", "split_bright"]

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

#: A tried peak whose shared fits met is parted again by :func:`mixture_pairs` where its rays
#: carry at least this many times the reference light (two particles nearly behind one
#: another: the shared fit gives both the rays of the central views, and they meet). On the
#: seeds the bounds were chosen on, at 0.3 particles per lenslet equally bright / with a
#: brightness spread of 0.3: detection 0.954 → 0.963 with 1.1 % ghosts / 0.948 → 0.954 with
#: 2.1 → 3.4 % (1.7: 0.964 / 0.955 with 1.1 / 3.8 %).
MIXTURE_LIGHT = 1.8
#: The mixture's iterations, and the width of a ray's membership about a point (the σ of a
#: Gaussian in the point's half beam widths).
MIXTURE_ITERATIONS = 20
MIXTURE_WIDTH = 0.5
#: Rays within this many half beam widths of the peak's single fit take part; particles
#: within :data:`MIXTURE_NEIGHBOURS` resolution cells compete for them, held where they are.
MIXTURE_REACH = 1.5
MIXTURE_NEIGHBOURS = 4.0
#: Each of the two must hold at least this share of the pair's light.
MIXTURE_MIN_SHARE = 0.25
#: Peaks per vectorised chunk of the mixture (memory only).
MIXTURE_CHUNK = 64

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

    @classmethod
    def unsplit(cls, positions) -> SplitParticles:
        """The particles as found: none split."""
        n = len(positions)
        return cls(positions, np.arange(n), np.zeros(n, bool))


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
                 settings: BundleSettings = PARTICLE_BUNDLE,
                 table: RayTable | None = None) -> SplitParticles:
    """Fit the peaks whose rays carry ``factor`` times the median light as two particles.

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
    table : RayTable, optional
        :func:`~plenopiv.particles.bundle.ray_table` of ``lf``, when already built.

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
    if n == 0:
        return SplitParticles.unsplit(positions)
    table = ray_table(lf) if table is None else table
    cell = np.asarray(cell, float)
    reference = reference_brightness(positions[:, 2], light, float(cell[2]))
    tried = np.flatnonzero(light >= factor * reference)
    if len(tried) == 0:
        return SplitParticles.unsplit(positions)
    step = SEED_OFFSET_CELLS * blob_axes(volume, grid, centroids[tried], cell) * cell
    rest = np.setdiff1d(np.arange(n), tried)
    seeds = np.concatenate([positions[rest], centroids[tried] + step, centroids[tried] - step])
    half = 0.5 * brightness[tried]
    fit = bundle_positions(lf, image, seeds, settings=settings, depth_cell=float(cell[2]),
                           brightness=np.concatenate([brightness[rest], half, half]),
                           table=table)
    m, k = len(rest), len(tried)
    a, b = fit.position[m:m + k], fit.position[m + k:]
    apart = np.linalg.norm((a - b) / cell, axis=1)
    keep = (fit.converged[m:m + k] & fit.converged[m + k:]
            & (apart >= PARTED_CELLS[0]) & (apart <= PARTED_CELLS[1]))
    out = positions.copy()
    out[tried[keep]] = a[keep]
    first, second, source = [out], [b[keep]], [tried[keep]]
    # where the shared fits met but the rays carry the light of two: the mixture of lines
    again = np.flatnonzero(~keep & (light[tried] >= MIXTURE_LIGHT * reference[tried]))
    if len(again):
        peaks = tried[again]
        # along the depth: two particles whose shared fits meet lie nearly on one line of sight
        along = np.array([0.0, 0.0, SEED_OFFSET_CELLS * cell[2]])
        ma, mb, share = mixture_pairs(lf, image, positions[peaks] - along,
                                      positions[peaks] + along,
                                      np.concatenate([out, b[keep]]), peaks, cell, table)
        apart = np.linalg.norm((ma - mb) / cell, axis=1)
        ok = (np.all(np.isfinite(ma), axis=1) & np.all(np.isfinite(mb), axis=1)
              & (apart >= PARTED_CELLS[0]) & (apart <= PARTED_CELLS[1])
              & (np.minimum(share, 1.0 - share) >= MIXTURE_MIN_SHARE))
        out[peaks[ok]] = ma[ok]
        second.append(mb[ok])
        source.append(peaks[ok])
    extra = np.concatenate(source)
    split = np.zeros(n + len(extra), bool)
    split[extra] = True
    split[n:] = True
    return SplitParticles(np.concatenate(first + second), np.concatenate([np.arange(n), extra]),
                          split)


def _memberships(lf: LightField, point, origin, direction) -> np.ndarray:
    """exp(-m²/2σ²) of each ray about ``point`` (rows matched), σ = MIXTURE_WIDTH half beams."""
    v = point - origin
    perp = v - np.sum(v * direction, axis=1)[:, None] * direction
    m = np.linalg.norm(perp, axis=1) / (MIXTURE_WIDTH * _half_beam(lf, point[:, 2]))
    return np.exp(-0.5 * m * m)


def mixture_pairs(lf: LightField, image, start_a, start_b, positions, own, cell,
                  table: RayTable | None = None):
    """Two points from the rays of each peak by a Gaussian mixture of lines.

    ``start_a``, ``start_b``: (K, 3) first points, metres; ``positions``: (N, 3) every
    particle's position, which compete for the rays where within
    :data:`MIXTURE_NEIGHBOURS` cells (``own``: (K,) the index of each peak's own particle,
    left out); ``cell``: (3,) resolution cell, metres; ``table``: :func:`ray_table` of
    ``lf`` when already built. The rays within
    :data:`MIXTURE_REACH` half beams of the mid-point are shared by their memberships
    (:func:`_memberships`) among the two points and the neighbours, and each point is the
    closest point of its share, :data:`MIXTURE_ITERATIONS` times. Unlike the ray-bundle fit's
    cone weights, a ray here belongs mostly to the point it passes nearest, so two points on
    nearly one line of sight part.

    Returns ``(a (K, 3), b (K, 3), share (K,))``: the points and the share of the pair's light
    that ``a`` holds (NaN points where the rays do not define them).
    """
    from scipy.spatial import cKDTree

    table = ray_table(lf) if table is None else table
    weight = ray_weights(lf, image, PARTICLE_BUNDLE.floor)
    a, b = np.array(start_a, float), np.array(start_b, float)
    share = np.full(len(a), np.nan)
    near = cKDTree(positions / cell).query_ball_point(0.5 * (a + b) / cell, MIXTURE_NEIGHBOURS)
    for lo in range(0, len(a), MIXTURE_CHUNK):
        idx = np.arange(lo, min(lo + MIXTURE_CHUNK, len(a)))
        mid = 0.5 * (a[idx] + b[idx])
        pid, ray, _ = _select_rays(lf, table.order, table.ptr, table.lens_ids, table.tree, mid,
                                   MIXTURE_REACH * _half_beam(lf, mid[:, 2]))
        origin, d = ray_lines(lf, ray)
        w = weight[ray]
        # the neighbours' memberships, held fixed
        rest = np.zeros(len(ray))
        for k, i in enumerate(idx):
            rows = np.flatnonzero(pid == k)
            for q in near[i]:
                if q != own[i]:
                    rest[rows] += _memberships(lf, np.broadcast_to(positions[q], (len(rows), 3)),
                                               origin[rows], d[rows])
        pa, pb = a[idx], b[idx]
        alive = np.ones(len(idx), bool)
        for _ in range(MIXTURE_ITERATIONS):
            ma = np.nan_to_num(_memberships(lf, pa[pid], origin, d))
            mb = np.nan_to_num(_memberships(lf, pb[pid], origin, d))
            total = np.maximum(ma + mb + rest, 1e-300)
            group = np.concatenate([2 * pid, 2 * pid + 1])
            pts, _, ok = closest_points(group, np.concatenate([origin, origin]),
                                        np.concatenate([d, d]),
                                        np.concatenate([w * ma / total, w * mb / total]),
                                        2 * len(idx))
            alive &= ok.reshape(-1, 2).all(axis=1)
            pa = np.where(alive[:, None], pts[0::2], np.nan)
            pb = np.where(alive[:, None], pts[1::2], np.nan)
        light_a = np.bincount(pid, w * ma / total, len(idx))
        light_b = np.bincount(pid, w * mb / total, len(idx))
        a[idx], b[idx] = pa, pb
        share[idx] = light_a / np.maximum(light_a + light_b, 1e-300)
    return a, b, share
