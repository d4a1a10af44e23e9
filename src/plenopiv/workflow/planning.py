"""What a box costs before anything is reconstructed: ``plenopiv plan``.

From a camera and a box, :func:`plan` gives the resolution cell and the near-focus zone
(docs/methods.md#resolution-cell), the recommended voxel and PIV windows scaled to the camera
(:func:`recommended_voxel`, :func:`recommended_windows`), whether the windows fit the box and
how many vectors each pass gives, what the reconstruction will run (the reconstruction's own
decision, :func:`plenopiv.reconstruction.choose.choose_reconstruction`), its memory and its
time from :mod:`plenopiv.workflow.rates`, and the chain's response time. Everything here is
computation; printing belongs to :mod:`plenopiv.cli`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import CameraModel
from plenopiv.errors import ConfigError
from plenopiv.piv.settings import PIVSettings
from plenopiv.reconstruction.choose import sweep_cost
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.workflow.judgement import (
    MIN_VECTORS_LAST_PASS,
    VALIDATED_PARTICLES_PER_LENSLET,
    VALIDATED_SEEDING,
    Camera,
    Finding,
    Judgement,
    camera_resolution,
    judge,
    lenslets_in_box,
    recommended_voxel,
    recommended_windows,
    snap_grid,
)
from plenopiv.workflow.rates import (
    BENCHMARK_RATES,
    Rates,
    _ray_pattern,
    _window_voxels,
    vectors_per_pass,
)

if TYPE_CHECKING:
    from plenopiv.reconstruction.choose import ReconstructionChoice

#: The judgement's resolution, recommendations and thresholds are planning's public names too.
__all__ = ["BENCHMARK_RATES", "MIN_VECTORS_LAST_PASS", "Camera", "Plan", "available_memory",
           "camera_resolution", "estimate_size", "plan", "recommended_voxel",
           "recommended_windows", "vectors_per_pass"]


#: Bytes per ray while the light field is built (temporaries included; the traced peak of the
#: Auburn camera's light field).
BYTES_PER_RAY_LIGHT_FIELD = 250


#: Bytes per voxel held by the PIV of a pair (two volumes, deformed copies, spline
#: coefficients, window spectra).
BYTES_PER_VOXEL_PIV = 160


#: The interpreter with numpy, scipy and numba loaded, bytes.
BASE_BYTES = 0.3e9


#: Bytes per ray held by the particle table's positions from the light field (``[particles]
#: position = "light_field"``, the default: the lit rays, their lenslet table and the rays
#: each particle's fit selects), on top of what the reconstruction holds: the traced peak of
#: the 16 MP camera at 0.36 particles per lenslet (rotated array).
BYTES_PER_RAY_PARTICLE_FIT = 30


#: Seconds per sensor pixel of the check of a recording against its calibration
#: (:func:`plenopiv.calibration.recording.check_recording`, ``[reconstruction] lattice_check``
#: not "off"; its two passes) where the reconstruction was not rehearsed: 0.16-0.24 s for the
#: 0.73 MP sensor of the small cameras, 4.2 s for the 16 MP one (``benchmarks/plan_accuracy.py``).
SECONDS_PER_PIXEL_RECORDING_CHECK = 2.7e-7


#: Seconds per ray of that fit on two threads, merged peaks split included
#: (:func:`plenopiv.particles.split.split_bright`, a second fit of every particle): from
#: ``plenopiv reconstruct``'s particles for the 11.6 million rays of the 16 MP turned array
#: at 0.36 particles per lenslet (9.9 s besides the peaks' 0.5 s; 4.5 s without the split).
SECONDS_PER_RAY_PARTICLE_FIT = 8.6e-7

#: Seconds per seeded particle of A and B of a pair's tracks (bundle fits, refinement,
#: matching; ``[tracking] correct_vectors`` or ``enabled``) on two threads: 18.9 s for the
#: 2 × 20,000 particles of a pair on the 16 MP turned array (25,080 found in A; ``plenopiv
#: run``, docs/performance.md#batches), 0.49 s for 2 × 221 in the demo.
SECONDS_PER_TRACKED_PARTICLE = 4.7e-4


@dataclass(frozen=True)
class Plan:
    """Everything ``plenopiv plan`` reports. Lengths in metres, memory in bytes, time in s."""

    camera: Camera
    grid: VolumeGrid
    windows: tuple[tuple[int, int, int], ...]
    passes: int
    overlap: float
    vectors: tuple[tuple[int, int, int], ...]
    recommended_voxel: tuple[float, float, float]
    recommended_windows: tuple[tuple[int, int, int], ...]
    recommended_grid: VolumeGrid
    recommended_vectors: tuple[int, int, int]
    n_rays: int
    nnz: int
    projector: str
    memory: dict
    time: dict
    time_model: str
    available_memory: float
    warnings: tuple[str, ...] = ()
    advice: tuple[str, ...] = ()
    particles_per_lenslet: float = VALIDATED_PARTICLES_PER_LENSLET
    decision: ReconstructionChoice | None = None
    response_s: float = 0.0
    findings: tuple[Finding, ...] = ()
    seeding: float | None = None

    @property
    def fits(self) -> bool:
        """True when every pass's windows fit the box."""
        return all(min(v) > 0 for v in self.vectors)

    def recommended_toml(self) -> str:
        """``[volume]`` and ``[piv]`` tables with the recommended voxel and windows."""
        g = self.recommended_grid
        b = g.bounds * 1e3
        vox = ", ".join(_mm(v * 1e3) for v in self.recommended_voxel)
        win = ", ".join("[" + ", ".join(str(int(w)) for w in ws) + "]"
                        for ws in self.recommended_windows)
        return ("[volume]\n"
                f"x_mm = [{_mm(b[0, 0])}, {_mm(b[0, 1])}]\n"
                f"y_mm = [{_mm(b[1, 0])}, {_mm(b[1, 1])}]\n"
                f"z_mm = [{_mm(b[2, 0])}, {_mm(b[2, 1])}]\n"
                f"voxel_mm = [{vox}]\n\n"
                "[piv]\n"
                f"windows = [{win}]\n")

    def judgement(self) -> Judgement:
        """The findings as the commands record them (a stated seeding as its particle count)."""
        n = (None if self.seeding is None
             else self.seeding * lenslets_in_box(self.camera, self.grid))
        sub = None if self.decision is None else self.decision.subdivision
        kz = None if self.decision is None else int(self.decision.depth_binning)
        return Judgement(self.camera, self.grid, self.findings, sub, n, depth_binning=kz)

    def _decision_dict(self) -> dict:
        """The reconstruction's decision (:class:`ReconstructionChoice`) as plan reports it."""
        d = self.decision
        if d is None:
            return {}
        return {"decision": d.to_dict(), "lateral_subdivision": list(d.subdivision),
                "depth_binning": int(d.depth_binning), "working_shape": list(d.working_shape),
                "projector_kind": d.projector}

    def to_dict(self) -> dict:
        """Plain JSON values; lengths in mm, memory in GB, times in s."""
        c, g = self.camera, self.grid
        return {
            "camera": c.name,
            "f_number": c.f_number,
            "footprint_mm": c.footprint * 1e3,
            "resolution_cell_mm": {"lateral": c.footprint * 1e3, "depth": c.depth_cell * 1e3},
            "near_focus_mm": [-c.near_focus * 1e3, c.near_focus * 1e3],
            "field_of_view_mm": {"x": [-c.field_of_view[0] * 1e3, c.field_of_view[0] * 1e3],
                                 "y": [-c.field_of_view[1] * 1e3, c.field_of_view[1] * 1e3]},
            "volume": {"x_mm": (g.bounds[0] * 1e3).tolist(), "y_mm": (g.bounds[1] * 1e3).tolist(),
                       "z_mm": (g.bounds[2] * 1e3).tolist(),
                       "voxel_mm": [v * 1e3 for v in g.voxel], "shape": list(g.shape)},
            "n_voxels": g.n_voxels,
            "windows_vox": [list(w) for w in self.windows],
            "passes": self.passes,
            "overlap": self.overlap,
            "vectors_per_pass": [list(v) for v in self.vectors],
            "windows_fit": self.fits,
            "recommended": {"voxel_mm": [v * 1e3 for v in self.recommended_voxel],
                            "windows_vox": [list(w) for w in self.recommended_windows],
                            "shape": list(self.recommended_grid.shape),
                            "vectors_last_pass": list(self.recommended_vectors),
                            "particles_per_lenslet": self.particles_per_lenslet,
                            "toml": self.recommended_toml()},
            "n_rays": self.n_rays,
            "nnz": self.nnz,
            "projector": self.projector,
            **self._decision_dict(),
            "memory_gb": {k: v / 1e9 for k, v in self.memory.items()},
            "available_memory_gb": self.available_memory / 1e9,
            "time_s": dict(self.time),
            "response_s": self.response_s,
            "time_model": self.time_model,
            "warnings": list(self.warnings),
            "advice": list(self.advice),
            "judgement": self.judgement().record(),
        }


