"""Which projector a reconstruction uses, what it costs, and the on-disk weights cache.

:func:`choose_projector` keeps the explicit weights (:mod:`plenopiv.reconstruction.weights`)
while their estimated memory fits the budget and takes the matrix-free lattice projector
(:mod:`plenopiv.reconstruction.lattice`) beyond it; :func:`cached_weights` loads explicit
weights built before for the same geometry (:func:`weights_key`) or builds and saves them.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import h5py

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import LightField
from plenopiv.products.hdf5 import write_h5
from plenopiv.reconstruction._kernels import weights as K
from plenopiv.reconstruction.geometry import (
    SLAB_VOXELS,
    ProjectionGeometry,
    check_grid_in_view,
    separable_axes,
    subcell_factors,
    weights_key,
)
from plenopiv.reconstruction.projector import SparseProjector
from plenopiv.reconstruction.real_lattice import estimate_lenslet_gb, matrix_free_projector
from plenopiv.reconstruction.weights import Weights, _kernel_args, build_weights

__all__ = ["BYTES_PER_NONZERO", "PROJECTORS", "ProjectorFit", "cached_weights",
           "choose_projector", "estimate_matrix_free_gb", "estimate_nnz", "fit_projector",
           "memory_budget_gb", "weights_key"]


#: Bytes per explicit non-zero in a reconstruction: W's CSR (8: int32 voxel index, float32
#: weight), held once (its row-normalised and row-selected projectors are views of it), and
#: 2 for the row views, schedules, images and volumes; the traced peak of a whole SMART or
#: row-action MART reconstruction stays within it (benchmarks/bench_weights.py
#: --reconstruct). Method "block" adds 4 for its block column sums.
BYTES_PER_NONZERO = 10
PROJECTORS = ("auto", "sparse", "lattice")


def estimate_nnz(lf: LightField, grid: VolumeGrid, *, min_weight: float = 1e-7,
                 sample: int = 101) -> int:
    """Non-zeros of the explicit W, counted on every ``sample``-th ray and scaled up."""
    check_grid_in_view(lf, grid)
    counts = K.count_nnz(*_kernel_args(lf, grid, min_weight, sample))
    return int(counts.sum() * lf.n_rays / max(len(counts), 1))


def memory_budget_gb() -> float:
    """Default memory for explicit weights: 40 % of the physical memory (GB)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        total = 8e9
    return 0.4 * total / 1e9


@dataclass(frozen=True)
class ProjectorFit:
    """The projector a memory budget allows on one grid, and the estimate that decided it.

    Attributes
    ----------
    kind : {"sparse", "lattice", "lenslet"}
        Explicit CSR weights, the separable matrix-free lattice projector (axis-aligned
        square lattice) or the per-lenslet matrix-free projector (any other lattice).
    memory_gb : float
        Estimated peak memory of a reconstruction with it, GB: :data:`BYTES_PER_NONZERO` ×
        ``nnz`` for explicit weights, :func:`estimate_matrix_free_gb` or
        :func:`~plenopiv.reconstruction.real_lattice.estimate_lenslet_gb` otherwise.
    nnz : int or None
        Estimated non-zeros of the explicit weights (None where not estimated).
    refusal : str or None
        Why nothing allowed fits the budget (the reconstruction's error message), else None.
    """

    kind: str
    memory_gb: float
    nnz: int | None = None
    refusal: str | None = None


def fit_projector(lf: LightField, grid: VolumeGrid, *, projector: str = "auto",
                  budget_gb: float, min_weight: float = 1e-7,
                  separable: bool | None = None) -> ProjectorFit:
    """The projector :func:`choose_projector` takes, with its estimate; refusals are returned.

    ``budget_gb`` is the memory allowed, GB. ``separable``: whether ``lf``'s rays are
    separable (:func:`~plenopiv.reconstruction.geometry.separable_axes`), where the caller
    knows it; computed here otherwise.
    """
    if projector not in PROJECTORS:
        raise ValueError(f"projector = {projector!r}: expected one of {PROJECTORS}")
    nnz = None
    if projector in ("auto", "sparse"):
        nnz = estimate_nnz(lf, grid, min_weight=min_weight)
        need = BYTES_PER_NONZERO * nnz / 1e9
        if need <= budget_gb:
            return ProjectorFit("sparse", need, nnz)
        if projector == "sparse":
            return ProjectorFit("sparse", need, nnz, refusal=(
                f"the explicit weights need ~{need:.3g} GB, more than the {budget_gb:.3g} GB "
                "allowed ([reconstruction] max_weights_gb): set projector = \"auto\" (the "
                "matrix-free projector), use fewer or larger voxels, or raise max_weights_gb"))
    if separable is None:
        separable = separable_axes(lf) is not None
    need = estimate_matrix_free_gb(lf, grid) if separable else estimate_lenslet_gb(lf, grid)
    kind = "lattice" if separable else "lenslet"
    if need <= budget_gb:
        return ProjectorFit(kind, need, nnz)
    return ProjectorFit(kind, need, nnz, refusal=(
        f"the matrix-free reconstruction of a {grid.shape[0]} × {grid.shape[1]} × "
        f"{grid.shape[2]}-voxel volume needs ~{need:.3g} GB ("
        + ("projection buffers of depth slices × voxel rows × sensor columns, "
           if separable else "") + "volumes, rays), more than the "
        f"{budget_gb:.3g} GB allowed ([reconstruction] max_weights_gb): use fewer or larger "
        "voxels, or raise max_weights_gb"))


