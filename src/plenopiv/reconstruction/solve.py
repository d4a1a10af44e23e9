"""One image -> one volume on the weights' grid: row scaling, bright rows, line of sight, MART.

:func:`solve_volume` scales the rows of W to a maximum weight of 1 (a view, no copy), leaves
out the rows that barely touch the volume and the masked pixels, takes MLOS with the sub-cell
line of sight as the first guess and runs :func:`plenopiv.reconstruction.mart.reconstruct`,
SMART with the dark pixels that see the first guess's support as ceilings, row-action and
block MART on the bright rows alone.

See docs/methods.md#from-image-to-volume.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction.geometry import ProjectionGeometry
from plenopiv.reconstruction.least_squares import least_squares
from plenopiv.reconstruction.mart import reconstruct
from plenopiv.reconstruction.real_lattice import LensletProjector
from plenopiv.reconstruction.sightline import subcell_sightline

__all__ = ["solve_volume", "touching_rows", "line_of_sight_guess", "perspective_blocks"]

#: A row touches the volume when its largest weight is at least this fraction of the 95th
#: percentile of the rows' largest weights.
TOUCHING_FRACTION = 0.25


def touching_rows(weights) -> np.ndarray:
    """Rows whose beam crosses the volume rather than passing mostly beside it (bool).

    Such rows would claim the light of particles outside the volume.
    """
    row_scale = weights.normalised[1]
    nonempty = weights.row_max > 0
    return nonempty & (row_scale >= TOUCHING_FRACTION
                       * float(np.percentile(row_scale[nonempty], 95)))


def _unmasked_rows(weights, image: np.ndarray, image_mask) -> tuple[np.ndarray, float]:
    """Rows of unmasked pixels (bool) and the brightest unmasked pixel value (counts)."""
    if image_mask is None:
        return np.ones(len(weights.pixel), bool), float(image.max())
    m = np.asarray(image_mask, dtype=bool)
    if m.shape != image.shape:
        raise ReconstructionError(f"image mask has shape {m.shape}: expected the image's "
                                  f"{image.shape} (rows, cols)")
    if not (~m).any():
        raise ReconstructionError("the image mask masks every pixel")
    return ~m.reshape(-1)[weights.pixel], float(image[~m].max())


def solve_volume(weights, image: np.ndarray, settings, *,
                 geometry: ProjectionGeometry | None = None, footprint: float | None = None,
                 image_mask=None, callback: Callable | None = None,
                 solver: str | None = None, solver_options: dict | None = None) -> np.ndarray:
    """The MART volume of one sensor image on ``weights.grid`` (float32, ``[z, y, x]``).

    Parameters
    ----------
    weights : Weights
        W of the reconstruction (explicit or matrix-free; see
        :mod:`plenopiv.reconstruction.weights`).
    image : (rows, cols) ndarray
        The checked sensor image, counts.
    settings : ReconstructionSettings
        ``method``, ``iterations``, relaxation, ``pixel_threshold`` (fraction of the brightest
        unmasked pixel), ``dark_tolerance``.
    geometry : ProjectionGeometry, optional
        What ``weights`` was built from (default ``weights.geometry``): its light field, built
        at most once, serves the sub-cell line of sight and the perspective blocks, and only
        when they need it.
    footprint : float, optional
        Lenslet footprint on the focal plane, metres (default ``geometry.footprint``).
    image_mask : (rows, cols) bool, optional
        Pixels to ignore (True): their rows count neither as light nor as dark.
    callback : callable, optional
        ``callback(iteration, volume)`` after each MART sweep.
    solver : {"fista", "sirt", "cgls"}, optional
        Instead of ``settings.method``, the least-squares solver of
        :func:`plenopiv.reconstruction.least_squares.least_squares` on SMART's rows (dark rows
        as ceilings), ``settings.iterations`` iterations, voxels held to the line of sight's
        support; FISTA and SIRT start from the line of sight, CGLS from zero.
    solver_options : dict, optional
        More keywords of ``least_squares`` (``l1``, ``relaxation``, ``initial``,
        ``support``; ``support=None`` frees every voxel), and ``smart_sweeps``: that many
        SMART sweeps (``settings.relaxation_used``) from the solver's volume.
    """
    geometry = weights.geometry if geometry is None else geometry
    if geometry is None:
        raise ReconstructionError("solve_volume: the weights carry no ProjectionGeometry; pass "
                                  "geometry= (the calibration, grid, f_number and min_lit they "
                                  "were built from)")
    if footprint is None:
        footprint = geometry.footprint
    proj, row_scale = weights.normalised
    raw = weights.image_vector(image)
    usable, peak_value = _unmasked_rows(weights, image, image_mask)
    threshold = settings.pixel_threshold * peak_value
    touching = touching_rows(weights) & usable
    bright = (raw > threshold) & touching
    if not bright.any():
        raise ReconstructionError(f"no pixel seen by the volume is above the threshold "
                                  f"{threshold:g} ([reconstruction] pixel_threshold = "
                                  f"{settings.pixel_threshold}): is the volume in view?")
    floor = max(threshold, 1e-6 * float(image.max()))
    first, used, used_sums = _line_of_sight(weights, raw, floor, touching, bright, geometry,
                                            tolerance=settings.dark_tolerance,
                                            footprint=footprint)
    common = dict(iterations=settings.iterations, relaxation=settings.relaxation_used,
                  pixel_threshold=0.0, initial=first, shape=weights.grid.shape,
                  callback=callback)
    if settings.method == "smart" or solver is not None:
        # the dark pixels take part as ceilings: their light is at most the threshold, so
        # they lower the voxels that would send more into them and never raise any; only
        # those that see the first guess's support can change anything
        if isinstance(proj, LensletProjector):
            # all touching rows (bright ones included): a row whose beams miss the first
            # guess's support projects to zero and changes nothing, now or later (the
            # support only shrinks), and its lenslet's empty patches are skipped by the
            # kernels. The view then depends on the geometry and mask alone, so the next
            # image reuses its column sums, and no forward projection of the support selects
            # the rows. When they are the line of sight's used rows, the column sums are
            # those the line of sight pooled from its cells (no back projection at all)
            rows = touching
            same = used_sums is not None and np.array_equal(used, rows)
            view = proj.summed_row_view(rows, column_sums=used_sums if same else None)
        else:
            reach = np.asarray(proj.forward((first > 0).astype(np.float32))) > 0
            rows = bright | (touching & reach)
            view = proj.select_rows(rows)
        values = np.maximum(raw[rows], np.float32(floor)) / row_scale[rows]
        if solver is not None:
            options = dict(solver_options or {})
            sweeps = options.pop("smart_sweeps", 0)
            volume = _least_squares(values, view, ~bright[rows], first, solver, settings,
                                    options, callback)
            if not sweeps:
                return volume.reshape(weights.grid.shape)
            common.update(iterations=sweeps, initial=volume, callback=None)
        return reconstruct(values, view, method="smart", ceiling=~bright[rows], **common)
    blocks = None
    if settings.method == "block":
        blocks = perspective_blocks(weights, geometry.light_field)[bright]
    return reconstruct(raw[bright] / row_scale[bright], proj.select_rows(bright),
                       method=settings.method, blocks=blocks, **common)


def _least_squares(values, view, ceiling, first, solver, settings, options, callback):
    """:func:`least_squares` of the selected rows, the line of sight as support and start."""
    kw = dict(support=first.reshape(-1) > 0,
              initial=None if solver == "cgls" else first.reshape(-1))
    kw.update(options or {})
    return least_squares(values, view, solver=solver, iterations=settings.iterations,
                         ceiling=ceiling, callback=callback, **kw)


def line_of_sight_guess(weights, raw, floor: float, touching, bright, geometry, *,
                        tolerance: float, footprint: float) -> np.ndarray:
    """Return the first guess of MART: MLOS judged on sub-voxel cells.

    A voxel is empty unless some lit pixel sees it and one of its sub-cells has at most
    ``tolerance`` of its weight on dark pixels (the soft line-of-sight mask,
    :mod:`plenopiv.reconstruction.sightline`); otherwise it takes the largest MLOS value of
    its sub-cells, the weighted geometric mean of the normalised intensities I_i/R_i of the
    rows that see the cell, dark rows entering with the noise floor ``floor`` (counts).
    Judged per voxel instead, a grid whose voxel edges cross the lenslets would empty the
    voxels of in-focus particles.
    """
    return _line_of_sight(weights, raw, floor, touching, bright, geometry,
                          tolerance=tolerance, footprint=footprint)[0]


def _line_of_sight(weights, raw, floor, touching, bright, geometry, *, tolerance,
                   footprint) -> tuple:
    """``(first guess, used rows, their coarse column sums or None)``: see line_of_sight_guess.

    "Seen by a lit pixel" comes from the line of sight's own cell sums where it gives it
    (the per-lenslet projector), else from a back projection of the bright rows.
    """
    proj, row_scale = weights.normalised
    row_sums = np.asarray(proj.row_sums())
    used = touching & (row_sums > 0)
    log_values = np.zeros(len(raw), np.float32)
    log_values[used] = np.log(np.maximum(raw[used], floor) / row_scale[used] / row_sums[used])
    sl = subcell_sightline(weights, geometry, touching & ~bright, log_values, used,
                           tolerance=tolerance, footprint=footprint)
    if sl.seen_by_lit is not None:
        seen_lit = sl.seen_by_lit
    else:
        seen_lit = np.asarray(proj.back(bright.astype(np.float32))) > 0
    return np.where(sl.keep & seen_lit, sl.guess, np.float32(0.0)), used, sl.used_column_sums


def perspective_blocks(weights, lf) -> np.ndarray:
    """Block label of each weight row: its perspective view (aperture cell) in ``lf``.

    A block holds one pixel per lenslet, and its pixels share few voxels.
    """
    idx = np.searchsorted(lf.pixel, weights.pixel)       # lf.pixel is sorted
    cell = np.rint(lf.u[idx] / lf.cell)
    _, labels = np.unique(cell, axis=0, return_inverse=True)
    return labels.ravel().astype(np.int64)
