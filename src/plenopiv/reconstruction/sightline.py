"""The soft line-of-sight mask, judged on sub-voxel cells so that no grid can empty a particle.

Before MART a voxel is emptied when most of the light that would reach the sensor from it
falls on dark pixels. Judged on the whole voxel this depends on where the voxel edges fall and
can empty an in-focus particle; here a voxel is kept when the best-lit of its lateral sub-cells
(no wider than half a lenslet footprint) is within the tolerance. The refined projector (the
lattice projector, or the per-lenslet one in depth slabs) is built once per weights object and
kept. :func:`subcell_sightline` is the entry point.

See docs/methods.md#line-of-sight.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction._kernels import sightline as _ks
from plenopiv.reconstruction.geometry import (
    SLAB_VOXELS,
    ProjectionGeometry,
    separable_axes,
    subcell_factors,
)
from plenopiv.reconstruction.lattice import LatticeProjector
from plenopiv.reconstruction.real_lattice import LensletProjector

__all__ = ["SightLine", "subcell_factors", "refined_grid", "pool_min", "subcell_line_of_sight",
           "subcell_sightline"]

_CACHE: dict = {}
_LOCK = threading.Lock()


def refined_grid(grid: VolumeGrid, kx: int, ky: int) -> VolumeGrid:
    """``grid`` with every voxel split into ``kx × ky`` lateral cells (same depths, same box)."""
    vx, vy, vz = (float(v) for v in grid.voxel)
    ox, oy, oz = (float(o) for o in grid.origin)
    nz, ny, nx = grid.shape
    return VolumeGrid((ox - vx / 2 + vx / (2 * kx), oy - vy / 2 + vy / (2 * ky), oz),
                      (vx / kx, vy / ky, vz), (nz, ny * ky, nx * kx))


def pool_min(cells: np.ndarray, kx: int, ky: int) -> np.ndarray:
    """Return per voxel the smallest value of its ``kx × ky`` cells.

    ``cells`` is ``(nz, ny·ky, nx·kx)``; the result ``(nz, ny, nx)``.
    """
    nz, fy, fx = cells.shape
    return cells.reshape(nz, fy // ky, ky, fx // kx, kx).min(axis=(2, 4))


def _cells(values, shape) -> np.ndarray:
    """A refined projection as a contiguous float32 ``shape`` array (no copy if it is one)."""
    return np.ascontiguousarray(np.asarray(values, np.float32).reshape(shape))


def _slabs(grid: VolumeGrid, kx: int, ky: int) -> list[tuple[int, int]]:
    nz, ny, nx = grid.shape
    per = max(1, SLAB_VOXELS // max(ny * ky * nx * kx, 1))
    return [(z0, min(z0 + per, nz)) for z0 in range(0, nz, per)]


def _slab_grid(grid: VolumeGrid, z0: int, z1: int) -> VolumeGrid:
    ox, oy, oz = grid.origin
    return VolumeGrid((ox, oy, oz + z0 * grid.voxel[2]), grid.voxel,
                      (z1 - z0, grid.shape[1], grid.shape[2]))


def _light_field_and_axes(geometry) -> tuple:
    """``(light field, separable axes or None)`` of a ProjectionGeometry or a callable.

    A callable returns the light field (built on each call); a geometry holds its own.
    """
    if isinstance(geometry, ProjectionGeometry):
        return geometry.light_field, geometry.separable_axes
    lf = geometry()
    return lf, separable_axes(lf)


def _refined_projectors(weights, geometry, kx: int, ky: int) -> list:
    """Return one projector per depth slab of the refined grid.

    Rows are scaled like ``weights.normalised`` (each by 1/max of its coarse weights); the
    list is cached for the last weights object.
    """
    key = (weights.key or id(weights), kx, ky)
    with _LOCK:
        if _CACHE.get("key") == key:
            return _CACHE["projectors"]
    _, row_scale = weights.normalised
    inv = (1.0 / row_scale).astype(np.float32)
    fine = refined_grid(weights.grid, kx, ky)
    if isinstance(weights.projector, LensletProjector):
        # the same rays on the refined slabs: no light field, no tables to build again
        out = [((z0, z1), weights.projector.on_grid(_slab_grid(fine, z0, z1)).scale_rows(inv))
               for z0, z1 in _slabs(weights.grid, kx, ky)]
        with _LOCK:
            _CACHE.clear()
            _CACHE.update(key=key, projectors=out)
        return out
    lf, axes = _light_field_and_axes(geometry)
    if len(lf.pixel) != len(weights.pixel) or not np.array_equal(lf.pixel, weights.pixel):
        raise ReconstructionError("the light field's rays are not the weights' rows: build both "
                                  "with the same f_number and min_lit")
    # matrix-free on the refined slabs whatever projector the coarse weights use: explicit
    # refined weights, every slab kept for the next image, would hold about twice the coarse
    # non-zeros again (a 49 x 72-lenslet rotated patch: 20 bytes per coarse non-zero, the
    # estimate's 10 exceeded and the process killed at 21 GB)
    lenslets = None if axes is not None else LensletProjector.from_light_field(lf, fine)
    out = []
    for z0, z1 in _slabs(weights.grid, kx, ky):
        g = _slab_grid(fine, z0, z1)
        p = (LatticeProjector.from_light_field(lf, g) if lenslets is None
             else lenslets.on_grid(g))
        out.append(((z0, z1), p.scale_rows(inv)))
    with _LOCK:
        _CACHE.clear()
        _CACHE.update(key=key, projectors=out)
    return out


def _geometry_sums(proj, used: np.ndarray, z0: int) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(Σ_all ŵ, Σ_used ŵ)`` per refined cell of one slab, kept per slab and rows mask.

    ``Σ_used`` is ``proj.back(used)``; with the per-lenslet projector ``Σ_all`` (the column
    sums) adds the back projection of the other rows to it, which costs little when they are
    few (rows whose beams pass beside the volume lie under the array's rim: the kernels skip
    every lenslet without one; 164 of 11.55 M rays in 145 of 55,391 lenslets on the 16 MP
    rotated array), instead of a second full back projection of ones. The rows that enter
    MLOS depend on the geometry only, so every image of a series reuses both; the store is
    emptied with the refined projectors (a new weights object).
    """
    import hashlib

    key = (z0, hashlib.blake2b(np.packbits(used > 0).tobytes(), digest_size=16).hexdigest())
    with _LOCK:
        store = _CACHE.setdefault("used", {})
        hit = store.get(key)
    if hit is None:
        s_used = np.asarray(proj.back(used))
        others = (used <= 0).astype(np.float32)
        if not isinstance(proj, LensletProjector):
            seen = np.asarray(proj.column_sums())    # its cost does not fall with fewer rows
        elif others.any():
            seen = s_used + np.asarray(proj.back(others))
        else:
            seen = s_used
        hit = (seen, s_used)
        with _LOCK:
            if len(store) > 64:
                store.clear()
            store[key] = hit
    return hit