def _mm(mm: float) -> str:
    """Return a length in mm, short: 3 decimals at most, no trailing zeros."""
    s = f"{mm:.3f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _axis_counts(u, pos, t, al, be, origin, vox, n):
    """Voxels that each pattern ray's beam overlaps along one axis on every slice: (R, nz).

    Summed over the lenslet positions ``pos``.
    """
    half = 0.5 * (al + be)
    out = np.zeros((len(u), len(t)), np.float64)
    for k in range(len(t)):
        m = (1.0 - t[k]) * u[:, None] + t[k] * pos[None, :]
        i0 = np.maximum(np.floor((m - half[k] - origin) / vox + 0.5), 0)
        i1 = np.minimum(np.floor((m + half[k] - origin) / vox + 0.5), n - 1)
        out[:, k] = np.maximum(i1 - i0 + 1, 0).sum(axis=1)
    return out


def estimate_size(camera: CameraModel, grid: VolumeGrid, *, f_number=None,
                  min_lit: float = 0.5) -> tuple[int, int]:
    """``(n_rays, nnz)``: rays of the camera and non-zero weights of the explicit W for ``grid``.

    From the ray pattern of one micro-image repeated at every lenslet.

    Separable per axis: a square lattice's lenslets are a product of columns and rows; a
    hexagonal one is two such products (even and odd rows).
    """
    u, lit, lf = _ray_pattern(camera, f_number, min_lit)
    mla = camera.microlens_array
    centres = mla.nominal_centres() / camera.magnification     # X_f on the focal plane
    rows = mla.grid_index()[:, 0]
    so = lf.object_distance
    t = (so + grid.z) / so
    al = np.abs(1.0 - t) * lf.cell
    be = t * lf.footprint
    nz, ny, nx = grid.shape
    nnz = 0.0
    for parity in ((0, 1) if mla.grid == "hexagonal" else (None,)):
        sel = rows % 2 == parity if parity is not None else np.ones(len(rows), bool)
        if not sel.any():
            continue
        xs = np.unique(np.round(centres[sel, 0], 12))
        ys = np.unique(np.round(centres[sel, 1], 12))
        cx = _axis_counts(u[:, 0], xs, t, al, be, grid.origin[0], grid.voxel[0], nx)
        cy = _axis_counts(u[:, 1], ys, t, al, be, grid.origin[1], grid.voxel[1], ny)
        nnz += float((cx * cy).sum())
    return int(len(u) * mla.count), int(nnz)


