"""Voxel-pixel weights from the effective image distance: sparse, built in parallel, cached.

Row i of the weight matrix W is the ray of lit pixel i of a
:class:`~plenopiv.lightfield.LightField`; column j is voxel j of a
:class:`~plenopiv.volume.VolumeGrid` (flat ``[z, y, x]`` order).
``W[i, j]`` is the fraction of the light of a particle spread uniformly over voxel j that
reaches pixel i, in the simulator's units (a particle of energy 1 gives an image summing to 1),
so that I = W E for a volume E of particle energies.

Notes
-----
A pixel's beam is every line from its aperture cell (width a = p_p S_i/f̄ about u) to its
lenslet footprint on the nominal focal plane (width b = p_m S_o/S_i about X_f). A point at
depth Z lies on the line through aperture point u' and footprint point X_f' where
X = (1 - t) u' + t X_f', t = (S_o + Z)/S_o; the fraction of the point's light (the aperture
of area A sampled uniformly) that goes through the pixel is per axis

    L(X) = |{u' in cell : (X - (1 - t) u')/t in footprint}| = a b t · f(X)

where f is the density of X for independent uniform u', X_f' (a trapezoid). Averaged over the
voxel, W = lit · (a b t)² / (A Δx Δy) · ΔF_x · ΔF_y with F the trapezoid's CDF, evaluated at
the voxel's centre depth. Everything is in effective (air-equivalent) coordinates (DESIGN.md §4).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from plenopiv import _weights_kernels as K
from plenopiv.calibration.model import Calibration
from plenopiv.errors import ReconstructionError
from plenopiv.io import write_h5
from plenopiv.lattice import LatticeProjector, separable_axes
from plenopiv.lightfield import LightField, light_field
from plenopiv.projector import Projector, SparseProjector
from plenopiv.real_lattice import LensletProjector, estimate_lenslet_gb, matrix_free_projector
from plenopiv.volume import VolumeGrid

WEIGHTS_VERSION = 3


@dataclass(frozen=True)
class Weights:
    """The weight matrix of one camera calibration and one volume grid.

    Attributes
    ----------
    projector : SparseProjector, LatticeProjector or LensletProjector
        W (rows: lit pixels, columns: voxels): CSR float32 / int32, or computed on the fly
        for an axis-aligned lattice (:mod:`plenopiv.lattice`) or any other
        (:mod:`plenopiv.real_lattice`).
    pixel : (P,) int64
        Flat sensor pixel index of each row.
    grid : VolumeGrid
    key : str
        Hash of what the weights depend on (camera, calibration, grid, options).
    """

    projector: SparseProjector | LatticeProjector | LensletProjector
    pixel: np.ndarray
    grid: VolumeGrid
    key: str

    @functools.cached_property
    def row_max(self) -> np.ndarray:
        """Largest weight of each row, float32 (0 for a row that misses the volume)."""
        return np.asarray(self.projector.row_max(), np.float32)

    @functools.cached_property
    def normalised(self) -> tuple[Projector, np.ndarray]:
        """W with every row scaled to a maximum of 1, and each row's scale (computed once).

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
        """True for the matrix-free projectors (no stored weights)."""
        return isinstance(self.projector, (LatticeProjector, LensletProjector))

    def image_vector(self, image) -> np.ndarray:
        """Return the rows' pixel values of a full sensor image, float32 (P,)."""
        return np.asarray(image, np.float32).reshape(-1)[self.pixel]

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
            fx = np.diff(_cdf_np(xe, m[0], al, be))
            fy = np.diff(_cdf_np(ye, m[1], al, be))
            w = lf.lit[i] * (lf.cell * be) ** 2 / (area * grid.voxel[0] * grid.voxel[1])
            out[r, iz * ny * nx:(iz + 1) * ny * nx] = (w * fy[:, None] * fx[None, :]).ravel()
    return out


