"""Whole-chain validation on synthetic vortex flows: simulate -> calibrate -> reconstruct ->
correlate -> compare with the known displacement field.

:func:`run_case` drives one case (Lamb-Oseen vortex with its axis along y, so that particles
move in depth; or Hill's spherical vortex); ``plenopiv demo`` and ``plenopiv validate
oseen|hill`` are thin wrappers around it.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from plenopiv.calibration.pipeline import calibrate
from plenopiv.camera import CameraModel, load_camera
from plenopiv.config import (
    Experiment,
    ImagesConfig,
    OutputConfig,
    PIVConfig,
    ReconstructionSettings,
)
from plenopiv.io import atomic_path
from plenopiv.pipeline import process_pair, save_pair
from plenopiv.synthetic.flows import HillVortex, LambOseen, advect
from plenopiv.synthetic.images import (
    Ruler,
    alignment_image,
    field_of_view,
    finish_image,
    focal_point_image,
    ruler_image,
)
from plenopiv.synthetic.seeding import SeedingBox, particle_count, simulate_pair
from plenopiv.volume import VolumeGrid


@dataclass(frozen=True)
class VortexCase:
    """One synthetic case. Lengths in metres, seconds for dt.

    Attributes
    ----------
    flow : {"oseen", "hill"}
    camera : preset name or path
    particles_per_lenslet : seeding density
    depth : half depth of the seeded and reconstructed volume, metres
    max_displacement : largest particle displacement, metres
    lateral_fill : fraction of the field of view seeded and reconstructed
    voxel_depth_factor : depth voxel / lateral voxel
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


def _flow(case: VortexCase, box: SeedingBox):
    half_y = 0.5 * (box.y[1] - box.y[0])
    vmax = case.max_displacement / case.dt
    if case.flow == "oseen":
        rc = 0.6 * min(half_y, case.depth)
        return LambOseen(circulation=vmax * 2 * np.pi * rc / 0.6382, core_radius=rc,
                         axis=(0.0, 1.0, 0.0))
    if case.flow == "hill":
        return HillVortex(radius=0.8 * min(half_y, case.depth), speed=vmax / 1.5,
                          axis=(1.0, 0.0, 0.0))
    raise ValueError(f"flow = {case.flow!r}: expected 'oseen' or 'hill'")


def aligned_grid(camera: CameraModel, case: VortexCase) -> VolumeGrid:
    """A grid whose lateral voxels are the lenslet footprints on the focal plane (centred on
    them), in effective coordinates."""
    b = camera.microlens_array.pitch * camera.object_distance / camera.image_distance
    hx, hy = field_of_view(camera, 0.0)
    nx = int(case.lateral_fill * hx / b)
    ny = int(case.lateral_fill * hy / b)
    dz = b * case.voxel_depth_factor
    eff_depth = case.depth
    if camera.external_interface is not None:
        eff_depth *= camera.external_interface.depth_ratio
    nz = int(np.ceil(eff_depth / dz))
    return VolumeGrid.from_bounds(((-nx - 0.5) * b, (nx + 0.5) * b), ((-ny - 0.5) * b,
                                  (ny + 0.5) * b), (-(nz + 0.5) * dz, (nz + 0.5) * dz),
                                  voxel=(b, b, dz))


def compare_with_truth(vectors, flow, dt, grid: VolumeGrid, window_vox) -> dict:
    """Error of the measured field against the flow's displacement at the window centres.

    Returns bias and rms per component in voxels (lateral voxel for u, v; depth voxel for w),
    over valid vectors at least half a window inside the volume.
    """
    x, y, z = vectors.x, vectors.y, vectors.z
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    # PIV measures the displacement of the particles around the window centre between the
    # exposures, i.e. of the material point that sits at the centre half-way between them
    truth = advect(flow, pts, dt / 2) - advect(flow, pts, -dt / 2)
    meas = np.stack([vectors.u.ravel(), vectors.v.ravel(), vectors.w.ravel()], axis=1)
    b = grid.bounds
    wz, wy, wx = window_vox
    inner = ((np.abs(X.ravel()) <= b[0, 1] - 0.5 * wx * grid.voxel[0])
             & (np.abs(Y.ravel()) <= b[1, 1] - 0.5 * wy * grid.voxel[1])
             & (np.abs(Z.ravel()) <= b[2, 1] - 0.5 * wz * grid.voxel[2]))
    ok = np.asarray(vectors.valid).ravel() & inner
    vox = np.array([grid.voxel[0], grid.voxel[1], grid.voxel[2]])
    err = (meas[ok] - truth[ok]) / vox
    return {"n_vectors": int(ok.sum()), "valid_fraction": float(np.mean(vectors.valid)),
            "bias_vox": err.mean(axis=0).tolist() if len(err) else [np.nan] * 3,
            "rms_vox": np.sqrt((err ** 2).mean(axis=0)).tolist() if len(err) else [np.nan] * 3,
            "true_max_displacement_vox": (np.abs(truth) / vox).max(axis=0).tolist()}