def available_memory() -> float:
    """Physical memory of the computer, bytes."""
    try:
        return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 8e9


#: Time of a reconstruction's sweeps with the per-lenslet projector (rotated or hexagonal
#: arrays) over the separable lattice projector's, the same grid moved off the footprints:
#: 14.7 s against 7.5 s a volume (MLOS and 5 sweeps, 2 threads, wall) for the 16 MP array
#: turned 2 mrad and aligned at full size (``benchmarks/full_camera.py --lateral-subdivision
#: 1``, docs/performance.md); 3.2 before the per-lenslet back projection was vectorised.
LENSLET_COST_RATIO = 2.0


def plan(camera: CameraModel, grid: VolumeGrid, *,
         reconstruction: ReconstructionSettings | None = None, piv: PIVSettings | None = None,
         rates: Rates | None = None, memory_total: float | None = None,
         calibration=None, geometry=None, seeding: float | None = None,
         chosen: tuple[Finding, ...] = (), tracking=None) -> Plan:
    """Plan the reconstruction of ``grid`` (effective coordinates) with ``camera``.

    ``camera`` must know its image distance (from the camera file, or a calibration's
    ``effective_camera``). ``reconstruction`` and ``piv``: the experiment's tables (default:
    the defaults). ``rates``: :func:`measure_rates` (in this process) or
    :data:`BENCHMARK_RATES` (default). ``calibration``: the experiment's calibration product
    (:class:`~plenopiv.calibration.model.Calibration`; default: the camera's exact one).
    ``geometry``: a :class:`~plenopiv.reconstruction.geometry.ProjectionGeometry` of that
    calibration and these settings whose light field is built already (a reconstruction's).

    The projector, the lateral subdivision and the working grid are the reconstruction's own
    decision (:func:`plenopiv.reconstruction.choose.choose_reconstruction`, on the light field
    of the calibration: seconds and ~250 bytes per ray for a 16 MP camera), so memory and
    time are those of what ``plenopiv reconstruct`` will run.

    With ``[piv] uncertainty = "response"`` the chain's response is measured once per
    experiment, before its pairs: ``response_s`` estimates that time
    (:func:`plenopiv.workflow.response.response_seconds`), s. ``tracking``: the ``[tracking]``
    table (default: the defaults); where it tracks the pairs (``correct_vectors`` or
    ``enabled``) the pair's time holds its tracks (``track``), at the ``seeding`` given or
    the top of the validated one (:data:`~plenopiv.workflow.judgement.VALIDATED_SEEDING`).

    The warnings and advice are :func:`plenopiv.workflow.judgement.judge`'s on the decided
    subdivision (``seeding``: the particles per lenslet expected, judged too), after the
    settings ``chosen`` for the user (:func:`~plenopiv.workflow.judgement.choose_unset`),
    then the memory's.
    """
    from plenopiv.calibration.model import Calibration
    from plenopiv.reconstruction.choose import choose_reconstruction

    reconstruction = reconstruction or ReconstructionSettings()
    piv = piv or PIVSettings()
    try:
        _ = camera.image_distance
    except ConfigError:
        raise ConfigError(f"camera {camera.name!r}: [main_lens] image_distance_mm is not set; "
                          "plan needs it: give --image-distance-mm or --calibration CAL.h5"
                          ) from None
    rates = rates or BENCHMARK_RATES
    total_mem = available_memory() if memory_total is None else float(memory_total)
    cam = camera_resolution(camera, reconstruction.f_number)
    windows = tuple(tuple(int(v) for v in w) for w in piv.windows)
    passes = piv.passes or len(windows)
    vectors = vectors_per_pass(grid.shape, windows, piv.overlap, passes)
    rec_vox = recommended_voxel(cam)
    rec_grid = snap_grid(grid, rec_vox)
    rec_win = recommended_windows(cam, rec_grid.voxel, rec_grid.shape)
    rec_vectors = vectors_per_pass(rec_grid.shape, rec_win, piv.overlap, len(rec_win))[-1]

    cal = Calibration.from_camera(camera) if calibration is None else calibration
    choice = choose_reconstruction(cal, grid, reconstruction, geometry=geometry)
    n_rays = choice.n_rays
    nnz = choice.nnz
    if nnz is None:                  # not needed by the decision: counted for the report
        nnz = estimate_size(camera, choice.grid, f_number=reconstruction.f_number,
                            min_lit=reconstruction.min_lit)[1]
    memory = _memory(choice, grid, nnz)
    checked = 0 if reconstruction.lattice_check == "off" else int(np.prod(camera.sensor.shape))
    times = _times(choice, grid, nnz, rates, reconstruction.iterations, windows, piv.overlap,
                   passes, memory["weights_cache_file"], checked_pixels=checked)
    times.update(_track_times(times, cam, grid, tracking, seeding))
    response_s = 0.0
    if piv.uncertainty == "response":
        from plenopiv.workflow.response import response_particle_count, response_seconds

        n = response_particle_count(cal, grid, piv.response_particles_per_lenslet)
        response_s = response_seconds(times["volume"], times["piv"], n,
                                      piv.response_displacements)
    model = ("rates measured in this process" if rates.source == "measured"
             else "benchmark rates (rates.BENCHMARK_RATES, docs/performance.md)")
    model = f"{model}, {rates.threads} threads"
    if _rehearsal_of(rates, choice, reconstruction.iterations) is not None:
        model += ", the reconstruction rehearsed on a patch of the camera"

    findings = chosen + judge(cam, grid, reconstruction, piv, subdivision=choice.subdivision,
                              particles_per_lenslet=seeding, advice=True)
    warnings = ([f"plenopiv reconstruct refuses this box: {choice.refusal}"]
                if choice.refusal is not None else []) + list(choice.fallbacks)
    warnings += [f.text for f in findings if f.severity == "warning"]
    warnings += _memory_warnings(memory, total_mem, choice.settings_projector)
    advice = [f.text for f in findings if f.severity == "advice"]
    if advice:
        advice.append("recommended [piv] windows for the recommended voxel: "
                      + " then ".join(str(list(w)) for w in rec_win))
    return Plan(camera=cam, grid=grid, windows=windows, passes=passes, overlap=piv.overlap,
                vectors=vectors, recommended_voxel=tuple(rec_grid.voxel),
                recommended_windows=rec_win, recommended_grid=rec_grid,
                recommended_vectors=rec_vectors, n_rays=n_rays, nnz=nnz,
                projector=choice.settings_projector, memory=memory, time=times,
                time_model=model, available_memory=total_mem, warnings=tuple(warnings),
                advice=tuple(advice), decision=choice, response_s=response_s,
                findings=findings, seeding=seeding)


