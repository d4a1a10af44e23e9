"""Tracking against correlation on the vortex pairs, and ray-bundle against centroid depths.

Two measurements (stage functions: cases in, dicts of numbers out; no files):

:func:`measure_case`
    one Oseen or Hill pair of :mod:`plenopiv.workflow.vortex_case` (calibration from images,
    reconstruction, correlation) tracked by :func:`plenopiv.workflow.tracking.track_pair`:
    fraction of the true particles tracked, wrong-match rate, displacement error per axis
    of the tracks and of the correlation (on its grid and interpolated at the particles),
    position error per axis of the bundle fits and of the volume centroids, and how often
    the true error lies within ±2 reported standard uncertainties;
:func:`measure_single_particles`
    one particle at a time at the depths of thesis §5.1 (-10 … +10 mm), centroid against
    bundle position, with the bundle's reported uncertainty.

``pipelines/validate_tracking.py`` writes ``docs/validation/tracking.{json,md}`` from them.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.model import Calibration
from plenopiv.camera.resolution import resolution_cell
from plenopiv.config.experiment import Experiment, ImagesConfig, OutputConfig
from plenopiv.lightfield import light_field
from plenopiv.particles.bundle import bundle_positions
from plenopiv.particles.forward import refine_positions
from plenopiv.piv.settings import PIVSettings
from plenopiv.synthetic.images import (
    Ruler,
    alignment_image,
    field_of_view,
    finish_image,
    focal_point_image,
    particle_image,
    ruler_image,
)
from plenopiv.synthetic.seeding import SeedingBox, particle_count, simulate_pair
from plenopiv.tracking.matching import interpolate_displacement
from plenopiv.tracking.settings import TrackingSettings
from plenopiv.tracking.tracks import bin_tracks
from plenopiv.workflow.pair import process_pair
from plenopiv.workflow.tracking import track_pair
from plenopiv.workflow.volume import reconstruct_volume
from plenopiv.workflow.vortex_case import (
    VortexCase,
    _flow,
    aligned_grid,
    case_camera,
    compare_with_truth,
)

__all__ = ["associate", "associate_tracks", "measure_case", "measure_single_particles",
           "rms_per_axis"]


def rms_per_axis(err) -> list[float]:
    """Root mean square of (N, 3) errors per axis (NaN when empty)."""
    e = np.asarray(err, float).reshape(-1, 3)
    return np.sqrt((e ** 2).mean(axis=0)).tolist() if len(e) else [np.nan] * 3


def associate(found, truth, scale, tolerance: float = 1.0) -> np.ndarray:
    """Index of the nearest true particle of each found one, -1 beyond ``tolerance`` cells.

    ``found`` (N, 3), ``truth`` (M, 3) metres; ``scale`` (3,) metres per cell.
    """
    f = np.asarray(found, float).reshape(-1, 3) / scale
    t = np.asarray(truth, float).reshape(-1, 3) / scale
    if not len(f) or not len(t):
        return np.full(len(f), -1)
    d, j = cKDTree(t).query(f, k=1, distance_upper_bound=tolerance)
    return np.where(np.isfinite(d), j, -1)


def associate_tracks(pos_a, pos_b, true_a, true_b, scale, tolerance: float = 1.0) -> np.ndarray:
    """Return the true particle of each track (-1: none within ``tolerance`` cells of both ends).

    The true particle is the nearest in the joint (A, B) space (positions divided by
    ``scale``, metres per cell); the track is correct when both its ends lie within
    ``tolerance`` cells of that particle's positions at the two exposures (one resolution
    cell: particles closer than that are not told apart; a correct pair with a large position
    error is an accuracy matter, counted in the rms, not a wrong match).
    """
    sc = np.asarray(scale, float)
    t6 = np.hstack([np.asarray(true_a, float) / sc, np.asarray(true_b, float) / sc])
    f6 = np.hstack([np.asarray(pos_a, float).reshape(-1, 3) / sc,
                    np.asarray(pos_b, float).reshape(-1, 3) / sc])
    if not len(f6) or not len(t6):
        return np.full(len(f6), -1)
    _, j = cKDTree(t6).query(f6, k=1)
    da = np.linalg.norm(f6[:, :3] - t6[j, :3], axis=1)
    db = np.linalg.norm(f6[:, 3:] - t6[j, 3:], axis=1)
    return np.where((da <= tolerance) & (db <= tolerance), j, -1)


def _calibration(case: VortexCase, rng):
    cam = case_camera(case)
    if not case.calibrate:
        return cam, Calibration.from_camera(cam)
    fp = finish_image(focal_point_image(cam, f_number=16), noise="poisson", rng=rng)
    al = finish_image(alignment_image(cam), noise="poisson", rng=rng)
    ru = finish_image(ruler_image(cam, Ruler(1e-3), rays_per_lenslet=1000), noise="poisson",
                      rng=rng)
    user = cam.replace(main_lens=replace(cam.main_lens, image_distance=None))
    rep = calibrate(user, fp, alignment_image=al, ruler_image=ru, ruler_spacing=1e-3,
                    method="both")
    return cam, rep.calibration


def _simulate(case: VortexCase, cam, cal, rng, axis=None):
    """Grid, flow, pair and the two images of a case; ``axis`` (3,) turns the vortex."""
    grid = aligned_grid(cal.effective_camera, case)
    box = SeedingBox(tuple(grid.bounds[0] * 0.98), tuple(grid.bounds[1] * 0.98),
                     (-case.depth, case.depth))
    flow = _flow(case, box)
    if axis is not None:
        flow = replace(flow, axis=tuple(float(a) for a in axis))
    n = particle_count(cam, box, per_lenslet=case.particles_per_lenslet)
    fov = np.prod(2 * np.array(field_of_view(cam, 0.0)))
    n = int(n * (box.x[1] - box.x[0]) * (box.y[1] - box.y[0]) / fov)
    pair = simulate_pair(cam, flow, dt=case.dt, box=box, n_particles=n, rng=rng,
                         rays_per_particle=case.rays_per_particle)
    ia = finish_image(pair.image_a, noise="poisson", rng=rng) if case.noise else pair.image_a
    ib = finish_image(pair.image_b, noise="poisson", rng=rng) if case.noise else pair.image_b
    return grid, flow, pair, ia, ib


def measure_case(case: VortexCase) -> dict:
    """Track one vortex pair and compare tracks and correlation with the truth.

    Returns
    -------
    dict
        ``n_true`` (true particles with both exposures inside the volume), ``n_found_a``,
        ``n_tracks``, ``tracked_fraction`` (true particles with a correct track / n_true),
        ``wrong_match_rate`` (tracks without a true particle within one resolution cell
        of both ends, :func:`associate_tracks` / tracks),
        ``track_rms_vox`` / ``track_bias_vox`` (displacement error of the correct tracks,
        x y z, in voxels of the grid), ``track_rms_vox_off_focus`` (the tracks whose two ends
        were each seen through more than one lenslet, ``off_focus_fraction`` of them),
        ``track_within_2sigma`` (fraction within ±2 reported uncertainties),
        ``piv_grid_rms_vox`` (correlation against the flow on its grid,
        :func:`~plenopiv.workflow.vortex_case.compare_with_truth`), ``piv_at_tracks_rms_vox``
        (correlation interpolated at the correct tracks' mid-points against their true
        displacement), ``binned_rms_vox`` (tracks binned on the PIV grid against the flow),
        ``position_rms_vox`` for ``bundle`` and ``centroid`` (A particles of the correct
        tracks), ``within_2sigma`` (fraction of bundle position errors within ±2σ, per axis),
        ``counts`` of the matching, ``timings_s``.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(case.seed)
    cam, cal = _calibration(case, rng)
    grid, flow, pair, ia, ib = _simulate(case, cam, cal, rng)
    exp = Experiment(camera=cal.camera, volume=grid,
                     piv=PIVSettings(windows=tuple(case.windows_vox), overlap=0.5, passes=3,
                                     response_particles_per_lenslet=case.particles_per_lenslet),
                     images=ImagesConfig(dt_s=case.dt), output=OutputConfig(weights_cache=""))
    t1 = time.perf_counter()
    res = process_pair(cal, ia, ib, exp)
    t2 = time.perf_counter()
    tracks = track_pair(cal, ia, ib, res.volume_a, res.volume_b, res.vectors,
                        settings=exp.tracking)
    t3 = time.perf_counter()

    vox = np.asarray(grid.voxel)
    corr = res.volume_a.correction
    lat, dep = resolution_cell(cal.effective_camera)
    scale = np.array([lat, lat, dep * corr.scale])
    lo, hi = grid.bounds[:, 0].copy(), grid.bounds[:, 1].copy()
    lo[2], hi[2] = corr.depth(lo[2]), corr.depth(hi[2])
    inside = np.all((pair.positions_a >= lo) & (pair.positions_a <= hi)
                    & (pair.positions_b >= lo) & (pair.positions_b <= hi), axis=1)
    true_a, true_b = pair.positions_a, pair.positions_b
    ja = associate_tracks(tracks.position_a, tracks.position_b, true_a, true_b, scale)
    correct = ja >= 0
    n_true = int(inside.sum())
    tracked = np.unique(ja[correct & inside[np.maximum(ja, 0)]])
    true_d = true_b[ja[correct]] - true_a[ja[correct]]
    err = (tracks.displacement[correct] - true_d) / vox
    mid = 0.5 * (tracks.position_a[correct] + tracks.position_b[correct])
    vec = res.vectors
    piv_d = interpolate_displacement(vec.x, vec.y, vec.z, vec.u, vec.v, vec.w, mid)
    pos_err_b = (tracks.position_a[correct] - true_a[ja[correct]])
    centroid = res.volume_a.correction.points(res.volume_a.volume_position_effective)
    pos_err_c = centroid[tracks.index_a[correct]] - true_a[ja[correct]]
    sig = tracks.uncertainty_a[correct]
    disp = replace(vec, dt=None)
    piv_grid = compare_with_truth(disp, flow, case.dt, grid, case.windows_vox[-1])
    binned = compare_with_truth(bin_tracks(tracks, disp), flow, case.dt, grid,
                                case.windows_vox[-1])
    sharp = (tracks.n_lenslets_a[correct] > 1) & (tracks.n_lenslets_b[correct] > 1)
    return {
        "flow": case.flow, "particles_per_lenslet": case.particles_per_lenslet,
        "seed": case.seed, "grid_shape": list(grid.shape),
        "voxel_mm": (vox * 1e3).tolist(), "cell_mm": (scale * 1e3).tolist(),
        "n_true": n_true, "n_found_a": len(res.volume_a.particle_position),
        "n_tracks": len(tracks), "n_correct": int(correct.sum()),
        "tracked_fraction": len(tracked) / n_true if n_true else np.nan,
        "wrong_match_rate": float((~correct).mean()) if len(tracks) else np.nan,
        "track_rms_vox": rms_per_axis(err),
        "track_bias_vox": err.mean(axis=0).tolist() if len(err) else [np.nan] * 3,
        "off_focus_fraction": float(sharp.mean()) if len(sharp) else np.nan,
        "track_rms_vox_off_focus": rms_per_axis(err[sharp]),
        "piv_at_tracks_rms_vox_off_focus": rms_per_axis(((piv_d - true_d) / vox)[sharp]),
        "track_within_2sigma": (np.abs(err * vox) <= 2 * tracks.uncertainty[correct]).mean(
            axis=0).tolist() if len(err) else [np.nan] * 3,
        "piv_grid_rms_vox": piv_grid["rms_vox"],
        "piv_at_tracks_rms_vox": rms_per_axis((piv_d - true_d) / vox),
        "position_rms_vox_off_focus": {
            "bundle": rms_per_axis((pos_err_b / vox)[tracks.n_lenslets_a[correct] > 1]),
            "centroid": rms_per_axis((pos_err_c / vox)[tracks.n_lenslets_a[correct] > 1])},
        "binned_rms_vox": binned["rms_vox"], "binned_valid_fraction":
            binned["valid_fraction"],
        "position_rms_vox": {"bundle": rms_per_axis(pos_err_b / vox),
                             "centroid": rms_per_axis(pos_err_c / vox)},
        "within_2sigma": (np.abs(pos_err_b) <= 2 * sig).mean(axis=0).tolist()
        if len(sig) else [np.nan] * 3,
        "median_sigma_vox": (np.median(sig, axis=0) / vox).tolist()
        if len(sig) else [np.nan] * 3,
        "counts": tracks.counts,
        "timings_s": {"simulate_calibrate": round(t1 - t0, 2), "pair": round(t2 - t1, 2),
                      "track": round(t3 - t2, 2)},
    }