def run_case(case: VortexCase, out: str | Path, *, progress=None) -> dict:
    """Run one synthetic case end to end and write every product to ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rng = np.random.default_rng(case.seed)
    truth_cam = load_camera(case.camera)
    timings = {}

    # calibration images and calibration (or the exact model calibration)
    if case.calibrate:
        fp = finish_image(focal_point_image(truth_cam, f_number=16), noise="poisson", rng=rng)
        al = finish_image(alignment_image(truth_cam), noise="poisson", rng=rng)
        ru = finish_image(ruler_image(truth_cam, Ruler(1e-3), rays_per_lenslet=1000),
                          noise="poisson", rng=rng)
        # the user's camera file does not know S_i
        user_cam = truth_cam.replace(main_lens=replace(truth_cam.main_lens,
                                                       image_distance=None))
        rep = calibrate(user_cam, fp, alignment_image=al, ruler_image=ru, ruler_spacing=1e-3,
                        method="both")
        cal = rep.calibration
        cal.save(out / "calibration.h5", config={"summary": rep.summary()})
        cal_summary = rep.summary()
    else:
        from plenopiv.calibration.model import Calibration

        cal = Calibration.from_camera(truth_cam)
        cal_summary = {"image_distance_mm": cal.image_distance * 1e3, "method": "model"}
    timings["calibrate_s"] = time.perf_counter() - t0

    # the pair
    t1 = time.perf_counter()
    grid = aligned_grid(cal.effective_camera, case)
    box = SeedingBox(tuple(grid.bounds[0] * 0.98), tuple(grid.bounds[1] * 0.98),
                     (-case.depth, case.depth))
    flow = _flow(case, box)
    n = particle_count(truth_cam, box, per_lenslet=case.particles_per_lenslet)
    n = int(n * (box.x[1] - box.x[0]) * (box.y[1] - box.y[0])
            / np.prod(2 * np.array(field_of_view(truth_cam, 0.0))))
    pair = simulate_pair(truth_cam, flow, dt=case.dt, box=box, n_particles=n, rng=rng,
                         rays_per_particle=case.rays_per_particle)
    if case.noise:
        ia = finish_image(pair.image_a, noise="poisson", rng=rng)
        ib = finish_image(pair.image_b, noise="poisson", rng=rng)
    else:
        ia, ib = pair.image_a, pair.image_b
    timings["simulate_s"] = time.perf_counter() - t1

    exp = Experiment(camera=cal.camera, volume=grid,
                     reconstruction=ReconstructionSettings(),
                     piv=PIVConfig(windows=list(case.windows), overlap=0.5, passes=3),
                     images=ImagesConfig(dt_s=case.dt),
                     output=OutputConfig(directory=str(out), weights_cache=""),
                     base_dir=out)
    t2 = time.perf_counter()
    res = process_pair(cal, ia, ib, exp, progress=progress)
    timings.update(res.timings)
    paths = save_pair(res, out, "pair", exp, extra_attrs={"flow": case.flow})
    timings["total_s"] = time.perf_counter() - t0
    timings["pair_s"] = time.perf_counter() - t2

    # comparison with the truth: displacement (the saved field holds velocity when dt is set)
    disp = replace(res.vectors, dt=None)
    err = compare_with_truth(disp, flow, case.dt, grid, case.windows[-1])
    found = len(res.volume_a.particle_position)
    summary = {"case": case.__dict__, "n_particles": n, "n_found_a": found,
               "calibration": cal_summary, "grid_shape": list(grid.shape),
               "voxel_mm": [v * 1e3 for v in grid.voxel], "errors": err,
               "timings_s": {k: round(v, 2) for k, v in timings.items()}, "products": paths}
    with atomic_path(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=1, default=str))
    return summary