def _cdf_np(x, centre, alpha, beta):
    """NumPy twin of :func:`plenopiv._weights_kernels.box_sum_cdf` (by numerical convolution)."""
    lo, hi = sorted((alpha, beta))
    if lo <= 1e-9 * hi:
        return np.clip((x - centre) / hi + 0.5, 0, 1)
    # the density is a trapezoid; integrate it with a fine trapezoid rule
    grid = np.linspace(centre - (lo + hi) / 2, centre + (lo + hi) / 2, 20001)
    dens = np.clip(np.minimum(grid - grid[0], grid[-1] - grid) / lo, 0, 1) / hi
    cum = np.concatenate([[0], np.cumsum((dens[1:] + dens[:-1]) / 2 * np.diff(grid))])
    return np.interp(x, grid, cum, left=0.0, right=1.0)


# --------------------------------------------------------------------------------------------
# cache
# --------------------------------------------------------------------------------------------


def weights_key(calibration: Calibration, grid: VolumeGrid, *, f_number: float | None,
                min_lit: float, min_weight: float) -> str:
    """SHA-256 of everything the weights depend on."""
    h = hashlib.sha256()
    h.update(json.dumps({"v": WEIGHTS_VERSION, "camera": calibration.camera.to_dict(),
                         "si": round(calibration.image_distance, 15), "grid": grid.key(),
                         "f_number": f_number, "min_lit": min_lit, "min_weight": min_weight},
                        sort_keys=True).encode())
    for arr in (calibration.centre_px, calibration.focal_spot_px, calibration.grid_index):
        h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    return h.hexdigest()


#: Bytes per explicit non-zero in a reconstruction: W (8), its row-normalised copy (4) and the
#: copy restricted to the bright rows (8 × their share; counted in full).
BYTES_PER_NONZERO = 20
PROJECTORS = ("auto", "sparse", "lattice")


def estimate_nnz(lf: LightField, grid: VolumeGrid, *, min_weight: float = 1e-7,
                 sample: int = 101) -> int:
    """Non-zeros of the explicit W, counted on every ``sample``-th ray and scaled up."""
    check_grid_in_view(lf, grid)
    counts = K.count_nnz(*_kernel_args(lf, grid, min_weight, sample))
    return int(counts.sum() * lf.n_rays / max(len(counts), 1))