def measure_single_particles(depths, *, camera=None, rays_per_particle: int = 20000,
                             offset_vox: float = 0.5, seed: int = 0) -> dict:
    """Centroid against bundle position of one particle at a time (thesis §5.1 geometry).

    Parameters
    ----------
    depths : array_like
        True depths Z, metres.
    camera : CameraModel, optional
        Default :func:`pipelines.studies.depth.thesis_camera` (41 x 41 lenslets,
        50 mm lens at M = -1, no interface).
    offset_vox : float
        Lateral position drawn uniformly within ± this many voxels of the axis, so that the
        particle does not sit on a lenslet's axis (voxel = footprint).
    seed : int
        Seeds the lateral offsets and the renderer.

    Returns
    -------
    dict
        Per depth: ``depth_m``, ``centroid_error_m``, ``bundle_error_m`` and
        ``refined_error_m`` (the bundle position refined by
        :func:`plenopiv.particles.forward.refine_positions`, as the tracks use it) (N, 3, NaN
        where no particle was found), ``bundle_sigma_m`` (N, 3), ``n_lenslets``; summaries
        ``rms_mm`` for centroid, bundle and refined per axis, ``within_2sigma`` (bundle).
    """
    from pipelines.studies.depth import STUDY_PARTICLES, VOXEL, study_grid, thesis_camera
    from plenopiv.reconstruction.build import cached_weights

    cam = thesis_camera() if camera is None else camera
    depths = np.asarray(depths, float)
    cal = Calibration.from_camera(cam)
    grid = study_grid(depths)
    weights, _ = cached_weights(cal, grid, cache_dir=None, f_number=None, min_lit=0.5)
    lf = light_field(cal, min_lit=0.5)
    rng = np.random.default_rng(seed)
    nan3 = np.full((len(depths), 3), np.nan)
    cen, bun, sig, ref = nan3.copy(), nan3.copy(), nan3.copy(), nan3.copy()
    n_lens = np.zeros(len(depths), int)
    seen = max(2, TrackingSettings().min_lenslets)
    # the volume's centroid, the bundle's seed here, is this study's reference
    volume_positions = dataclasses.replace(STUDY_PARTICLES, position="volume")
    for i, z in enumerate(depths):
        x, y = rng.uniform(-offset_vox, offset_vox, 2) * VOXEL
        truth = np.array([x, y, z])
        img = particle_image(cam, [truth], rays_per_particle=rays_per_particle, seed=seed + i)
        res = reconstruct_volume(cal, img, grid, weights=weights, particles=volume_positions)
        if not len(res.particle_intensity):
            continue
        k = int(np.argmax(res.particle_intensity))
        cell = resolution_cell(cal.effective_camera)[1]
        b = bundle_positions(lf, img, res.particle_position_effective[k][None], depth_cell=cell)
        cen[i] = res.particle_position[k] - truth
        bun[i] = res.correction.points(b.position)[0] - truth
        r = b.position
        if b.converged[0] and b.n_lenslets[0] >= seen:    # as the tracks (tracking.pair)
            r = refine_positions(lf, img, b.position, depth_cell=cell)[0]
        ref[i] = res.correction.points(r)[0] - truth
        sig[i] = b.uncertainty[0] * np.array([1.0, 1.0, res.correction.scale])
        n_lens[i] = b.n_lenslets[0]
    ok = np.isfinite(bun).all(axis=1) & np.isfinite(cen).all(axis=1)
    ok &= np.isfinite(ref).all(axis=1)
    return {"depth_m": depths, "centroid_error_m": cen, "bundle_error_m": bun,
            "refined_error_m": ref,
            "bundle_sigma_m": sig, "n_lenslets": n_lens, "n_found": int(ok.sum()),
            "rms_mm": {"centroid": (np.array(rms_per_axis(cen[ok])) * 1e3).tolist(),
                       "bundle": (np.array(rms_per_axis(bun[ok])) * 1e3).tolist(),
                       "refined": (np.array(rms_per_axis(ref[ok])) * 1e3).tolist()},
            "within_2sigma": (np.abs(bun[ok]) <= 2 * sig[ok]).mean(axis=0).tolist()}
