"""What a projector is built from: one calibration's light field and one volume grid.

:class:`ProjectionGeometry` is the start of every reconstruction: the calibration, the
working grid, the f-number and the lit fraction that choose the rays. Its light field is built
on first use and shared by the weights, the sub-cell line of sight and the perspective blocks
(:meth:`ProjectionGeometry.on_grid`: another grid, the same light field). The checks that
depend on the geometry alone live here too: :func:`check_grid_in_view`,
:func:`separable_axes` (the condition of the lattice projector), :func:`footprint` and
:func:`subcell_factors`. The module calls nothing downstream of it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.resolution import footprint
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import LightField, light_field
from plenopiv.products.jsonio import dumps

__all__ = ["CELLS_PER_FOOTPRINT", "SEPARABLE_TOLERANCE", "SLAB_VOXELS", "WEIGHTS_VERSION",
           "ProjectionGeometry", "check_grid_in_view", "separable_axes",
           "subcell_factors", "weights_key"]

#: Version of the beam model in the weights' key: weights cached by an older model are
#: rebuilt.
WEIGHTS_VERSION = 3

#: Largest scatter of a line's rays, as a fraction of an aperture cell (u) and of a lenslet
#: footprint (focal-plane x), that the lattice projector replaces by the line's mean. A
#: calibrated light field takes u from each lenslet's measured focal spot, so u scatters by
#: the spot noise, a few hundredths of a cell after a good lattice fit. 0.1 cell (spot
#: centres within 0.1 px of their column's) moves a beam by a tenth of its width; a rotation
#: of 0.1 mrad already exceeds it across 60 lenslets of 17 px.
SEPARABLE_TOLERANCE = 0.1

#: Sub-cells per lenslet footprint along each lateral axis (at least): cells of ≤ b/2.
CELLS_PER_FOOTPRINT = 2
#: Refined voxels per depth slab (bounds the memory of one refined projection: with the
#: lattice projector its buffer is slices × refined rows × sensor columns float32).
SLAB_VOXELS = 20_000_000


def subcell_factors(grid: VolumeGrid, footprint: float) -> tuple[int, int]:
    """Sub-cells per voxel along x and y: ``ceil(CELLS_PER_FOOTPRINT · voxel / footprint)``.

    Parameters
    ----------
    grid : VolumeGrid
    footprint : float
        Lenslet footprint on the focal plane, metres (effective).
    """
    if not footprint > 0:
        raise ReconstructionError(f"lenslet footprint {footprint!r} m: expected > 0")
    return tuple(max(1, math.ceil(CELLS_PER_FOOTPRINT * float(v) / footprint - 1e-9))
                 for v in grid.voxel[:2])


def weights_key(calibration: Calibration, grid: VolumeGrid, *, f_number: float | None,
                min_lit: float, min_weight: float) -> str:
    """SHA-256 of everything the weights depend on."""
    h = hashlib.sha256()
    h.update(dumps({"v": WEIGHTS_VERSION, "camera": calibration.camera.to_dict(),
                         "si": round(calibration.image_distance, 15), "grid": grid.key(),
                         "f_number": f_number, "min_lit": min_lit, "min_weight": min_weight},
                        sort_keys=True).encode())
    for arr in (calibration.centre_px, calibration.focal_spot_px, calibration.grid_index):
        h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    return h.hexdigest()


def check_grid_in_view(lf: LightField, grid: VolumeGrid) -> None:
    """Raise if the grid lies outside the field of view or crosses the main lens."""
    zmin = grid.bounds[2, 0]
    if zmin <= -0.9 * lf.object_distance:
        raise ReconstructionError(f"[volume] z_mm starts at {zmin * 1e3:.4g} mm, within 10 % of "
                                  f"the main lens (S_o,eff = {lf.object_distance * 1e3:.4g} mm)")
    xf = lf.focal_plane_position
    half = np.abs(xf).max(axis=0) + lf.footprint
    b = grid.bounds
    if (b[0, 0] > half[0] or b[0, 1] < -half[0] or b[1, 0] > half[1] or b[1, 1] < -half[1]):
        raise ReconstructionError(
            f"[volume] x_mm = {(b[0] * 1e3).round(3).tolist()}, y_mm = "
            f"{(b[1] * 1e3).round(3).tolist()} lies outside the field of view "
            f"(±{half[0] * 1e3:.3g} mm × ±{half[1] * 1e3:.3g} mm at the focal plane)")


def separable_axes(lf: LightField, *, tolerance: float = SEPARABLE_TOLERANCE) -> tuple | None:
    """Per-column and per-row ray coordinates, or None when the rays are not separable.

    Returns ``(u_col, xf_col, u_row, xf_row)`` (metres, one value per sensor column/row;
    NaN where no ray lies) when every ray's aperture x and focal-plane x depend only on its
    sensor column, and its y coordinates only on its row, within ``tolerance`` of an aperture
    cell and of a lenslet footprint respectively. The aperture coordinate of a line is that
    of its fully lit pixels' cell centres; a line with only edge pixels (cut by the aperture)
    takes its neighbour's minus its offset in cells.
    """
    rows, cols = lf.shape
    r = lf.pixel // cols
    c = lf.pixel % cols
    xf = lf.focal_plane_position
    full = lf.lit >= 1.0 - 1e-9
    out = []
    for line, n, axis in ((c, cols, 0), (r, rows, 1)):
        x_line = _line_mean(line, xf[:, axis], np.ones_like(full), n)
        u_line = _line_mean(line, lf.u[:, axis], full, n)
        _fill_edge_lines(u_line, x_line, lf.cell, lf.footprint)
        du = np.abs(lf.u[full, axis] - u_line[line[full]])
        dx = np.abs(xf[:, axis] - x_line[line])
        if (du.size and du.max() > tolerance * lf.cell) or dx.max() > tolerance * lf.footprint:
            return None
        out += [u_line, x_line]
    return tuple(out)


def _line_mean(line, values, use, n):
    """Mean of ``values`` over the rays ``use`` of each line (NaN where none)."""
    total = np.bincount(line[use], weights=values[use], minlength=n)
    count = np.bincount(line[use], minlength=n)
    with np.errstate(invalid="ignore", divide="ignore"):
        return total / count


def _fill_edge_lines(u_line, x_line, cell, footprint, reach=4):
    """Give lines with rays but no fully lit ray the aperture coordinate of their cell centre.

    The coordinate is that of the nearest line of the same lenslet, minus the offset times a cell
    (u = -(pixel - spot) · cell).
    """
    missing = np.flatnonzero(np.isnan(u_line) & np.isfinite(x_line))
    n = len(u_line)
    for d in range(1, reach + 1):
        if not missing.size:
            return
        for step in (d, -d):
            q = missing + step
            ok = (q >= 0) & (q < n)
            p, q = missing[ok], q[ok]
            good = np.isfinite(u_line[q]) & (np.abs(x_line[q] - x_line[p]) < 0.5 * footprint)
            u_line[p[good]] = u_line[q[good]] + step * cell
            missing = np.flatnonzero(np.isnan(u_line) & np.isfinite(x_line))
            if not missing.size:
                return


@dataclass(frozen=True, eq=False)
class ProjectionGeometry:
    """The rays of one calibration and one volume grid, the light field built once and held.

    Parameters
    ----------
    calibration : Calibration
        The camera and its effective S_i.
    grid : VolumeGrid
        The working grid (effective coordinates, metres).
    f_number : float, optional
        Aperture of the recording (default: the camera's).
    min_lit : float
        Pixels whose aperture cell is at least this fraction inside the aperture are rays.

    Notes
    -----
    The light field (:attr:`light_field`) depends on the calibration, ``f_number`` and
    ``min_lit`` only, not on the grid: the geometries of other grids made by :meth:`on_grid`
    share it, and it is computed at most once for all of them. Two geometries compare equal
    only when they are the same object.
    """

    calibration: Calibration
    grid: VolumeGrid
    f_number: float | None = None
    min_lit: float = 0.5
    _shared: dict = field(default_factory=dict, repr=False)

    @classmethod
    def for_settings(cls, calibration: Calibration, grid: VolumeGrid,
                     settings) -> ProjectionGeometry:
        """The geometry of ``settings`` (``f_number``, ``min_lit``: ReconstructionSettings)."""
        return cls(calibration, grid, settings.f_number, settings.min_lit)

    def on_grid(self, grid: VolumeGrid) -> ProjectionGeometry:
        """The same rays on ``grid``: the light field is shared, not built again."""
        if grid == self.grid:
            return self
        return dataclasses.replace(self, grid=grid)

    @property
    def light_field(self) -> LightField:
        """The rays of the lit pixels (:func:`plenopiv.lightfield.light_field`), built once."""
        lf = self._shared.get("light_field")
        if lf is None:
            lf = light_field(self.calibration, f_number=self.f_number, min_lit=self.min_lit)
            self._shared["light_field"] = lf
        return lf

    @property
    def separable_axes(self) -> tuple | None:
        """:func:`separable_axes` of the light field (computed once), None when not separable."""
        if "separable_axes" not in self._shared:
            self._shared["separable_axes"] = separable_axes(self.light_field)
        return self._shared["separable_axes"]

    @property
    def footprint(self) -> float:
        """Lenslet footprint on the focal plane of the effective camera, metres."""
        return footprint(self.calibration.effective_camera)

    def key(self, min_weight: float = 1e-7) -> str:
        """The weights cache key of this geometry (:func:`weights_key`)."""
        return weights_key(self.calibration, self.grid, f_number=self.f_number,
                           min_lit=self.min_lit, min_weight=min_weight)

    def check_in_view(self) -> None:
        """Raise ReconstructionError if the grid is out of view (:func:`check_grid_in_view`)."""
        check_grid_in_view(self.light_field, self.grid)