def memory_budget_gb() -> float:
    """Default memory for explicit weights: 40 % of this machine's physical memory (GB)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 8e9
    return 0.4 * total / 1e9


def choose_projector(lf: LightField, grid: VolumeGrid, *, projector: str = "auto",
                     max_weights_gb: float | None = None, min_weight: float = 1e-7) -> str:
    """``"sparse"`` or ``"lattice"`` for a reconstruction of ``grid`` from ``lf``.

    ``"auto"`` keeps the explicit weights while their estimated memory
    (:data:`BYTES_PER_NONZERO` × :func:`estimate_nnz`) fits in ``max_weights_gb`` (default
    :func:`memory_budget_gb`), and takes a matrix-free projector beyond that
    (:func:`plenopiv.real_lattice.matrix_free_projector`: the separable lattice projector for
    an axis-aligned square lattice, the per-lenslet one for any other).

    Both estimates are checked against the same budget before anything large is allocated.

    Raises
    ------
    ReconstructionError
        The explicit weights would not fit and ``"sparse"`` was asked for, or the
        matrix-free reconstruction's estimate (:func:`estimate_matrix_free_gb`, or
        :func:`plenopiv.real_lattice.estimate_lenslet_gb` for a lattice that is not
        axis-aligned) exceeds the budget.
    """
    if projector not in PROJECTORS:
        raise ValueError(f"projector = {projector!r}: expected one of {PROJECTORS}")
    budget = memory_budget_gb() if max_weights_gb is None else float(max_weights_gb)
    if projector in ("auto", "sparse"):
        need = BYTES_PER_NONZERO * estimate_nnz(lf, grid, min_weight=min_weight) / 1e9
        if need <= budget:
            return "sparse"
        if projector == "sparse":
            raise ReconstructionError(
                f"the explicit weights need ~{need:.3g} GB, more than the {budget:.3g} GB "
                "allowed ([reconstruction] max_weights_gb): set projector = \"auto\" (the "
                "matrix-free projector), use fewer or larger voxels, or raise max_weights_gb")
    separable = separable_axes(lf) is not None
    need = estimate_matrix_free_gb(lf, grid) if separable else estimate_lenslet_gb(lf, grid)
    if need > budget:
        raise ReconstructionError(
            f"the matrix-free reconstruction of a {grid.shape[0]} × {grid.shape[1]} × "
            f"{grid.shape[2]}-voxel volume needs ~{need:.3g} GB ("
            + ("projection buffers of depth slices × voxel rows × sensor columns, "
               if separable else "") + "volumes, rays), more than the "
            f"{budget:.3g} GB allowed ([reconstruction] max_weights_gb): use fewer or larger "
            "voxels, or raise max_weights_gb")
    return "lattice"


def estimate_matrix_free_gb(lf: LightField, grid: VolumeGrid) -> float:
    """Peak memory of a matrix-free SMART reconstruction of ``grid`` from ``lf``, GB.

    Two projection buffers (depth slices × voxel rows × used sensor columns, float32), about
    twelve float32 volumes (estimate, update, column sums, first guess, masks), the rays and
    their per-call copies (~64 bytes each), and one depth slab of the sub-voxel line-of-sight
    mask (:mod:`plenopiv.sightline`: its buffer and six refined float32 arrays).
    """
    from plenopiv.sightline import SLAB_VOXELS, subcell_factors

    nz, ny, nx = grid.shape
    cols = lf.pixel % lf.shape[1]
    n_cols = int(cols.max() - cols.min() + 1) if len(cols) else 0
    kx, ky = subcell_factors(grid, lf.footprint)
    fine = min(SLAB_VOXELS, grid.n_voxels * kx * ky)
    slab_nz = max(1, fine // max(ny * ky * nx * kx, 1))
    total = (2 * 4 * nz * ny * n_cols + 12 * 4 * grid.n_voxels + 64 * lf.n_rays
             + 4 * slab_nz * ny * ky * n_cols + 6 * 4 * fine)
    return total / 1e9


def cached_weights(calibration: Calibration, grid: VolumeGrid, *, cache_dir: str | Path | None,
                   f_number: float | None = None, min_lit: float = 0.5,
                   min_weight: float = 1e-7, projector: str = "auto",
                   max_weights_gb: float | None = None) -> tuple[Weights, bool]:
    """Load the weights from ``cache_dir``, or build (and save) them.

    They are loaded when built before for the same geometry; returns
    ``(weights, from_cache)``.

    The file name carries the key, and the key stored inside is checked again, so weights of
    another camera, calibration or grid are never reused; a corrupt cache file is rebuilt.
    ``projector`` (see :func:`choose_projector`) may pick the matrix-free lattice projector
    instead, which is built in seconds and never cached.
    """
    key = weights_key(calibration, grid, f_number=f_number, min_lit=min_lit,
                      min_weight=min_weight)
    path = None if cache_dir is None else Path(cache_dir) / f"weights-{key[:24]}.h5"
    if projector != "lattice" and path is not None and path.exists():
        try:
            with h5py.File(path, "r") as fh:
                if fh.attrs.get("key") == key:
                    proj = SparseProjector(fh["/indptr"][()], fh["/indices"][()],
                                           fh["/data"][()], n_voxels=grid.n_voxels, check=False)
                    return Weights(proj, fh["/pixel"][()], grid, key), True
        except (OSError, KeyError, ValueError):
            pass   # unreadable or from another geometry: rebuild below
    lf = light_field(calibration, f_number=f_number, min_lit=min_lit)
    kind = choose_projector(lf, grid, projector=projector, max_weights_gb=max_weights_gb,
                            min_weight=min_weight)
    if kind == "lattice":
        check_grid_in_view(lf, grid)
        return Weights(matrix_free_projector(lf, grid), lf.pixel, grid, key), False
    w = build_weights(lf, grid, min_weight=min_weight, key=key)
    if path is not None:
        p = w.projector
        write_h5(path, {"/indptr": p.indptr, "/indices": p.indices, "/data": p.data,
                        "/pixel": w.pixel}, attrs={"key": key, "grid": grid.key()},
                 kind="weights cache", compress=False)
    return w, False