@dataclass(frozen=True)
class SightLine:
    """What the sub-cell line of sight gives (see :func:`subcell_sightline`).

    Attributes
    ----------
    keep : (n_voxels,) bool
        Seen by some row, and some cell has a dark fraction of at most the tolerance.
    guess : (n_voxels,) float32 or None
        The largest MLOS value of the voxel's cells (None without ``log_values``).
    dark_fraction : (nz, ny, nx) float32
        The smallest dark fraction of the voxel's cells (inf where no row sees any).
    used_column_sums : (n_voxels,) float32 or None
        Σ_used ŵ_ij per coarse voxel: the cells' sums pooled, divided by ``kx · ky`` (a
        voxel's weight is the mean of its cells' weights per unit area, so the sum over its
        cells, over ``kx · ky``); equal to the coarse projector's back projection of the used
        rows to float32 rounding. Only where the per-lenslet projector serves the cells and
        ``log_values`` are given (else None).
    seen_by_lit : (n_voxels,) bool or None
        Some used row that is not dark has a positive weight on the voxel: on some cell
        Σ_used − Σ_dark > 0. Only where the per-lenslet projector serves the cells and the
        dark rows are used rows (else None); see :func:`subcell_sightline`.
    """

    keep: np.ndarray
    guess: np.ndarray | None
    dark_fraction: np.ndarray
    used_column_sums: np.ndarray | None = None
    seen_by_lit: np.ndarray | None = None


def subcell_line_of_sight(weights, geometry, dark_rows, log_values=None,
                          used_rows=None, *, tolerance: float,
                          footprint: float) -> tuple:
    """Return ``(keep, guess, dark_fraction)`` of :func:`subcell_sightline`."""
    sl = subcell_sightline(weights, geometry, dark_rows, log_values, used_rows,
                           tolerance=tolerance, footprint=footprint)
    return sl.keep, sl.guess, sl.dark_fraction


