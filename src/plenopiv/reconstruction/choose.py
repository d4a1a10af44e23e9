"""What a reconstruction runs on: its working grid and its projector, decided in one place.

:func:`choose_reconstruction` takes a calibration, a ``[volume]`` grid and the
``[reconstruction]`` settings and returns a :class:`ReconstructionChoice`: the lateral
subdivision of the voxels (:func:`lateral_subdivision`), the working grid
(:func:`subdivided_grid`), the projector (explicit weights, the separable matrix-free lattice
projector, or the per-lenslet one), its estimated memory and the reason. The reconstruction
(:func:`plenopiv.reconstruction.build.weights_for`) builds what it says, and
``plenopiv plan`` reports it, so the two cannot disagree. Nothing is built here but the
light field the estimates need.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.resolution import footprint, resolution_cell
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import LightField
from plenopiv.lightfield.rays import light_field_build_bytes
from plenopiv.reconstruction._kernels import weights as K
from plenopiv.reconstruction.geometry import (
    SEPARABLE_TOLERANCE,
    SLAB_VOXELS,
    ProjectionGeometry,
    check_grid_in_view,
    separable_axes,
    subcell_factors,
)
from plenopiv.reconstruction.real_lattice import estimate_lenslet_gb
from plenopiv.reconstruction.weights import _kernel_args

if TYPE_CHECKING:
    from plenopiv.reconstruction.settings import ReconstructionSettings

__all__ = ["BYTES_PER_NONZERO", "PROJECTORS", "SUBDIVIDED_VOXEL_FOOTPRINTS", "ProjectorFit",
           "ReconstructionChoice", "choose_projector", "choose_reconstruction",
           "estimate_matrix_free_gb", "estimate_nnz", "fit_projector", "lateral_subdivision",
           "memory_budget_gb", "reconstruction_grid", "depth_binning", "depth_binning_for",
           "BINNED_DEPTH_CELLS", "subdivided_grid", "subdivision_for",
           "wanted_subdivision", "MAX_AUTO_WORKING_VOXELS", "LENSLET_COST", "auto_cap_counts",
           "projector_cost", "model_projector_cost", "sweep_cost"]


#: Largest working voxel of the ``"auto"`` lateral subdivision, in lenslet footprints.
SUBDIVIDED_VOXEL_FOOTPRINTS = 1 / 3

#: Most working voxels ``"auto"`` subdivides to: a finer subdivision is given up for one
#: coarser by one per axis until the working grid holds at most this many on the grid's own
#: depth slices, and at most this many on the binned working slices (:func:`depth_binning`)
#: counted at the projector's cost (:data:`LENSLET_COST`). A grid larger is never
#: subdivided. The first count bounds memory: the 16 MP camera's full volume (287 x 193 x
#: 201 footprint voxels) cut 2 x 2 (45 million) takes 3.5-3.9 GB a volume with either
#: projector, cut 3 x 3 (100 million) 4.8 GB on an aligned array
#: (docs/performance.md#full-camera-scale). The second bounds the sweeps' time
#: (:func:`auto_cap_counts`).
MAX_AUTO_WORKING_VOXELS = 50_000_000

#: Largest working depth slice of the ``"auto"`` depth binning, in depth resolution cells
#: (:func:`~plenopiv.camera.resolution.resolution_cell`).
BINNED_DEPTH_CELLS = 1 / 3

#: Weight of a binned working voxel of the per-lenslet projector (a rotated, hexagonal or
#: irregular lattice) in :data:`MAX_AUTO_WORKING_VOXELS`: its sweeps cost 2.0 times the
#: separable lattice projector's on the footprints and 5.4 times on a 2 x 2 cut. So a
#: per-lenslet reconstruction is cut no finer than 16.7 million binned working voxels: the
#: 16 MP camera's full box cut 2 x 2 holds 14.8 million on its 67 binned slices and takes
#: 60 s a volume turned by 2 mrad, 66 s hexagonal, on 2 cores (``plenopiv run``, weights
#: and the recording's check included), where its footprint voxels lose a fifth of the
#: depth motion (w gain 0.79-0.83 against 0.96-0.97; docs/performance.md).
LENSLET_COST = 3.0


def auto_cap_counts(grid: VolumeGrid, ky: int, kx: int, *, cost: float = 1.0,
                    depth_binning: int = 1) -> tuple[float, float]:
    """The two counts :data:`MAX_AUTO_WORKING_VOXELS` bounds for a ``ky × kx`` cut.

    ``(working voxels on the grid's depth slices, cost × working voxels on the binned
    slices)``: ``cost`` of the projector (:func:`projector_cost`), ``depth_binning`` the
    slices a working slice holds (:func:`depth_binning_for`).
    """
    working = subdivided_grid(grid, ky, kx, max(1, depth_binning))
    return float(grid.n_voxels * ky * kx), cost * float(working.n_voxels)


def sweep_cost(ky: int, kx: int) -> float:
    """A matrix-free sweep's time on a ``ky × kx`` cut over one on the footprint voxels.

    The projectors contract a beam's patch of voxels one axis at a time, so a sweep's work
    grows with the patch's side, not its area. Measured at full size (the 16 MP camera's
    ±37 × ±25 × ±26 mm box, 67 binned working slices; one forward and one back projection):
    1.86 and 2.70 times at 2 × 2 and 3 × 3 for the per-lenslet projector (turned 2 mrad),
    1.88 and 3.35 for the separable lattice projector (docs/performance.md).
    """
    return 0.15 + 0.85 * math.sqrt(ky * kx)


def projector_cost(separable: bool) -> float:
    """The cost factor of the matrix-free projector a lattice takes (1 for separable rays)."""
    return 1.0 if separable else LENSLET_COST


def model_projector_cost(camera) -> float:
    """:func:`projector_cost` of a camera model's lattice, judged from its description.

    Separable: a square lattice turned so little that a sensor column's micro-image
    centres stay within :data:`~plenopiv.reconstruction.geometry.SEPARABLE_TOLERANCE` of a
    pixel across the array. A calibration decides on its measured centres
    (:func:`choose_reconstruction`); this is for where only the model is known.
    """
    mla = camera.microlens_array
    span_px = max(mla.rows, mla.cols) * mla.pitch / camera.sensor.pixel_pitch
    return projector_cost(mla.grid == "square"
                          and abs(mla.rotation) * span_px <= SEPARABLE_TOLERANCE)


def lateral_subdivision(calibration: Calibration, grid: VolumeGrid,
                        settings: ReconstructionSettings, *, cost: float | None = None
                        ) -> tuple[int, int]:
    """Subdivision ``(ky, kx)`` of the lateral voxels during the reconstruction.

    ``settings.lateral_subdivision`` as given, or for ``"auto"`` the smallest k per axis for
    which the working voxel is at most a third of a lenslet footprint (5 % slack, at most
    :data:`~plenopiv.reconstruction.settings.MAX_SUBDIVISION`), coarser where the working
    grid would exceed :data:`MAX_AUTO_WORKING_VOXELS` (``cost``: :func:`projector_cost`,
    by default the calibrated camera's :func:`model_projector_cost`; the working slices
    :func:`depth_binning`'s).
    Depth along a pixel's beam is told apart by the beams of the other views shifting
    sideways by a fraction of a footprint;
    voxels a footprint wide hold those shifts in one voxel, and the reconstructed particle
    is 2-3 times longer in depth than with half-footprint voxels. On the CI camera (Oseen,
    0.3 particles per lenslet, footprint voxels) the w gain is 0.73 with k = 2, 0.89 with 3
    and 0.89 with 4 (w rms 0.60, 0.48, 0.40 voxel; without subdivision see
    docs/validation/vortex.md).

    This is the subdivision asked for; :func:`choose_reconstruction` may take a coarser one
    where the weights of this one would not fit in memory.
    """
    if cost is None:
        cost = model_projector_cost(calibration.camera)
    return subdivision_for(footprint(calibration.effective_camera), grid,
                           settings.lateral_subdivision, cost=cost,
                           depth_binning=depth_binning(calibration, grid, settings))


def subdivision_for(footprint_m: float, grid: VolumeGrid, setting: str | int, *,
                    cost: float = 1.0, depth_binning: int = 1) -> tuple[int, int]:
    """``(ky, kx)`` of :func:`lateral_subdivision` from the footprint and the grid.

    ``footprint_m``: the lenslet footprint, m; ``grid``: the ``[volume]`` grid; ``setting``:
    ``[reconstruction] lateral_subdivision`` (``"auto"`` or an int); ``cost``: the
    projector's cost per working voxel (:func:`projector_cost`); ``depth_binning``: the
    grid's slices a working slice holds (:func:`depth_binning_for`).
    """
    ky, kx = wanted_subdivision(footprint_m, grid.voxel, setting)
    if setting != "auto":
        return ky, kx
    while max(ky, kx) > 1 and max(auto_cap_counts(grid, ky, kx, cost=cost,
                                                  depth_binning=depth_binning)
                                  ) > MAX_AUTO_WORKING_VOXELS:
        ky, kx = max(1, ky - 1), max(1, kx - 1)
    return ky, kx


def wanted_subdivision(footprint_m: float, voxel, setting: str | int) -> tuple[int, int]:
    """``(ky, kx)`` that makes the working voxel a third of a footprint, whatever its size.

    ``voxel``: ``(dx, dy, dz)``, m; the rest as :func:`subdivision_for`.
    """
    from plenopiv.reconstruction.settings import MAX_SUBDIVISION

    if setting != "auto":
        return int(setting), int(setting)
    third = SUBDIVIDED_VOXEL_FOOTPRINTS * footprint_m
    return tuple(int(min(MAX_SUBDIVISION, max(1, math.ceil(d / third - 0.05))))
                 for d in (voxel[1], voxel[0]))


def depth_binning(calibration: Calibration, grid: VolumeGrid,
                  settings: ReconstructionSettings) -> int:
    """Depth slices of ``grid`` that one working slice of the reconstruction holds.

    ``settings.depth_binning`` as given, or for ``"auto"`` :func:`depth_binning_for` the
    depth resolution cell of the calibrated camera at ``settings.f_number``.
    """
    cell = resolution_cell(calibration.effective_camera, settings.f_number)[1]
    return depth_binning_for(cell, grid, settings.depth_binning)


def depth_binning_for(depth_cell_m: float, grid: VolumeGrid, setting: str | int) -> int:
    """``kz`` of :func:`depth_binning` from the depth cell (m) and the ``[volume]`` grid.

    ``"auto"``: the largest kz whose working slice is at most :data:`BINNED_DEPTH_CELLS` of
    the depth cell (5 % slack, as the lateral subdivision's), never more slices than the
    grid has. A reconstructed particle is about a depth cell long, so working slices of a
    third of it sample it as the lateral working voxels of a third of a footprint sample
    its width; finer slices cost time in proportion and resolve nothing more.
    """
    nz, dz = grid.shape[0], float(grid.voxel[2])
    if setting != "auto":
        return max(1, min(int(setting), nz))
    k = math.floor(BINNED_DEPTH_CELLS * depth_cell_m / dz * 1.05)
    return max(1, min(k, nz))


def subdivided_grid(grid: VolumeGrid, ky: int, kx: int, kz: int = 1) -> VolumeGrid:
    """``grid`` with every voxel cut into ``ky × kx`` laterally and ``kz`` slices merged.

    The merged slices (``ceil(nz / kz)`` of them, ``kz`` times as deep) are centred on the
    grid's depth range, which they overhang by less than half a merged slice at each end.
    """
    dx, dy, dz = grid.voxel
    ox, oy, oz = grid.origin
    nz, ny, nx = grid.shape
    wz = -(-nz // kz)
    centre = oz + 0.5 * (nz - 1) * dz
    return VolumeGrid((ox - 0.5 * dx + 0.5 * dx / kx, oy - 0.5 * dy + 0.5 * dy / ky,
                       centre - 0.5 * (wz - 1) * kz * dz if kz > 1 else oz),
                      (dx / kx, dy / ky, dz * kz), (wz, ny * ky, nx * kx))


def reconstruction_grid(calibration: Calibration, grid: VolumeGrid,
                        settings: ReconstructionSettings) -> VolumeGrid:
    """The working grid of a reconstruction on ``grid``: subdivided and binned.

    :func:`lateral_subdivision` and :func:`depth_binning`, as asked for;
    :attr:`ReconstructionChoice.grid` is the one a reconstruction takes (coarser where that
    one would not fit in memory).
    """
    return subdivided_grid(grid, *lateral_subdivision(calibration, grid, settings),
                           depth_binning(calibration, grid, settings))


@dataclass(frozen=True)
class ReconstructionChoice:
    """How a reconstruction of a ``[volume]`` grid runs (:func:`choose_reconstruction`).

    Attributes
    ----------
    projector : {"sparse", "lattice", "lenslet"}
        Explicit CSR weights (cached), the separable matrix-free lattice projector
        (axis-aligned square lattice), or the per-lenslet matrix-free projector (any other
        lattice).
    subdivision : (int, int)
        Lateral subdivision ``(ky, kx)`` of the voxels.
    grid : VolumeGrid
        The working grid: the ``[volume]`` grid subdivided by ``subdivision``.
    memory_bytes : float
        Estimated peak memory of the reconstruction with this projector, bytes
        (:class:`~plenopiv.reconstruction.choose.ProjectorFit`).
    budget_bytes : float
        Memory allowed (``[reconstruction] max_weights_gb``, default
        :func:`~plenopiv.reconstruction.choose.memory_budget_gb`), bytes.
    reason : str
        Why this projector and this subdivision, in words.
    nnz : int or None
        Estimated non-zeros of the explicit weights of the working grid (None where the
        decision did not need them).
    n_rays : int
        Rays (lit pixels) of the light field.
    fallbacks : tuple of str
        Subdivisions given up because their weights did not fit, with why (``"auto"``
        only); a reconstruction warns with each.
    refusal : str or None
        Why a reconstruction refuses this grid (nothing allowed fits the budget), else None.
    depth_binning : int
        Depth slices of the ``[volume]`` grid merged into one working slice
        (:func:`depth_binning`).
    """

    projector: str
    subdivision: tuple[int, int]
    grid: VolumeGrid
    memory_bytes: float
    budget_bytes: float
    reason: str
    nnz: int | None = None
    n_rays: int = 0
    fallbacks: tuple[str, ...] = ()
    refusal: str | None = None
    depth_binning: int = 1

    @property
    def working_shape(self) -> tuple[int, int, int]:
        """Shape ``(nz, ny, nx)`` of the working grid."""
        return tuple(int(n) for n in self.grid.shape)

    @property
    def matrix_free(self) -> bool:
        """True for the lattice and the per-lenslet projectors (no stored weights)."""
        return self.projector != "sparse"

    @property
    def settings_projector(self) -> str:
        """The projector in the words of ``[reconstruction] projector``: sparse or lattice."""
        return "sparse" if self.projector == "sparse" else "lattice"

    def to_dict(self) -> dict:
        """Plain JSON values; memory in bytes and GB."""
        return {"projector": self.projector, "lateral_subdivision": list(self.subdivision),
                "depth_binning": int(self.depth_binning),
                "working_shape": list(self.working_shape),
                "memory_bytes": float(self.memory_bytes), "memory_gb": self.memory_bytes / 1e9,
                "budget_bytes": float(self.budget_bytes), "reason": self.reason,
                "nnz": self.nnz, "n_rays": int(self.n_rays),
                "fallbacks": list(self.fallbacks), "refusal": self.refusal}


def choose_reconstruction(calibration: Calibration, grid: VolumeGrid,
                          settings: ReconstructionSettings, *,
                          geometry: ProjectionGeometry | None = None) -> ReconstructionChoice:
    """The working grid and projector of a reconstruction of ``grid`` with ``settings``.

    Parameters
    ----------
    calibration : Calibration
        The camera and its effective S_i (``Calibration.from_camera`` for a camera model).
    grid : VolumeGrid
        The ``[volume]`` grid, effective coordinates, metres.
    settings : ReconstructionSettings
        ``method``, ``projector``, ``max_weights_gb``, ``lateral_subdivision``,
        ``f_number`` and ``min_lit`` are read.
    geometry : ProjectionGeometry, optional
        Of ``calibration`` with ``settings.f_number`` and ``settings.min_lit``, on any grid:
        lends its light field (built here otherwise).

    Returns
    -------
    ReconstructionChoice

    Raises
    ------
    ReconstructionError
        The grid lies out of view. A budget that nothing fits is not raised but returned
        (:attr:`ReconstructionChoice.refusal`).

    Notes
    -----
    In order:

    1. ``projector = "auto"`` with ``method`` other than ``"smart"`` takes explicit weights:
       row-action and block MART walk their rows.
    2. Building the light field alone must fit the budget
       (:func:`~plenopiv.lightfield.rays.light_field_build_bytes`, checked before it is
       built). The subdivision is :func:`lateral_subdivision`'s, its working voxels
       counted at the cost of the projector the lattice takes (:func:`projector_cost`:
       separable rays or not). ``"auto"`` projector on a
       subdivided grid whose rays are separable (axis-aligned square lattice) takes the
       lattice projector, within the budget like every other: the explicit weights grow k²
       and the lattice projector projects them about ten times faster
       (docs/validation/vortex.md).
    3. Otherwise :func:`~plenopiv.reconstruction.choose.fit_projector`: explicit weights while
       their estimate fits the budget, then (``"auto"``, ``"lattice"``) the matrix-free
       projector of the lattice while its estimate fits.
    4. With ``lateral_subdivision = "auto"``, a subdivision whose reconstruction fits nothing
       is given up for one coarser by one per axis (recorded in ``fallbacks``).
    """
    if settings.projector not in PROJECTORS:
        raise ValueError(f"projector = {settings.projector!r}: expected one of {PROJECTORS}")
    if geometry is None:
        geometry = ProjectionGeometry.for_settings(calibration, grid, settings)
    budget = memory_budget_gb() if settings.max_weights_gb is None else settings.max_weights_gb
    projector, why = settings.projector, f"projector = \"{settings.projector}\""
    if projector == "auto" and settings.method != "smart":
        projector = "sparse"
        why = f"method = \"{settings.method}\" walks the rows of explicit weights"
    rays = _light_field_refusal(calibration, settings.f_number, budget)
    kz = depth_binning(calibration, grid, settings)
    if rays is not None:
        ky, kx = lateral_subdivision(calibration, grid, settings)
        return ReconstructionChoice(settings.projector, (ky, kx),
                                    subdivided_grid(grid, ky, kx, kz), rays[0], budget * 1e9,
                                    f"{why}: {rays[1]}", refusal=rays[1], depth_binning=kz)
    n_rays = geometry.light_field.n_rays
    cost = projector_cost(geometry.separable_axes is not None)
    ky, kx = lateral_subdivision(calibration, grid, settings, cost=cost)
    fallbacks: list[str] = _size_fallbacks(calibration, grid, settings, (ky, kx), cost,
                                           kz)
    while True:
        work = geometry.on_grid(subdivided_grid(grid, ky, kx, kz))
        separable = work.separable_axes is not None
        if projector == "auto" and (ky, kx) != (1, 1) and separable:
            # k² times the explicit weights otherwise: the lattice projector, in the budget
            work.check_in_view()
            fit = fit_projector(work.light_field, work.grid, projector="lattice",
                                budget_gb=budget, separable=True)
            fit_why = (f"{why}: a {ky} x {kx} subdivided grid on an axis-aligned square "
                       "lattice (explicit weights would grow k²)")
        else:
            fit = fit_projector(work.light_field, work.grid, projector=projector,
                                budget_gb=budget, separable=separable)
            fit_why = why
        if (fit.refusal is None or settings.lateral_subdivision != "auto"
                or max(ky, kx) == 1):
            break
        fallbacks.append(f"lateral_subdivision = \"auto\": the weights of a {ky} x {kx} "
                         f"subdivision do not fit ({fit.refusal}); trying "
                         f"{max(1, ky - 1)} x {max(1, kx - 1)}")
        ky, kx = max(1, ky - 1), max(1, kx - 1)
    return ReconstructionChoice(
        fit.kind, (ky, kx), work.grid, fit.memory_gb * 1e9, budget * 1e9,
        _reason(fit, fit_why, budget, (ky, kx), fallbacks), nnz=fit.nnz, n_rays=n_rays,
        fallbacks=tuple(fallbacks), refusal=fit.refusal, depth_binning=kz)


def _size_fallbacks(calibration: Calibration, grid: VolumeGrid,
                    settings: ReconstructionSettings, taken: tuple[int, int],
                    cost: float, kz: int) -> list[str]:
    """Why ``"auto"`` took ``taken`` instead of the third-footprint subdivision (or none)."""
    wanted = wanted_subdivision(footprint(calibration.effective_camera), grid.voxel,
                                settings.lateral_subdivision)
    if wanted == tuple(taken):
        return []

    def counts(cut) -> str:
        on_slices, binned = auto_cap_counts(grid, *cut, cost=cost, depth_binning=kz)
        said = []
        if on_slices > MAX_AUTO_WORKING_VOXELS:
            said.append(f"{on_slices / 1e6:.3g} million working voxels on the grid's depth "
                        "slices")
        if binned > MAX_AUTO_WORKING_VOXELS:
            slices = subdivided_grid(grid, 1, 1, kz).shape[0]
            said.append(f"{binned / cost / 1e6:.3g} million on its {slices} binned depth "
                        f"slices, at {cost:g} times the lattice projector's time each")
        return " and ".join(said)

    # the next cut first: it costs the least of those given up
    step = max(taken) + 1
    cuts = str(step) if step >= max(wanted) else f"{step} (or up to {max(wanted)})"
    nearest = (min(step, wanted[0]), min(step, wanted[1]))
    also = "" if nearest == tuple(wanted) else (f"; a {nearest[0]} x {nearest[1]} one "
                                                f"{counts(nearest)}")
    return [f"lateral_subdivision = \"auto\": a {wanted[0]} x {wanted[1]} subdivision would "
            f"make {counts(wanted)}{also} (at most {MAX_AUTO_WORKING_VOXELS / 1e6:.3g} "
            "million either way: the reconstruction's memory and time grow with them); "
            f"taking {taken[0]} x {taken[1]}. Depth motion is then less resolved (w gain "
            f"lower); set [reconstruction] lateral_subdivision = {cuts} to subdivide anyway"]


def _light_field_refusal(calibration: Calibration, f_number, budget: float
                         ) -> tuple[float, str] | None:
    """``(bytes, why)`` where building the light field alone exceeds ``budget`` GB, else None.

    Checked before the light field is built: its working arrays
    (:func:`~plenopiv.lightfield.rays.light_field_build_bytes`) are the first large
    allocation of every reconstruction, and on a small volume its peak.
    """
    need = light_field_build_bytes(calibration, f_number=f_number)
    if need <= budget * 1e9:
        return None
    return need, (f"building the light field of the {calibration.camera.sensor.shape[0]} × "
                  f"{calibration.camera.sensor.shape[1]}-pixel sensor needs ~{need / 1e9:.3g} "
                  f"GB, more than the {budget:.3g} GB allowed ([reconstruction] "
                  "max_weights_gb): raise max_weights_gb, or record a smaller part of the "
                  "sensor")


def _reason(fit, why: str, budget: float, subdivision, fallbacks) -> str:
    """Why :func:`choose_reconstruction` took ``fit``, in words (``budget`` in GB)."""
    names = {"sparse": "explicit weights", "lattice": "the matrix-free lattice projector",
             "lenslet": "the per-lenslet matrix-free projector (the lattice is rotated, "
                        "hexagonal or irregular)"}
    if fit.refusal is not None:
        text = f"{why}: nothing fits the {budget:.3g} GB allowed"
    elif fit.kind == "sparse":
        text = (f"{why}: {names['sparse']}, ~{fit.memory_gb:.3g} GB of the {budget:.3g} GB "
                "allowed")
    elif fit.nnz is not None:
        text = (f"{why}: the explicit weights (~{fit.nnz:.3g} non-zeros) do not fit the "
                f"{budget:.3g} GB allowed; {names[fit.kind]}")
    else:
        text = (f"{why}: {names[fit.kind]}, ~{fit.memory_gb:.3g} GB of the {budget:.3g} GB "
                "allowed")
    if fallbacks:
        why_not = ("finer ones do not fit" if any("do not fit" in f for f in fallbacks) else
                   f"finer ones exceed {MAX_AUTO_WORKING_VOXELS / 1e6:.3g} million working "
                   "voxels")
        text += f" on a {subdivision[0]} x {subdivision[1]} subdivision ({why_not})"
    return text


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

    Held throughout: the light field (52 bytes a ray), the lattice projector's tables and
    rays, the sensor image (float64) and two copies. On top, the larger of its two phases:
    the sub-voxel line of sight (:mod:`plenopiv.reconstruction.sightline`: one depth slab's
    buffer and six refined float32 arrays, two volumes) and SMART (one projection buffer of
    depth slices × voxel rows × used sensor columns, float32; ten float32 volumes: estimate,
    update, column sums, first guess, masks; 32 bytes a ray of per-call copies). Building
    the light field comes before and is budgeted on its own (:func:`choose_reconstruction`).
    """
    nz, ny, nx = grid.shape
    cols = lf.pixel % lf.shape[1]
    n_cols = int(cols.max() - cols.min() + 1) if len(cols) else 0
    kx, ky = subcell_factors(grid, lf.footprint)
    fine = min(SLAB_VOXELS, grid.n_voxels * kx * ky)
    slab_nz = max(1, fine // max(ny * ky * nx * kx, 1))
    held = (52 * lf.n_rays + _lattice_table_bytes(lf, grid, n_cols)
            + 24 * lf.shape[0] * lf.shape[1])
    sightline = 4 * slab_nz * ny * ky * n_cols + 6 * 4 * fine + 2 * 4 * grid.n_voxels
    smart = 4 * nz * ny * n_cols + 10 * 4 * grid.n_voxels + 32 * lf.n_rays
    return (held + max(sightline, smart)) / 1e9


def _lattice_table_bytes(lf: LightField, grid: VolumeGrid, n_cols: int) -> float:
    """Bytes of the lattice projector's tables and rays (``LatticeProjector``).

    Per depth slice and sensor column or row a start, a count and ``kmax`` float32 weights;
    the rows' transposed copy; 20 bytes per ray.
    """
    nz, ny, _ = grid.shape
    t = (lf.object_distance + np.asarray(grid.z, float)) / lf.object_distance
    reach = float(np.max(np.abs(1.0 - t) * lf.cell + t * lf.footprint)) if nz else 0.0
    kmax = math.ceil(reach / min(grid.voxel[0], grid.voxel[1])) + 2
    lines = n_cols + lf.shape[0]
    return (nz * lines * (8 + 4 * kmax) + nz * lf.shape[0] * kmax * 8 + 8 * (ny * nz + 1)
            + 20 * lf.n_rays)
