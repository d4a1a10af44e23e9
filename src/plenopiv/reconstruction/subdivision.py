"""The working grid of a reconstruction: lateral subdivision, its weights, and the way back.

A reconstruction on a ``[volume]`` grid runs on voxels ``ky × kx`` times finer laterally
(:func:`lateral_subdivision`, :func:`subdivided_grid`), with the weights of that working grid
(:func:`weights_for`: explicit and cached, or the matrix-free lattice projector), and its
volume returns to the ``[volume]`` grid by :func:`merge_subdivided`.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.resolution import footprint
from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction.geometry import ProjectionGeometry
from plenopiv.reconstruction.lattice import LatticeProjector
from plenopiv.reconstruction.select import cached_weights
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.weights import Weights

__all__ = ["SUBDIVIDED_VOXEL_FOOTPRINTS", "footprint", "lateral_subdivision", "merge_subdivided",
           "reconstruction_grid", "subdivided_grid", "subdivision_of", "weights_for"]


#: Largest working voxel of the ``"auto"`` lateral subdivision, in lenslet footprints.
SUBDIVIDED_VOXEL_FOOTPRINTS = 1 / 3


def lateral_subdivision(calibration: Calibration, grid: VolumeGrid,
                        settings: ReconstructionSettings) -> tuple[int, int]:
    """Subdivision ``(ky, kx)`` of the lateral voxels during the reconstruction.

    ``settings.lateral_subdivision`` as given, or for ``"auto"`` the smallest k per axis for
    which the working voxel is at most a third of a lenslet footprint (5 % slack, at most
    :data:`~plenopiv.reconstruction.settings.MAX_SUBDIVISION`). Depth along a pixel's beam is told
    apart by
    the beams of the other views shifting sideways by a fraction of a footprint; voxels a
    footprint wide hold those shifts in one voxel, and the reconstructed particle comes out
    much longer in depth. A third of a footprint is where the depth gain stops growing with
    k (docs/validation/vortex.md; docs/methods.md#lateral-subdivision).
    """
    from plenopiv.reconstruction.settings import MAX_SUBDIVISION

    k = settings.lateral_subdivision
    if k != "auto":
        return int(k), int(k)
    half = SUBDIVIDED_VOXEL_FOOTPRINTS * footprint(calibration.effective_camera)
    return tuple(int(min(MAX_SUBDIVISION, max(1, math.ceil(d / half - 0.05))))
                 for d in (grid.voxel[1], grid.voxel[0]))


def subdivided_grid(grid: VolumeGrid, ky: int, kx: int) -> VolumeGrid:
    """``grid`` with every voxel cut into ``ky × kx`` laterally (same box, same depth)."""
    dx, dy, dz = grid.voxel
    ox, oy, oz = grid.origin
    nz, ny, nx = grid.shape
    return VolumeGrid((ox - 0.5 * dx + 0.5 * dx / kx, oy - 0.5 * dy + 0.5 * dy / ky, oz),
                      (dx / kx, dy / ky, dz), (nz, ny * ky, nx * kx))


def reconstruction_grid(calibration: Calibration, grid: VolumeGrid,
                        settings: ReconstructionSettings) -> VolumeGrid:
    """The working grid of a reconstruction on ``grid`` (:func:`lateral_subdivision`)."""
    return subdivided_grid(grid, *lateral_subdivision(calibration, grid, settings))


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

    Explicit (cached in ``cache_dir``) or the matrix-free lattice projector, by
    ``settings.projector``, on the laterally subdivided working grid
    (:func:`reconstruction_grid`).

    Row-action and block MART walk explicit rows, so ``"auto"`` keeps them explicit; SMART
    on a subdivided grid takes the matrix-free projector where the lattice allows. With
    ``lateral_subdivision = "auto"``, weights that would not fit in memory on a lattice the
    matrix-free projector cannot take (rotated or hexagonal) fall back to a coarser
    subdivision, with a warning, instead of failing. A grid whose arrays cannot fit in memory
    is refused before anything is estimated. ``load=False`` only fills the cache: explicit
    weights are built and saved unless cached, the matrix-free projector is not built, and
    None comes back in place of the weights.

    ``geometry`` (:class:`~plenopiv.reconstruction.geometry.ProjectionGeometry` of
    ``calibration`` with ``settings.f_number`` and ``settings.min_lit``, on any grid) lends
    its light field; by default one is made here. Either way the weights carry the geometry
    of their working grid, so the light field is built at most once per reconstruction.
    """
    from plenopiv.resources import check_grid

    check_grid(grid)
    if geometry is None:
        geometry = ProjectionGeometry.for_settings(calibration, grid, settings)
    projector = settings.projector
    if projector == "auto" and settings.method != "smart":
        projector = "sparse"
    ky, kx = lateral_subdivision(calibration, grid, settings)
    if projector == "auto" and (ky, kx) != (1, 1):
        # a subdivided grid has k² times the explicit weights; the matrix-free projector is
        # quick to build and projects it much faster (docs/validation/vortex.md)
        work = geometry.on_grid(subdivided_grid(grid, ky, kx))
        if work.separable_axes is not None:
            work.check_in_view()
            if not load:
                return None, False
            lf = work.light_field
            return Weights(LatticeProjector.from_light_field(lf, work.grid), lf.pixel,
                           work.grid, work.key(1e-7), work), False
    while True:
        try:
            return cached_weights(calibration, subdivided_grid(grid, ky, kx),
                                  cache_dir=cache_dir, f_number=settings.f_number,
                                  min_lit=settings.min_lit, projector=projector,
                                  max_weights_gb=settings.max_weights_gb, load=load,
                                  geometry=geometry)
        except ReconstructionError as exc:
            if (settings.lateral_subdivision != "auto" or max(ky, kx) == 1
                    or "max_weights_gb" not in str(exc)):
                raise
            warnings.warn(f"lateral_subdivision = \"auto\": the weights of a {ky} x {kx} "
                          f"subdivision do not fit ({exc}); trying "
                          f"{max(1, ky - 1)} x {max(1, kx - 1)}", stacklevel=2)
            ky, kx = max(1, ky - 1), max(1, kx - 1)