def subcell_sightline(weights, geometry, dark_rows, log_values=None,
                      used_rows=None, *, tolerance: float, footprint: float) -> SightLine:
    """Return the soft line-of-sight mask and the MLOS first guess, judged on sub-voxel cells.

    Parameters
    ----------
    weights : Weights
        The coarse weights of the reconstruction.
    geometry : ProjectionGeometry or callable
        What the weights were built from (same rows): its light field is used only when the
        refined projector is not cached. A callable returning the light field also serves.
    dark_rows : (n_pixels,) bool
        Rows counted as dark.
    log_values : (n_pixels,) float, optional
        ln(I_i/R_i) per row for the MLOS guess (skipped when None).
    used_rows : (n_pixels,) bool, optional
        Rows that enter the MLOS guess (default all).
    tolerance : float
        Largest dark fraction of a kept cell (``[reconstruction] dark_tolerance``).
    footprint : float
        Lenslet footprint, metres (sets the cell size, :func:`subcell_factors`).

    Returns
    -------
    SightLine
        ``keep``: seen by some row, and some cell has a dark fraction Σ_dark ŵ_ic /
        Σ_all ŵ_ic (ŵ: weights with each row scaled to a coarse maximum of 1, as MART uses
        them) of at most ``tolerance``; ``guess``: the largest MLOS value of the voxel's
        cells, exp(Σ_used ŵ_ic ln v_i / Σ_used ŵ_ic), 0 where no used row sees a cell;
        ``dark_fraction``; and, with ``log_values``, the used rows' coarse column sums and
        which voxels a used row that is not dark sees.

    Notes
    -----
    ``seen_by_lit`` takes no back projection of its own: Σ_used − Σ_dark on a cell is the
    lit rows' weight on it. The per-lenslet kernels add a ray of zero weight on a cell as an
    exact zero, in an order that does not depend on the image, so where no lit row reaches a
    cell the two sums are equal to the bit and the difference is 0; a lit weight below the
    float32 resolution of the cell's dark weight (~6e-8 of it) may be lost in the difference.
    """
    kx, ky = subcell_factors(weights.grid, footprint)
    dark = np.asarray(dark_rows, np.float32)
    lit_check = False
    if log_values is not None:
        used = (np.ones(len(dark), np.float32) if used_rows is None
                else np.asarray(used_rows, np.float32))
        logv = np.where(used > 0, np.asarray(log_values, np.float32), np.float32(0.0))
        lit_check = not np.any((dark > 0) & (used <= 0))
    nz, ny, nx = weights.grid.shape
    best = np.empty((nz, ny, nx), np.float32)
    projectors = _refined_projectors(weights, geometry, kx, ky)
    per_lenslet = all(isinstance(p, LensletProjector) for _, p in projectors)
    guess = used_sums = lit = None
    if log_values is not None:
        guess = np.empty((nz, ny, nx), np.float32)
        if per_lenslet:
            used_sums = np.empty((nz, ny, nx), np.float32)
            if lit_check:
                lit = np.empty((nz, ny, nx), bool)
    for (z0, z1), proj in projectors:
        shape = (z1 - z0, ny * ky, nx * kx)
        if guess is None:
            seen = np.asarray(proj.column_sums()).reshape(shape)
            d = np.asarray(proj.back(dark)).reshape(shape)
            with np.errstate(invalid="ignore", divide="ignore"):
                frac = np.where(seen > 0, d / seen, np.inf).astype(np.float32)
            best[z0:z1] = pool_min(frac, kx, ky)
            continue
        seen, s_used = (_cells(a, shape) for a in _geometry_sums(proj, used, z0))
        d = _cells(proj.back(dark), shape)
        s_log = _cells(proj.back(logv), shape)
        coarse = (z1 - z0, ny, nx)
        ratio = np.empty(coarse, np.float32)
        has_used = np.empty(coarse, bool)
        u = np.empty(coarse, np.float32)
        lt = np.empty(coarse, bool)
        _ks.pool_cells(seen, d, s_used, s_log, kx, ky, best[z0:z1], ratio, has_used, u, lt)
        # the largest cell value exp(ratio) is exp of the largest ratio (exp is monotonic)
        with np.errstate(over="ignore"):
            guess[z0:z1] = np.where(has_used, np.exp(ratio), np.float32(0.0))
        if used_sums is not None:
            used_sums[z0:z1] = u / np.float32(kx * ky)
        if lit is not None:
            lit[z0:z1] = lt
    keep = best.reshape(-1) <= tolerance
    return SightLine(keep, None if guess is None else guess.reshape(-1), best,
                     None if used_sums is None else used_sums.reshape(-1),
                     None if lit is None else lit.reshape(-1))
