"""Voxel-pixel weights from the effective image distance: sparse, built in parallel, cached.

Row i of W is the ray of lit pixel i of a :class:`~plenopiv.lightfield.LightField`, column j
voxel j of a :class:`~plenopiv.camera.grid.VolumeGrid` (flat ``[z, y, x]`` order); ``W[i, j]``
is the fraction of the light of a particle spread uniformly over voxel j that reaches pixel i
(a particle of energy 1 gives an image summing to 1), so that I = W E. The beam of a pixel is
the trapezoid profile of its aperture cell and lenslet footprint, integrated over each voxel,
in effective (air-equivalent) coordinates. :func:`build_weights` builds them.

See docs/methods.md#weights.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import LightField
from plenopiv.reconstruction._kernels import weights as K
from plenopiv.reconstruction.geometry import ProjectionGeometry, check_grid_in_view
from plenopiv.reconstruction.lattice import LatticeProjector
from plenopiv.reconstruction.projector import Projector, SparseProjector
from plenopiv.reconstruction.real_lattice import LensletProjector


@dataclass(frozen=True)
class Weights:
    """The weight matrix of one camera calibration and one volume grid.

    Attributes
    ----------
    projector : SparseProjector, LatticeProjector or LensletProjector
        W (rows: lit pixels, columns: voxels): CSR float32 / int32, or computed on the fly
        for an axis-aligned lattice (:mod:`plenopiv.reconstruction.lattice`).
    pixel : (P,) int64
        Flat sensor pixel index of each row.
    grid : VolumeGrid
    key : str
        Hash of what the weights depend on (camera, calibration, grid, options).
    geometry : ProjectionGeometry, optional
        What they were built from (its light field built at most once and shared with the
        line-of-sight mask and the perspective blocks); None for weights made without one.
    """

    projector: SparseProjector | LatticeProjector | LensletProjector
    pixel: np.ndarray
    grid: VolumeGrid
    key: str
    geometry: ProjectionGeometry | None = field(default=None, repr=False, compare=False)

    @functools.cached_property
    def row_max(self) -> np.ndarray:
        """Largest weight of each row, float32 (0 for a row that misses the volume)."""
        return np.asarray(self.projector.row_max(), np.float32)

    @functools.cached_property
    def normalised(self) -> tuple[Projector, np.ndarray]:
        """W with every row scaled to a maximum of 1, and each row's scale (computed once).

        The scaled projector is a row view of W (the CSR is shared, the scale kept per row).
        MART raises a voxel's factor to the power μ w_ij; with the physical weights (fractions
        of a particle's light, ~1e-3) the updates would be tiny. Scaling row i and pixel i by
        the same c_i = 1/max_j w_ij leaves the system I = W E and its solution unchanged.
        Empty rows keep scale 1.
        """
        safe = np.where(self.row_max > 0, self.row_max, 1.0).astype(np.float32)
        return self.projector.scale_rows(1.0 / safe), safe

    @property
    def nnz(self) -> int:
        """Number of stored non-zero weights (0 for the matrix-free lattice projector)."""
        return int(getattr(self.projector, "nnz", 0))

    @property
    def matrix_free(self) -> bool:
        """True for the lattice projector (no stored weights)."""
        return isinstance(self.projector, (LatticeProjector, LensletProjector))

    def image_vector(self, image) -> np.ndarray:
        """The rows' pixel values of a full sensor image, float32 (P,).

        The rows are gathered first and then converted: no float32 copy of the whole image.
        """
        return np.asarray(image).reshape(-1)[self.pixel].astype(np.float32, copy=False)

    def forward_image(self, volume, shape) -> np.ndarray:
        """Project a volume ``[z, y, x]`` into a full sensor image of ``shape``."""
        img = np.zeros(int(np.prod(shape)), np.float32)
        img[self.pixel] = self.projector.forward(np.asarray(volume, np.float32).reshape(-1))
        return img.reshape(shape)


def _kernel_args(lf: LightField, grid: VolumeGrid, min_weight: float, step: int = 1) -> tuple:
    """Arguments of the weight kernels for every ``step``-th ray of ``lf``."""
    xf = lf.focal_plane_position
    rays = tuple(np.ascontiguousarray(a[::step]) for a in (lf.u[:, 0], lf.u[:, 1], xf[:, 0],
                                                            xf[:, 1]))
    lit = np.ascontiguousarray(lf.lit[::step], dtype=np.float64)
    area = math.pi * lf.aperture_radius ** 2
    return (*rays, lit, lf.object_distance, lf.cell, lf.footprint, area,
            np.ascontiguousarray(grid.z, dtype=np.float64), grid.origin[0], grid.origin[1],
            grid.voxel[0], grid.voxel[1], grid.shape[2], grid.shape[1], float(min_weight))


def build_weights(lf: LightField, grid: VolumeGrid, *, min_weight: float = 1e-7,
                  key: str = "") -> Weights:
    """Build W for the light field ``lf`` and the grid ``grid`` (numba, parallel).

    Parameters
    ----------
    min_weight : float
        Weights at or below this (dimensionless fraction of a particle's light) are dropped.
    """
    check_grid_in_view(lf, grid)
    args = _kernel_args(lf, grid, min_weight)
    counts = K.count_nnz(*args)
    indptr = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    if indptr[-1] == 0:
        raise ReconstructionError("no pixel of the camera sees the volume: check [volume] "
                                  "against the field of view and the depth range")
    indices = np.empty(indptr[-1], np.int32)
    data = np.empty(indptr[-1], np.float32)
    K.fill_rows(indptr, *args, indices, data)
    proj = SparseProjector(indptr, indices, data, n_voxels=grid.n_voxels, check=False)
    return Weights(proj, lf.pixel, grid, key)


def weights_reference(lf: LightField, grid: VolumeGrid, rows) -> np.ndarray:
    """Plain-NumPy twin of :func:`build_weights` for a few rows: a dense (len(rows), n_vox)."""
    nz, ny, nx = grid.shape
    xe = grid.origin[0] + (np.arange(nx + 1) - 0.5) * grid.voxel[0]
    ye = grid.origin[1] + (np.arange(ny + 1) - 0.5) * grid.voxel[1]
    out = np.zeros((len(rows), grid.n_voxels))
    xf = lf.focal_plane_position
    area = math.pi * lf.aperture_radius ** 2
    for r, i in enumerate(rows):
        for iz, z in enumerate(grid.z):
            t = (lf.object_distance + z) / lf.object_distance
            al, be = abs(1 - t) * lf.cell, t * lf.footprint
            m = (1 - t) * lf.u[i] + t * xf[i]
            fx = np.diff(K.box_sum_cdf_numpy(xe, m[0], al, be))
            fy = np.diff(K.box_sum_cdf_numpy(ye, m[1], al, be))
            w = lf.lit[i] * (lf.cell * be) ** 2 / (area * grid.voxel[0] * grid.voxel[1])
            out[r, iz * ny * nx:(iz + 1) * ny * nx] = (w * fy[:, None] * fx[None, :]).ravel()
    return out