def _memory_warnings(memory: dict, total_mem: float, projector: str) -> list[str]:
    """A warning when the reconstruction's peak memory nears the machine's (bytes)."""
    if memory["peak"] <= 0.8 * total_mem:
        return []
    return [f"the reconstruction needs about {memory['peak'] / 1e9:.3g} GB, "
            f"{memory['peak'] / total_mem:.0%} of this machine's {total_mem / 1e9:.3g} GB: use "
            "larger voxels or a smaller box"
            + ("" if projector == "lattice" else ", or [reconstruction] projector = \"lattice\"")]


def _memory(choice, grid: VolumeGrid, nnz: int) -> dict:
    """Memory of the chosen reconstruction, bytes per stage (:class:`Plan` ``memory``).

    ``projector``: the decision's own estimate (explicit weights with the arrays of their
    reconstruction, or the matrix-free reconstruction's), which it checked against the
    budget; ``weights``: the same for explicit weights, 0 for a matrix-free projector.
    """
    n_rays = choice.n_rays
    build = BASE_BYTES + BYTES_PER_RAY_LIGHT_FIELD * n_rays
    cache_file = 0.0
    if choice.projector == "sparse":
        build += 8.0 * nnz
        cache_file = 8.0 * nnz + 16.0 * n_rays
    # the particles' fit, after the iterations
    recon = BASE_BYTES + choice.memory_bytes + BYTES_PER_RAY_PARTICLE_FIT * n_rays
    piv_bytes = BASE_BYTES + BYTES_PER_VOXEL_PIV * grid.n_voxels
    return {"weights": choice.memory_bytes if choice.projector == "sparse" else 0.0,
            "projector": choice.memory_bytes, "weights_build_peak": build,
            "reconstruct_peak": recon, "piv_peak": piv_bytes,
            "peak": max(build, recon, piv_bytes), "weights_cache_file": cache_file}


