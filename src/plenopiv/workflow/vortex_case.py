"""Whole-chain validation on synthetic vortex flows, against the known displacement field.

The chain: simulate -> calibrate -> reconstruct -> correlate -> compare with the truth.

:func:`run_case` drives one case (Lamb-Oseen vortex with its axis along y, so that particles
move in depth; or Hill's spherical vortex); ``plenopiv demo`` and ``plenopiv validate
oseen|hill`` are thin wrappers around it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from plenopiv.calibration.calibrate import calibrate
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import CameraModel, load_camera
from plenopiv.camera.resolution import footprint
from plenopiv.config.experiment import Experiment, ImagesConfig, OutputConfig
from plenopiv.piv.settings import PIVSettings
from plenopiv.products.figures import vector_comparison
from plenopiv.products.files import atomic_path
from plenopiv.products.jsonio import dumps
from plenopiv.reconstruction.choose import lateral_subdivision
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.settings import as_dict
from plenopiv.synthetic.flows import HillVortex, LambOseen, Uniform
from plenopiv.synthetic.images import (
    Ruler,
    alignment_image,
    field_of_view,
    finish_image,
    focal_point_image,
    ruler_image,
)
from plenopiv.synthetic.seeding import SeedingBox, particle_count, simulate_pair
from plenopiv.workflow.accuracy import gain_bias_rms
from plenopiv.workflow.compare import field_accuracy, inner_vectors, true_displacement
from plenopiv.workflow.pair import process_pair, save_pair

#: The flows a case can run.
FLOWS = ("oseen", "hill", "uniform")
FOCAL_POINT_F_NUMBER = 16.0
"""The stop of the rendered focal-point images (the thesis's f/16), given to the calibration."""


@dataclass(frozen=True)
class VortexCase:
    """One synthetic case. Lengths in metres, seconds for dt.

    Attributes
    ----------
    flow : {"oseen", "hill", "uniform"} ("uniform": every particle moves by
        ``max_displacement`` along ``uniform_axis``, for the sub-voxel response)
    camera : preset name or path
    particles_per_lenslet : seeding density
    depth : half depth of the seeded and reconstructed volume, metres
    max_displacement : largest particle displacement, metres
    lateral_fill : fraction of the field of view seeded and reconstructed
    voxel_depth_factor : depth voxel / lenslet footprint
    lenslets : (rows, cols) to run on the central patch of the camera (None: all of it)
    lateral_oversampling : lateral voxels per lenslet footprint (1: the footprint grid of the
        thesis; 2 halves the voxel, which removes most of the peak locking of footprint
        voxels, see docs/validation/vortex.md)
    uncertainty : ``[piv] uncertainty`` of the run: "response" (default; measures the chain's
        response, three more test pairs) or "correlation" (faster)
    response_displacements : ``[piv] response_displacements``: 3 (eight test pairs, default) or 1
    windows : interrogation windows per pass (z, y, x) in voxels of the footprint grid; the
        lateral edges are multiplied by ``lateral_oversampling``
    passes : PIV passes (the last window repeats)
    overlap_correction, broad_peaks : the PIV peak fit (:class:`plenopiv.piv.PIVSettings`)
    uniform_axis : "x", "y" or "z", the direction of the ``"uniform"`` flow
    flow_axis : "x", "y", "z", a direction (3,) (normalised) or None, the axis of the vortex
        (None: the flow's own, y for Oseen so that particles move in depth, x for Hill)
    depth_centre : Z of the centre of the seeded and reconstructed volume, metres (0: centred
        on the focal plane; > 0 places it beyond the focal plane, away from the camera)
    blur_px : standard deviation of a Gaussian blur of every rendered image, pixels (the
        optics' point spread function), before the noise
    reconstruction : reconstruction settings (the library's defaults unless given)
    centre_offset : (x, y, z) of the vortex's centre from the seeded volume's centre, metres
    f_number, image_distance, lattice_rotation, lattice_offset, lattice : the camera varied
        from its preset, one property at a time (:func:`case_camera`): the recording's
        f-number, the effective S_i (metres; the magnification follows), the lenslet array's
        rotation γ (radians) and offset (s_o, t_o) (metres), "square" or "hexagonal"; None
        keeps the preset's
    voxel_lateral_factor : lateral voxel / lenslet footprint before ``lateral_oversampling``
        (1: the footprint grid; e.g. 1.1 is the voxel a user keeps at 0.125 mm when the
        magnification goes from -1 to -1.1)
    grid_shift : (x, y, z) shift of the grid from the footprints' centres, in voxels
    continuity : ``[piv] continuity``: the field's w fitted to the continuity of the flow
        (the default), or the field as correlated and corrected by its tracks
    """

    flow: str = "oseen"
    camera: str = "small_m1"
    particles_per_lenslet: float = 0.15
    depth: float = 3e-3
    max_displacement: float = 0.25e-3
    lateral_fill: float = 0.85
    voxel_depth_factor: float = 1.0
    dt: float = 1e-3
    rays_per_particle: int = 2048
    noise: bool = True
    calibrate: bool = True
    seed: int = 1
    windows: tuple = ((16, 16, 16), (12, 12, 12))
    lenslets: tuple[int, int] | None = None
    lateral_oversampling: int = 1
    uncertainty: str = "response"
    response_displacements: int = 3
    passes: int = 3
    overlap_correction: bool = True
    broad_peaks: bool = True
    uniform_axis: str = "x"
    flow_axis: str | tuple[float, float, float] | None = None
    depth_centre: float = 0.0
    blur_px: float = 0.0
    reconstruction: ReconstructionSettings = ReconstructionSettings()
    centre_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    f_number: float | None = None
    image_distance: float | None = None
    lattice_rotation: float | None = None
    lattice_offset: tuple[float, float] | None = None
    lattice: str | None = None
    voxel_lateral_factor: float = 1.0
    grid_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    continuity: bool = True

    def __post_init__(self):
        if self.flow not in FLOWS:
            raise ValueError(f"flow = {self.flow!r}: expected one of {FLOWS}")
        if self.uniform_axis not in ("x", "y", "z"):
            raise ValueError(f"uniform_axis = {self.uniform_axis!r}: expected 'x', 'y' or 'z'")
        if self.flow_axis is not None:
            vortex_axis(self.flow_axis)
        k = self.lateral_oversampling
        if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 1:
            raise ValueError(f"lateral_oversampling = {k!r}: expected an int >= 1")
        if len(self.centre_offset) != 3:
            raise ValueError(f"centre_offset = {self.centre_offset!r}: expected (x, y, z) metres")
        if len(self.grid_shift) != 3:
            raise ValueError(f"grid_shift = {self.grid_shift!r}: expected (x, y, z) voxels")
        if not self.voxel_lateral_factor > 0:
            raise ValueError(f"voxel_lateral_factor = {self.voxel_lateral_factor!r}: "
                             "expected > 0")

    @property
    def camera_changes(self) -> dict:
        """The camera properties this case sets (name: value), none for the preset's."""
        names = ("f_number", "image_distance", "lattice_rotation", "lattice_offset", "lattice")
        return {n: getattr(self, n) for n in names if getattr(self, n) is not None}

    @property
    def windows_vox(self) -> tuple:
        """The windows in voxels of this case's grid."""
        k = self.lateral_oversampling
        return tuple((wz, wy * k, wx * k) for wz, wy, wx in self.windows)


def vortex_axis(axis) -> tuple[float, float, float]:
    """The unit vector of a case's ``flow_axis``: "x", "y", "z" or a non-zero direction (3,)."""
    if isinstance(axis, str):
        if axis not in ("x", "y", "z"):
            raise ValueError(f"flow_axis = {axis!r}: expected 'x', 'y', 'z' or a direction (3,)")
        return tuple(float(k == "xyz".index(axis)) for k in range(3))
    a = np.asarray(axis, float)
    if a.shape != (3,) or not np.all(np.isfinite(a)) or not np.linalg.norm(a) > 0:
        raise ValueError(f"flow_axis = {axis!r}: expected 'x', 'y', 'z' or a non-zero "
                         "direction (3,)")
    return tuple(float(v) for v in a / np.linalg.norm(a))


def varied_camera(camera: CameraModel, case: VortexCase) -> CameraModel:
    """``camera`` with the properties ``case`` varies (:attr:`VortexCase.camera_changes`)."""
    lens = camera.main_lens
    if case.f_number is not None:
        lens = replace(lens, f_number=float(case.f_number))
    if case.image_distance is not None:
        lens = replace(lens, image_distance=float(case.image_distance))
    mla = camera.microlens_array
    if case.lattice_rotation is not None:
        mla = replace(mla, rotation=float(case.lattice_rotation))
    if case.lattice_offset is not None:
        mla = replace(mla, offset=tuple(float(v) for v in case.lattice_offset))
    if case.lattice is not None:
        mla = replace(mla, grid=case.lattice)
    return camera.replace(main_lens=lens, microlens_array=mla)


def case_camera(case: VortexCase) -> CameraModel:
    """The true camera of a case: the preset with its changes, or their central patch.

    The changes are :func:`varied_camera`'s; the patch is ``case.lenslets``, when given.
    """
    cam = load_camera(case.camera)
    if case.camera_changes:
        cam = varied_camera(cam, case)
    return cam if case.lenslets is None else cam.patch(*case.lenslets)


def _axis(case: VortexCase, default: str) -> tuple[float, float, float]:
    """The unit vector of the case's vortex axis (``flow_axis``, else ``default``)."""
    return vortex_axis(default if case.flow_axis is None else case.flow_axis)


def _flow(case: VortexCase, box: SeedingBox):
    half_y = 0.5 * (box.y[1] - box.y[0])
    vmax = case.max_displacement / case.dt
    centre = tuple(float(c) for c in np.add((0.0, 0.0, case.depth_centre), case.centre_offset))
    if case.flow == "oseen":
        rc = 0.6 * min(half_y, case.depth)
        return LambOseen(circulation=vmax * 2 * np.pi * rc / 0.6382, core_radius=rc,
                         centre=centre, axis=_axis(case, "y"))
    if case.flow == "hill":
        return HillVortex(radius=0.8 * min(half_y, case.depth), speed=vmax / 1.5,
                          centre=centre, axis=_axis(case, "x"))
    if case.flow == "uniform":
        v = np.zeros(3)
        v["xyz".index(case.uniform_axis)] = vmax
        return Uniform(tuple(v))
    raise ValueError(f"flow = {case.flow!r}: expected one of {FLOWS}")


def seeding_box(case: VortexCase, grid: VolumeGrid) -> SeedingBox:
    """The box a case seeds: the grid's lateral extent (98 %) and the case's depth."""
    return SeedingBox(tuple(grid.bounds[0] * 0.98), tuple(grid.bounds[1] * 0.98),
                      (case.depth_centre - case.depth, case.depth_centre + case.depth))


def case_flow(case: VortexCase, grid: VolumeGrid):
    """The flow of a case on its grid (as :func:`run_case` builds it)."""
    return _flow(case, seeding_box(case, grid))


def aligned_grid(camera: CameraModel, case: VortexCase) -> VolumeGrid:
    """A grid whose lateral voxels are the lenslet footprints on the focal plane.

    The voxels are centred on the footprints, in effective coordinates; a case's
    ``voxel_lateral_factor`` scales the lateral voxel and its ``grid_shift`` moves the grid
    (in voxels) off the footprints.
    """
    b = footprint(camera) * case.voxel_lateral_factor
    hx, hy = field_of_view(camera, 0.0)
    nx = int(case.lateral_fill * hx / b)
    ny = int(case.lateral_fill * hy / b)
    dz = footprint(camera) * case.voxel_depth_factor
    eff_depth, eff_centre = case.depth, case.depth_centre
    if camera.external_interface is not None:
        eff_depth *= camera.external_interface.depth_ratio
        eff_centre *= camera.external_interface.depth_ratio
    nz = int(np.ceil(eff_depth / dz))
    zc = dz * round(eff_centre / dz)          # a voxel centre stays on the focal plane
    lat = b / case.lateral_oversampling
    sx, sy, sz = (float(v) for v in case.grid_shift)
    return VolumeGrid.from_bounds(((-nx - 0.5 + sx) * b, (nx + 0.5 + sx) * b),
                                  ((-ny - 0.5 + sy) * b, (ny + 0.5 + sy) * b),
                                  (zc + (sz - nz - 0.5) * dz, zc + (sz + nz + 0.5) * dz),
                                  voxel=(lat, lat, dz))


def coverage(error, sigma) -> np.ndarray:
    """Share of ``|error| <= 2 sigma`` per column (component); NaN sigma counts as a miss."""
    e, s = np.asarray(error, float), np.asarray(sigma, float)
    with np.errstate(invalid="ignore"):
        return np.mean(np.abs(e) <= 2.0 * s, axis=0)


def _band(meas: np.ndarray, truth: np.ndarray, vox: np.ndarray) -> dict:
    """Gain, bias and rms per component, in voxels, of (N, 3) measured and true metres."""
    g = gain_bias_rms((meas / vox).T, (truth / vox).T)
    return {"n_vectors": g["n"], "gain": g["gain"], "gain_se": g["gain_se"],
            "correlation": g["correlation"],
            "bias_vox": g["bias"], "rms_vox": g["rms"], "true_rms_vox": g["true_rms"]}


def compare_with_truth(vectors, flow, dt, grid: VolumeGrid, window_vox, *,
                       depth_bands: int = 3, truth: np.ndarray | None = None) -> dict:
    """Error of the measured field against the flow's displacement at the window centres.

    Returns, per component in voxels (lateral voxel for u, v; depth voxel for w), the gain
    (least-squares slope of measured on true, :func:`~plenopiv.workflow.accuracy.gain_bias_rms`;
    NaN for a component that does not vary, as in a uniform shift), the bias and the rms, over
    valid vectors at least half a window inside the volume; and the same in ``depth_bands``
    bands of |Z| (distance from the focal plane), the first one nearest focus.
    ``truth``: :func:`true_displacement` of these vectors when already computed.
    """
    Z = np.meshgrid(vectors.z, vectors.y, vectors.x, indexing="ij")[0]
    if truth is None:
        truth = true_displacement(vectors, flow, dt)
    truth = truth.reshape(3, -1).T
    meas = np.stack([vectors.u.ravel(), vectors.v.ravel(), vectors.w.ravel()], axis=1)
    ok = np.asarray(vectors.valid).ravel() & inner_vectors(vectors, grid, window_vox).ravel()
    vox = np.array([grid.voxel[0], grid.voxel[1], grid.voxel[2]])
    out = {**_band(meas[ok], truth[ok], vox), "valid_fraction": float(np.mean(vectors.valid)),
           "true_max_displacement_vox": (np.abs(truth) / vox).max(axis=0).tolist()}
    sigma = [getattr(vectors, f"{c}_uncertainty", None) for c in "uvw"]
    if all(s is not None for s in sigma) and ok.any():
        err = (meas[ok] - truth[ok]) / vox
        sig = np.stack([np.asarray(s).ravel() for s in sigma], axis=1)[ok] / vox
        out["coverage_2sigma"] = coverage(err, sig).tolist()
        n = np.sum(np.isfinite(sig), axis=0)        # a component may carry no uncertainty
        rms = np.sqrt(np.nansum(sig**2, axis=0) / np.maximum(n, 1))
        out["rms_sigma_vox"] = np.where(n > 0, rms, np.nan).tolist()
    z_abs = np.abs(Z.ravel()[ok])
    edges = np.linspace(0.0, z_abs.max() if len(z_abs) else 0.0, depth_bands + 1)
    edges[-1] = np.inf
    out["by_depth"] = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (z_abs >= lo) & (z_abs < hi)
        out["by_depth"].append({"abs_z_mm": [float(lo * 1e3), float(min(hi, z_abs.max()) * 1e3)],
                                **_band(meas[ok][sel], truth[ok][sel], vox)})
    if not len(z_abs):
        out["by_depth"] = []
    return out


def _finished_pair(case: VortexCase, pair, rng) -> tuple[np.ndarray, np.ndarray]:
    """The pair's images with the case's Poisson noise and PSF blur (as rendered without)."""
    if case.noise:
        return tuple(finish_image(im, noise="poisson", rng=rng, blur_px=case.blur_px)
                     for im in (pair.image_a, pair.image_b))
    if case.blur_px > 0:
        return tuple(finish_image(im, blur_px=case.blur_px, bit_depth=None)
                     for im in (pair.image_a, pair.image_b))
    return pair.image_a, pair.image_b


def case_experiment(case: VortexCase, calibration, out: Path) -> Experiment:
    """The experiment of ``case`` with ``calibration``: its grid, reconstruction and PIV."""
    return Experiment(camera=calibration.camera,
                      volume=aligned_grid(calibration.effective_camera, case),
                      reconstruction=case.reconstruction,
                      piv=PIVSettings(windows=list(case.windows_vox), overlap=0.5,
                                    passes=case.passes, uncertainty=case.uncertainty,
                                    response_displacements=case.response_displacements,
                                    response_particles_per_lenslet=case.particles_per_lenslet,
                                    overlap_correction=case.overlap_correction,
                                    broad_peaks=case.broad_peaks,
                                    continuity=case.continuity),
                      images=ImagesConfig(dt_s=case.dt),
                      output=OutputConfig(directory=str(out), weights_cache=""),
                      base_dir=out)


def _calibration(case: VortexCase, truth_cam: CameraModel, rng, out: Path, report) -> tuple:
    """``(calibration, its summary)`` of a case: from rendered calibration images, or exact."""
    from plenopiv.calibration.model import Calibration

    if not case.calibrate:
        cal = Calibration.from_camera(truth_cam)
        return cal, {"image_distance_mm": cal.image_distance * 1e3, "method": "model"}
    blur = case.blur_px
    report("calibration images", 0.0)
    fp = finish_image(focal_point_image(truth_cam, f_number=FOCAL_POINT_F_NUMBER),
                      noise="poisson", rng=rng, blur_px=blur)
    report("calibration images", 0.3)
    al = finish_image(alignment_image(truth_cam), noise="poisson", rng=rng, blur_px=blur)
    report("calibration images", 0.5)
    ru = finish_image(ruler_image(truth_cam, Ruler(1e-3), rays_per_lenslet=1000),
                      noise="poisson", rng=rng, blur_px=blur)
    report("calibrate")
    # the user's camera file does not know S_i
    user_cam = truth_cam.replace(main_lens=replace(truth_cam.main_lens, image_distance=None))
    rep = calibrate(user_cam, fp, alignment_image=al, ruler_image=ru, ruler_spacing=1e-3,
                    method="both", focal_point_f_number=FOCAL_POINT_F_NUMBER)
    rep.calibration.save(out / "calibration.h5", config={"summary": rep.summary()})
    return rep.calibration, rep.summary()


def _case_pair(case: VortexCase, grid: VolumeGrid, truth_cam: CameraModel, rng, out: Path,
               report) -> tuple:
    """The case's seeded pair on the calibrated grid, its truth in ``truth_particles.npz``.

    Returns ``(image A, image B, particle count, flow, start time)``.
    """
    report("simulate pair")
    t1 = time.perf_counter()
    box = seeding_box(case, grid)
    flow = _flow(case, box)
    n = particle_count(truth_cam, box, per_lenslet=case.particles_per_lenslet)
    n = int(n * (box.x[1] - box.x[0]) * (box.y[1] - box.y[0])
            / np.prod(2 * np.array(field_of_view(truth_cam, 0.0))))
    pair = simulate_pair(truth_cam, flow, dt=case.dt, box=box, n_particles=n, rng=rng,
                         rays_per_particle=case.rays_per_particle)
    ia, ib = _finished_pair(case, pair, rng)
    with atomic_path(out / "truth_particles.npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, positions_a=pair.positions_a, positions_b=pair.positions_b)
    return ia, ib, n, flow, t1


def _rehearsals(case: VortexCase, truth_cam: CameraModel, out: Path, precompile: bool):
    """The background compilation of a case (:mod:`plenopiv.workflow.precompile`), or none.

    Rehearsed on the exact calibration, while the case renders and calibrates.
    """
    from plenopiv.calibration.model import Calibration
    from plenopiv.workflow.precompile import Rehearsals

    if not (precompile and case.calibrate):
        return Rehearsals([])
    model = Calibration.from_camera(truth_cam)
    return Rehearsals.start(model, case_experiment(case, model, out))


def run_case(case: VortexCase, out: str | Path, *, progress=None,
             precompile: bool = False) -> dict:
    """Run one synthetic case end to end and write every product to ``out``.

    ``precompile``: while the case renders and calibrates, compile the reconstruction's and
    the PIV's kernels in two background processes (:mod:`plenopiv.workflow.precompile`; for a first
    run, before numba's cache holds them).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rng = np.random.default_rng(case.seed)
    truth_cam = case_camera(case)
    timings = {}

    with _rehearsals(case, truth_cam, out, precompile) as rehearsals:
        # each stage waits for its rehearsal, if any, before it calls its first kernel
        report = rehearsals.paced(progress)
        cal, cal_summary = _calibration(case, truth_cam, rng, out, report)
        timings["calibrate_s"] = time.perf_counter() - t0
        exp = case_experiment(case, cal, out)
        ia, ib, n, flow, t1 = _case_pair(case, exp.volume, truth_cam, rng, out, report)
        timings["simulate_s"] = time.perf_counter() - t1
        t2 = time.perf_counter()
        res = process_pair(cal, ia, ib, exp, progress=report)
    grid = exp.volume
    timings.update(res.timings)
    report("products")
    paths = save_pair(res, out, "pair", exp, extra_attrs={"flow": case.flow})
    paths["truth_particles"] = str(out / "truth_particles.npz")
    timings["total_s"] = time.perf_counter() - t0
    timings["pair_s"] = time.perf_counter() - t2

    # comparison with the truth: displacement (the saved field holds velocity when dt is set)
    disp = replace(res.vectors, dt=None)
    truth = true_displacement(disp, flow, case.dt)
    err = compare_with_truth(disp, flow, case.dt, grid, case.windows_vox[-1], truth=truth)
    used = np.asarray(disp.valid, bool) & inner_vectors(disp, grid, case.windows_vox[-1])
    acc = field_accuracy(np.stack([disp.u, disp.v, disp.w]), truth,
                         np.broadcast_to(np.asarray(disp.z)[:, None, None], used.shape),
                         grid.voxel, mask=used)
    accuracy = {"truth_kind": "simulated pair", "truth_at_vectors": "flow", **acc,
                "notes": [f"truth: the case's {case.flow} flow, evaluated at each window "
                          "centre half-way between the exposures", *acc["notes"]]}
    vox = np.asarray(grid.voxel)[:, None, None, None]
    measured = np.stack([disp.u, disp.v, disp.w]) / vox
    paths["png_truth"] = str(vector_comparison(
        disp.x, disp.y, disp.z, measured, truth / vox, disp.valid, out / "pair_vs_truth.png",
        voxel=grid.voxel, title=f"{case.flow}: measured against true displacement"))
    found = len(res.volume_a.particle_position)
    case_dict = {**case.__dict__, "reconstruction": as_dict(case.reconstruction)}
    summary = {"case": case_dict, "n_particles": n, "n_found_a": found,
               "lateral_subdivision": list(lateral_subdivision(cal, grid, case.reconstruction)),
               "calibration": cal_summary, "grid_shape": list(grid.shape),
               "voxel_mm": [v * 1e3 for v in grid.voxel], "errors": err, "accuracy": accuracy,
               "timings_s": {k: round(v, 2) for k, v in timings.items()}, "products": paths}
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(dumps(summary, indent=1, default=str))
    return summary
