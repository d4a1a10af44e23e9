"""The weights of a reconstruction's working grid, and the way back to the volume's grid.

A reconstruction on a ``[volume]`` grid runs on voxels ``ky × kx`` times finer laterally,
with the projector :func:`plenopiv.reconstruction.choose.choose_reconstruction` decides
(:func:`weights_for` builds it: explicit and cached, or matrix-free), and its volume returns
to the ``[volume]`` grid by :func:`merge_subdivided`.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction.choose import choose_reconstruction, subdivided_grid
from plenopiv.reconstruction.geometry import ProjectionGeometry
from plenopiv.reconstruction.real_lattice import matrix_free_projector
from plenopiv.reconstruction.select import cached_weights
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.weights import Weights

__all__ = ["merge_subdivided", "subdivision_of", "weights_for"]


def merge_subdivided(volume, ky: int, kx: int, *, kernel: str = "gaussian") -> np.ndarray:
    """A volume of laterally subdivided voxels back on the grid it subdivides, float32.

    ``volume`` is ``(nz, ny * ky, nx * kx)`` (:func:`subdivided_grid`). ``"box"`` sums each
    voxel's ``ky × kx`` working voxels. ``"gaussian"`` weights the working volume by a
    Gaussian of σ = half a voxel (``k/2`` working voxels) about each voxel's centre (linear
    between the two middle working voxels for an even k), scaled by ``ky kx`` so that the
    total is kept: a particle narrower than a voxel then spreads over its neighbours in the
    ratio of where it lies inside the voxel, which the box sum loses (the peak locking of
    voxels a lenslet footprint wide: docs/validation/vortex.md). The samples of a Gaussian
    of half a voxel sum to 1 within ±1.4 % per axis (2 exp(-π²/2)), a ripple of a particle's
    merged intensity with its position inside the voxel.
    """
    import scipy.ndimage

    v = np.asarray(volume, dtype=np.float32)
    nz, wy, wx = v.shape
    if wy % ky or wx % kx:
        raise ValueError(f"volume of shape {v.shape} is not subdivided by ({ky}, {kx})")
    if kernel == "box":
        return v.reshape(nz, wy // ky, ky, wx // kx, kx).sum(axis=(2, 4), dtype=np.float32)
    if kernel != "gaussian":
        raise ValueError(f"kernel = {kernel!r}: expected 'gaussian' or 'box'")
    for axis, k in ((1, ky), (2, kx)):
        if k == 1:
            continue
        f = scipy.ndimage.gaussian_filter1d(v, 0.5 * k, axis=axis, mode="constant")
        take = [slice(None)] * 3
        take[axis] = slice(k // 2, None, k)
        sampled = f[tuple(take)]
        if k % 2 == 0:             # the centre lies between two working voxels
            take[axis] = slice(k // 2 - 1, None, k)
            sampled = 0.5 * (sampled + f[tuple(take)])
        v = (sampled * k).astype(np.float32)
    return v


def subdivision_of(work: VolumeGrid, grid: VolumeGrid) -> tuple[int, int]:
    """``(ky, kx)`` when ``work`` is ``grid`` subdivided laterally, else ReconstructionError."""
    nz, ny, nx = grid.shape
    wz, wy, wx = work.shape
    if wz == nz and wy % ny == 0 and wx % nx == 0:
        ky, kx = wy // ny, wx // nx
        expect = subdivided_grid(grid, ky, kx)
        scale = max(grid.voxel)
        if (np.allclose(expect.origin, work.origin, rtol=0, atol=1e-9 * scale)
                and np.allclose(expect.voxel, work.voxel, rtol=1e-9, atol=0)):
            return ky, kx
    raise ReconstructionError("the given weights were built for another volume grid (neither "
                              "the volume's grid nor a lateral subdivision of it)")


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
        warnings.warn(text, stacklevel=2)
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
    lf = work.light_field
    return Weights(matrix_free_projector(lf, work.grid), lf.pixel, work.grid, work.key(1e-7),
                   work), False