def _rehearsal_of(rates: Rates, choice, iterations: int):
    """The rates' rehearsal where it stands for ``choice`` at ``iterations`` sweeps, or None."""
    reh = rates.rehearsal
    if reh is not None and reh.matches(choice.projector, choice.subdivision, iterations):
        return reh
    return None


def _track_times(times: dict, cam: Camera, grid: VolumeGrid, tracking, seeding) -> dict:
    """``track`` (s) and the pair's times with it, where the pairs are tracked."""
    from plenopiv.tracking.settings import TrackingSettings

    tracking = tracking or TrackingSettings()
    if not (tracking.correct_vectors or tracking.enabled):
        return {"track": 0.0}
    # unstated: the top of the validated seeding, so that a pair seeded within it takes no
    # longer than planned (the tracks' time grows with the particles)
    per_lenslet = VALIDATED_SEEDING[1] if seeding is None else float(seeding)
    t = SECONDS_PER_TRACKED_PARTICLE * 2.0 * per_lenslet * lenslets_in_box(cam, grid)
    return {"track": t, "pair": times["pair"] + t,
            "pair_cached_weights": times["pair_cached_weights"] + t}


def _times(choice, grid: VolumeGrid, nnz: int, rates: Rates, iterations: int, windows,
           overlap: float, passes: int, cache_file: float, checked_pixels: int = 0) -> dict:
    """Seconds per stage of the chosen reconstruction and the PIV (:class:`Plan` ``time``).

    ``recording_check``: the check of the recording against its calibration on a sensor of
    ``checked_pixels`` (once per image with ``plenopiv reconstruct``, once per pair with
    ``run``); ``first_volume``: what the first volume of a weights object adds (its row and
    column sums, the line of sight's refined cells); ``reconstruct``: one ``plenopiv
    reconstruct`` (weights, check, first volume).

    Where the reconstruction was rehearsed (:class:`~plenopiv.workflow.rates.Rehearsal`, the
    same projector, subdivision and sweeps) its figures scale by rays and depth slices.
    Otherwise a matrix-free sweep costs the measured rate at the subdivision it was measured
    at (:attr:`~plenopiv.workflow.rates.Rates.lattice_subdivision`); at another one it is
    scaled by :func:`~plenopiv.reconstruction.choose.sweep_cost`, which grows with the side of
    a beam's patch of working voxels, not its area.
    """
    n_rays = choice.n_rays
    sweeps = iterations + 3      # MLOS, masks and row scaling: ~3 sweeps
    t_first = 0.0
    reh = _rehearsal_of(rates, choice, iterations)
    if reh is not None:
        # the reconstruction itself, rehearsed on a patch of the camera
        ray_slices = n_rays * choice.grid.shape[0]      # the working grid's slices
        t_weights = reh.weights_s_per_ray * n_rays
        t_volume = reh.volume_s_per_ray_slice * ray_slices
        t_first = reh.first_s_per_ray_slice * ray_slices
    elif choice.projector == "sparse":
        # light field, weights, and the cache file written at ~250 MB/s
        t_weights = 2e-7 * n_rays + rates.build_s_per_nnz * nnz + cache_file / 250e6
        t_volume = (rates.sweep_s_per_nnz * nnz + rates.sweep_s_per_call) * sweeps
    else:
        t_weights = 2e-7 * n_rays                # light field and tables
        ray_slice = rates.lattice_s_per_ray_slice * (
            LENSLET_COST_RATIO if choice.projector == "lenslet" else 1.0)
        # the rate's voxels cut as the rate was measured; another cut scaled by its area
        (ky, kx), (my, mx) = choice.subdivision, rates.lattice_subdivision
        t_volume = (ray_slice * n_rays * choice.grid.shape[0]
                    * sweep_cost(ky, kx) / sweep_cost(my, mx)
                    + rates.lattice_s_per_call) * sweeps
    t_volume += 5e-8 * grid.n_voxels             # particle detection
    t_volume += SECONDS_PER_RAY_PARTICLE_FIT * n_rays   # their positions from the light field
    t_piv = rates.piv_s_per_call + rates.piv_s_per_window_voxel * _window_voxels(
        grid.shape, windows, overlap, passes)
    # the check does not depend on the reconstruction: rehearsed with any of them
    t_check = (rates.rehearsal.check_s_per_pixel if rates.rehearsal is not None else
               SECONDS_PER_PIXEL_RECORDING_CHECK) * checked_pixels
    return {"weights": t_weights, "volume": t_volume, "piv": t_piv,
            "recording_check": t_check, "first_volume": t_first,
            "reconstruct": t_weights + t_check + t_first + t_volume,
            "pair": t_weights + t_check + t_first + 2 * t_volume + t_piv,
            "pair_cached_weights": t_check + t_first + 2 * t_volume + t_piv}


