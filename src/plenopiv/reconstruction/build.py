"""Build the projector a reconstruction's choice names, on its working grid.

:func:`weights_for` builds what :func:`plenopiv.reconstruction.choose.choose_reconstruction`
decides: explicit weights, loaded from the weights cache or built and saved
(:func:`cached_weights`, the file format in :mod:`plenopiv.products.caches`), or a matrix-free
projector. See docs/methods.md#reconstruction.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import PlenopivWarning, ReconstructionError
from plenopiv.products.caches import (
    read_weights,
    weights_cache_path,
    weights_cached,
    write_weights,
)
from plenopiv.reconstruction.choose import choose_projector, choose_reconstruction
from plenopiv.reconstruction.geometry import ProjectionGeometry, check_grid_in_view
from plenopiv.reconstruction.projector import SparseProjector
from plenopiv.reconstruction.real_lattice import (
    LensletProjector,
    compile_ahead,
    matrix_free_projector,
)
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.weights import Weights, build_weights

__all__ = ["cached_weights", "weights_for"]


def weights_for(calibration: Calibration, grid: VolumeGrid, settings: ReconstructionSettings,
                cache_dir: str | Path | None = None, *, load: bool = True,
                geometry: ProjectionGeometry | None = None) -> tuple[Weights | None, bool]:
    """The weights a reconstruction on ``grid`` with ``settings`` uses: ``(weights, from_cache)``.

    What :func:`~plenopiv.reconstruction.choose.choose_reconstruction` decides, built: the
    explicit weights (cached in ``cache_dir``) or a matrix-free projector, on the laterally
    subdivided working grid. Row-action and block MART walk explicit rows, so ``"auto"``
    keeps them explicit; SMART on a subdivided grid takes the matrix-free projector where the
    lattice allows. With ``lateral_subdivision = "auto"``, weights that would not fit in
    memory on a lattice the matrix-free projector cannot take (rotated or hexagonal) fall
    back to a coarser subdivision, with a warning, instead of failing. A grid whose arrays
    cannot fit in memory is refused before anything is estimated. ``load=False`` only fills
    the cache: explicit weights are built and saved unless cached, the matrix-free projector
    is not built, and None comes back in place of the weights.

    ``geometry`` (:class:`~plenopiv.reconstruction.geometry.ProjectionGeometry` of
    ``calibration`` with ``settings.f_number`` and ``settings.min_lit``, on any grid) lends
    its light field; by default one is made here. Either way the weights carry the geometry
    of their working grid, so the light field is built at most once per reconstruction.

    Raises
    ------
    ReconstructionError
        Nothing the settings allow fits ``max_weights_gb`` (the choice's ``refusal``), or the
        grid lies out of view.
    """
    from plenopiv.resources import check_grid

    check_grid(grid)
    if geometry is None:
        geometry = ProjectionGeometry.for_settings(calibration, grid, settings)
    choice = choose_reconstruction(calibration, grid, settings, geometry=geometry)
    for text in choice.fallbacks:
        warnings.warn(text, PlenopivWarning, stacklevel=2)
    if choice.refusal is not None:
        raise ReconstructionError(choice.refusal)
    work = geometry.on_grid(choice.grid)
    if choice.projector == "sparse":
        return cached_weights(calibration, work.grid, cache_dir=cache_dir,
                              f_number=settings.f_number, min_lit=settings.min_lit,
                              projector="sparse", max_weights_gb=choice.budget_bytes / 1e9,
                              load=load, geometry=geometry)
    work.check_in_view()
    if not load:
        return None, False
    if choice.projector == "lenslet":
        compile_ahead()             # its kernels compile while the tables are built
    lf = work.light_field
    # the choice knows the lattice: a turned one is not tried on the separable projector
    proj = (LensletProjector.from_light_field(lf, work.grid) if choice.projector == "lenslet"
            else matrix_free_projector(lf, work.grid))
    return Weights(proj, lf.pixel, work.grid, work.key(1e-7), work), False



def cached_weights(calibration: Calibration, grid: VolumeGrid, *, cache_dir: str | Path | None,
                   f_number: float | None = None, min_lit: float = 0.5,
                   min_weight: float = 1e-7, projector: str = "auto",
                   max_weights_gb: float | None = None, load: bool = True,
                   geometry: ProjectionGeometry | None = None) -> tuple[Weights | None, bool]:
    """Load the weights from ``cache_dir``, or build (and save) them: ``(weights, from_cache)``.

    Loaded when built before for the same geometry.

    The file name carries the key, and the key stored inside is checked again, so weights of
    another camera, calibration or grid are never reused; a corrupt cache file is rebuilt, and
    so, with a warning, is one whose weights do not match their checksum or hold NaN
    (:func:`~plenopiv.products.caches.read_weights`).
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
    path = None if cache_dir is None else weights_cache_path(cache_dir, key)
    if projector != "lattice" and path is not None:
        if not load:
            if weights_cached(path, key):
                return None, True
        else:
            arrays = read_weights(path, key)
            if arrays is not None:
                indptr, indices, data, pixel = arrays
                proj = SparseProjector(indptr, indices, data, n_voxels=grid.n_voxels,
                                       check=False)
                return Weights(proj, pixel, grid, key, geometry), True
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
        write_weights(path, key, grid.key(), p.indptr, p.indices, p.data, w.pixel)
    return (dataclasses.replace(w, geometry=geometry) if load else None), False