def choose_projector(lf: LightField, grid: VolumeGrid, *, projector: str = "auto",
                     max_weights_gb: float | None = None, min_weight: float = 1e-7) -> str:
    """``"sparse"`` or ``"lattice"`` for a reconstruction of ``grid`` from ``lf``.

    ``"auto"`` keeps the explicit weights while their estimated memory
    (:data:`BYTES_PER_NONZERO` × :func:`estimate_nnz`) fits in ``max_weights_gb`` (default
    :func:`memory_budget_gb`), and takes a matrix-free projector beyond that
    (:func:`plenopiv.reconstruction.real_lattice.matrix_free_projector`: the separable lattice
    projector for an axis-aligned square lattice, the per-lenslet one for any other).

    Both estimates are checked against the same budget before anything large is allocated
    (:func:`fit_projector`, which also says which matrix-free projector and what memory).

    Raises
    ------
    ReconstructionError
        The explicit weights would not fit and ``"sparse"`` was asked for, or the
        matrix-free reconstruction's estimate (:func:`estimate_matrix_free_gb`, or
        :func:`plenopiv.reconstruction.real_lattice.estimate_lenslet_gb` for a lattice that is
        not axis-aligned) exceeds the budget.
    """
    budget = memory_budget_gb() if max_weights_gb is None else float(max_weights_gb)
    fit = fit_projector(lf, grid, projector=projector, budget_gb=budget, min_weight=min_weight)
    if fit.refusal is not None:
        raise ReconstructionError(fit.refusal)
    return "sparse" if fit.kind == "sparse" else "lattice"


def estimate_matrix_free_gb(lf: LightField, grid: VolumeGrid) -> float:
    """Peak memory of a matrix-free SMART reconstruction of ``grid`` from ``lf``, GB.

    Two projection buffers (depth slices × voxel rows × used sensor columns, float32), about
    twelve float32 volumes (estimate, update, column sums, first guess, masks), the rays and
    their per-call copies (~64 bytes each), and one depth slab of the sub-voxel line-of-sight
    mask (:mod:`plenopiv.reconstruction.sightline`: its buffer and six refined float32 arrays).
    """
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
                   max_weights_gb: float | None = None, load: bool = True,
                   geometry: ProjectionGeometry | None = None) -> tuple[Weights | None, bool]:
    """Load the weights from ``cache_dir``, or build (and save) them: ``(weights, from_cache)``.

    Loaded when built before for the same geometry.

    The file name carries the key, and the key stored inside is checked again, so weights of
    another camera, calibration or grid are never reused; a corrupt cache file is rebuilt.
    ``projector`` (see :func:`choose_projector`) may pick the matrix-free lattice projector
    instead, which is quick to build and never cached. ``load=False`` only fills the
    cache: a cached file is checked, not read; the lattice projector is not built; None
    comes back in place of the weights.
    ``geometry``, the :class:`~plenopiv.reconstruction.geometry.ProjectionGeometry` of
    ``calibration`` with ``f_number`` and ``min_lit`` (on any grid), shares its light field
    where the caller has one; the weights carry the geometry of ``grid`` either way.
    """
    if geometry is None:
        geometry = ProjectionGeometry(calibration, grid, f_number, min_lit)
    elif (geometry.calibration is not calibration or geometry.f_number != f_number
          or geometry.min_lit != min_lit):
        raise ValueError("cached_weights: the geometry is of another calibration, f_number "
                         "or min_lit than the arguments")
    geometry = geometry.on_grid(grid)
    key = geometry.key(min_weight)
    path = None if cache_dir is None else Path(cache_dir) / f"weights-{key[:24]}.h5"
    if projector != "lattice" and path is not None and path.exists():
        try:
            with h5py.File(path, "r") as fh:
                if fh.attrs.get("key") == key and not load:
                    return None, True
                if fh.attrs.get("key") == key:
                    proj = SparseProjector(fh["/indptr"][()], fh["/indices"][()],
                                           fh["/data"][()], n_voxels=grid.n_voxels, check=False)
                    return Weights(proj, fh["/pixel"][()], grid, key, geometry), True
        except (OSError, KeyError, ValueError):
            pass   # unreadable or from another geometry: rebuild below
    lf = geometry.light_field
    kind = choose_projector(lf, grid, projector=projector, max_weights_gb=max_weights_gb,
                            min_weight=min_weight)
    if kind == "lattice":
        check_grid_in_view(lf, grid)
        if not load:
            return None, False
        return Weights(matrix_free_projector(lf, grid), lf.pixel, grid, key, geometry), False
    w = build_weights(lf, grid, min_weight=min_weight, key=key)
    if path is not None:
        p = w.projector
        write_h5(path, {"/indptr": p.indptr, "/indices": p.indices, "/data": p.data,
                        "/pixel": w.pixel}, attrs={"key": key, "grid": grid.key()},
                 kind="weights cache", compress=False)
    return (dataclasses.replace(w, geometry=geometry) if load else None), False
