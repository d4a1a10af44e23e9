"""Full-camera scale: a 16 MP plenoptic pair reconstructed and correlated on this machine.

Not a unit test. Run ``python benchmarks/full_camera.py [--particles 20000 --iterations 5
--json]``. The Auburn camera (3280 × 4904 px, 193 × 287 lenslets, 135 mm lens, 10.4 mm
substrate) records a Lamb-Oseen vortex (axis along y, so particles move in depth); the
volume is 287 × 193 × 200 voxels of one lenslet footprint (0.26 mm) each way. Its explicit
weights would hold ~1.2·10¹⁰ non-zeros (~100 GB), so the pipeline's ``projector = "auto"``
takes the matrix-free lattice projector.

``--geometry rotated|hexagonal`` mounts a rotated square array (γ = 2 mrad, offset (3, -2) µm)
or a hexagonal one (222 × 287 lenslets, γ = 1 mrad) in the same camera; the grid is moved off
the footprints by ``--grid-offset-vox`` (default 0.37, 0.21 voxels) for every geometry. They
take the per-lenslet matrix-free projector (:mod:`plenopiv.reconstruction.real_lattice`); a geometry
the reconstruction cannot take stops at the weights stage (before rendering) with the library's
error, recorded as ``refused``. ``--lenslets ROWS COLS`` measures a central patch of the sensor at
the same seeding density and depth (docs/validation/real_arrays.md scales it). Every stage prints
its wall and CPU time and the load average.

Stages, each printed with its wall time and the process's peak resident memory during it:

1. render the pair with the project's ray tracer (cached in ``benchmarks/_cache/``);
2. light field and lattice projector (shared by both exposures);
3. reconstruct A and B (MLOS + ``--iterations`` SMART sweeps, particles); Q of A against
   Gaussian blobs of the camera's resolution cell at the true positions;
4. 3-D PIV of the pair, corrected by the pair's tracks as ``plenopiv run`` does (the tracks'
   time counts in the pair; ``--no-track-correction``: the correlation as it is), then its w
   fitted to continuity (``--no-continuity``: not); gain
   (least-squares slope of measured on true), bias and RMS error per component against the
   flow, in voxels, overall and in three bands of |Z| (``correlation_velocity_*``: the same
   before the correction);
5. the explicit-weight path on a 41 × 61-lenslet patch of the same camera at the same
   seeding density (cropped region): Q with explicit weights and with the lattice projector
   (both SMART), and the time and Q of plain row-action MART with explicit weights, which
   gives the speed-up.

With ``--track``, also 6. the particle tracks of the pair (:mod:`plenopiv.tracking`): the time
they add (bundle fits of A and B, forward refinement, matching; the light field of the
reconstruction reused), tracked fraction, wrong matches and the displacement error of the
tracks.

``--solver fista|sirt|cgls`` reconstructs with a least-squares solver instead of SMART
(docs/validation/solvers.md, at full size). With ``--json`` the last line is one JSON
object: ``reconstruct_seconds`` (per volume),
``reconstruct_peak_gb``, ``q``, ``pair_seconds`` (two volumes + PIV, the weights included),
``velocity_gain``, ``velocity_bias_vox`` and ``velocity_rms_vox`` (u, v, w),
``velocity_by_depth`` (the same per band of |Z|), and the patch figures. The reconstruction
takes the library's default lateral subdivision (``--lateral-subdivision``): 2 x 2 on every
array; 3 x 3 would exceed the working voxels the defaults allow
(:data:`plenopiv.reconstruction.choose.MAX_AUTO_WORKING_VOXELS`).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import math
import os
import resource
import sys
import threading
import time
from pathlib import Path

import numpy as np

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies import field_quality as fq
from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.errors import ReconstructionError
from plenopiv.particles.settings import ParticleSettings
from plenopiv.piv import PIVSettings
from plenopiv.products.files import atomic_path
from plenopiv.products.jsonio import dumps
from plenopiv.reconstruction.build import cached_weights, weights_for
from plenopiv.reconstruction.mart import reconstruction_quality
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.subdivision import working_factors
from plenopiv.resources import own_process_memory
from plenopiv.synthetic.seeding import SeedingBox, simulate_pair
from plenopiv.synthetic.truth import gaussian_truth_volume
from plenopiv.workflow.accuracy import gain_bias_rms
from plenopiv.workflow.pair import correlate
from plenopiv.workflow.volume import reconstruct_volume
from plenopiv.workflow.vortex_case import VortexCase, _flow, aligned_grid, compare_with_truth

CACHE = Path(__file__).parent / "_cache"


# ---- measuring ---------------------------------------------------------------------------------


def _rss_gb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024 / 1e9
    return float("nan")


@contextlib.contextmanager
def stage(name: str, log: dict):
    """Time a stage and sample the process's resident memory every 10 ms while it runs."""
    peak = [_rss_gb()]
    done = threading.Event()

    def sample():
        while not done.wait(0.01):
            peak[0] = max(peak[0], _rss_gb())

    th = threading.Thread(target=sample, daemon=True)
    th.start()
    t0 = time.perf_counter()
    c0 = time.process_time()
    u0 = resource.getrusage(resource.RUSAGE_SELF)
    try:
        yield
    finally:
        seconds = time.perf_counter() - t0
        cpu = time.process_time() - c0
        u1 = resource.getrusage(resource.RUSAGE_SELF)
        user, system = u1.ru_utime - u0.ru_utime, u1.ru_stime - u0.ru_stime
        faults = u1.ru_minflt - u0.ru_minflt
        done.set()
        th.join()
        peak[0] = max(peak[0], _rss_gb())
        load = os.getloadavg()[0]
        log[name] = {"seconds": round(seconds, 2), "cpu_seconds": round(cpu, 2),
                     "user_seconds": round(user, 2), "system_seconds": round(system, 2),
                     "page_faults": faults, "peak_gb": round(peak[0], 2),
                     "load": round(load, 1)}
        print(f"{name:<28s} {seconds:8.1f} s  cpu {cpu:8.1f} s (user {user:.1f}, system "
              f"{system:.1f}, {faults} faults)   peak {peak[0]:6.2f} GB   load {load:.1f}",
              file=sys.stderr, flush=True)


# ---- the case ----------------------------------------------------------------------------------


#: Lenslet arrays of ``--geometry``: the preset's (axis-aligned), a mounted square array
#: (γ = 2 mrad, offset (3, -2) µm) and a hexagonal one (222 × 287 lenslets, γ = 1 mrad).
GEOMETRIES = {"aligned": {},
              "rotated": {"rotation": 2e-3, "offset": (3e-6, -2e-6)},
              "hexagonal": {"grid": "hexagonal", "rows": 222, "cols": 287, "rotation": 1e-3}}


def full_case(args) -> tuple:
    cam = load_camera("auburn_135mm")
    geo = GEOMETRIES[args.geometry]
    if geo:
        cam = cam.replace(microlens_array=dataclasses.replace(cam.microlens_array, **geo))
    if args.lenslets:
        rows, cols = args.lenslets
        rows = int(round(rows * cam.microlens_array.rows / 193))   # hexagonal: 222 rows
        cam = cam.patch(rows, cols, margin_px=12)
    cal = Calibration.from_camera(cam)
    eff = cal.effective_camera
    b = eff.microlens_array.pitch * eff.object_distance / eff.image_distance
    case = VortexCase(flow="oseen", camera="auburn_135mm", depth=99.5 * b,
                      max_displacement=args.displacement_vox * b, lateral_fill=1.0,
                      voxel_depth_factor=args.voxel_depth_factor, dt=1e-3, seed=args.seed)
    grid = aligned_grid(eff, case)
    # voxels not aligned with the footprints: the grid moved by a fraction of a voxel
    shift = np.array([*args.grid_offset_vox, 0.0]) * np.array(grid.voxel)
    grid = VolumeGrid(tuple(np.array(grid.origin) + shift), grid.voxel, grid.shape)
    box = SeedingBox(tuple(grid.bounds[0] * 0.95), tuple(grid.bounds[1] * 0.95),
                     (-0.8 * case.depth, 0.8 * case.depth))
    return cam, cal, case, grid, box, _flow(case, box)


def render_pair(cam, flow, case, box, n, rays):
    key = hashlib.sha256(dumps([cam.to_dict(), repr(flow), case.dt, box.x, box.y, box.z,
                                     n, rays, case.seed], sort_keys=True,
                                    default=str).encode()).hexdigest()[:16]
    path = CACHE / f"full_pair_{key}.npz"
    if path.exists():
        d = np.load(path)
        return d["a"], d["b"], d["pa"], d["pb"], True
    pair = simulate_pair(cam, flow, dt=case.dt, box=box, n_particles=n,
                         rng=np.random.default_rng(case.seed), rays_per_particle=rays)
    CACHE.mkdir(exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, a=pair.image_a.astype(np.float32), b=pair.image_b.astype(np.float32),
                 pa=pair.positions_a, pb=pair.positions_b)
    return pair.image_a, pair.image_b, pair.positions_a, pair.positions_b, False


def q_breakdown(result, truth, positions, cal, grid, image, settings) -> dict:
    """Where the full-size Q is lost: Q within the patch study's depth (±16 footprints) and
    beyond, in the lateral interior, detection and ghost rates (matches inside the
    resolution cell, interior only), and the share of lit pixels (image density)."""
    eff = cal.effective_camera
    b = fq.footprint(eff)
    lat, dep = fq.resolution_cell(eff)
    vol = result.volume
    near = np.abs(grid.z) <= 16 * b
    out = {"q_depth_within_16b": reconstruction_quality(vol[near], truth[near]),
           "q_depth_beyond_16b": reconstruction_quality(vol[~near], truth[~near])}
    region = fq.Region(grid, fq.interior_margin(eff, depth=float(np.abs(positions[:, 2]).max())))
    sl = region.slices
    out["q_interior"] = reconstruction_quality(vol[sl], truth[sl])
    row = fq.score(result, positions, tolerance=(lat, lat, dep),
                   sigmas={"cell": fq.cell_sigma(grid, eff)}, region=region)
    out.update(detection=row["detection_rate"], ghosts=row["ghost_rate"],
               resolution_cell_mm=[lat * 1e3, dep * 1e3])
    if result.particle_centroid_effective is not None:      # positions from the light field
        volume_row = fq.score(dataclasses.replace(
            result, particle_position_effective=result.particle_centroid_effective),
            positions, tolerance=(lat, lat, dep), sigmas={"cell": fq.cell_sigma(grid, eff)},
            region=region)
        out.update(detection_volume_centroids=volume_row["detection_rate"],
                   ghosts_volume_centroids=volume_row["ghost_rate"])
    out["lit_pixel_share"] = float(np.mean(image > settings.pixel_threshold * image.max()))
    return out


def patch_study(args, log: dict) -> dict:
    """Explicit weights against the lattice projector on a 41 × 61-lenslet patch."""
    cam = fq.study_camera(41, 61, preset="auburn_135mm")
    cal = Calibration.from_camera(cam)
    b = fq.footprint(cam)
    grid = fq.study_grid(cam, depth=20 * b, depth_voxel=b)
    rng = np.random.default_rng(args.seed + 1)
    per_lenslet = args.particles / (193 * 287)
    box = SeedingBox(tuple(grid.bounds[0] * 0.95), tuple(grid.bounds[1] * 0.95),
                     (-16 * b, 16 * b))
    n = int(round(per_lenslet * 41 * 61 * 0.95 ** 2))
    pos = np.column_stack([rng.uniform(*box.x, n), rng.uniform(*box.y, n),
                           rng.uniform(*box.z, n)])
    img = fq.render(cam, pos, seed=args.seed)
    sigma = fq.cell_sigma(grid, cam)
    truth = gaussian_truth_volume(grid, pos, sigma_vox=sigma)
    out = {"lenslets": [41, 61], "grid": list(grid.shape), "particles": n,
           "lit_pixel_share": float(np.mean(img > 0.003 * img.max()))}
    smart = ReconstructionSettings(iterations=args.iterations)
    for kind in ("sparse", "lattice"):
        with stage(f"patch {kind} SMART", log):
            t0 = time.perf_counter()
            w, _ = cached_weights(cal, grid, cache_dir=None, projector=kind)
            t_w = time.perf_counter() - t0
            r = reconstruct_volume(cal, img, grid, settings=smart, weights=w)
        out[f"{kind}_smart"] = {"q": reconstruction_quality(r.volume, truth),
                                "weights_s": t_w, "reconstruct_s": log[f"patch {kind} SMART"]
                                ["seconds"], "nnz": w.nnz}
    mu = 0.03                       # row-action MART's default relaxation
    name = f"patch row-action MART mu={mu}"
    with stage(name, log):
        w, _ = cached_weights(cal, grid, cache_dir=None, projector="sparse")
        r = reconstruct_volume(cal, img, grid, weights=w, settings=ReconstructionSettings(
            method="mart", relaxation=mu, iterations=args.iterations))
    out["mart"] = {"relaxation": mu, "q": reconstruction_quality(r.volume, truth),
                   "seconds": log[name]["seconds"]}
    out["speedup_lattice_smart_vs_mart"] = (out["mart"]["seconds"]
                                            / out["lattice_smart"]["reconstruct_s"])
    return out


def pair_tracks(cal, ia, ib, vols, vec, settings, log, lf=None):
    """The pair's tracks (bundle fits, refinement, matching; the light field ``lf`` of the
    reconstruction's weights reused), timed as the stage "track"."""
    from plenopiv.workflow.tracking import track_pair

    with stage("track", log):
        return track_pair(cal, ia, ib, vols["A"], vols["B"], vec, f_number=settings.f_number,
                          min_lit=settings.min_lit, lf=lf)


def track_study(cal, tracks, vols, pa, pb, grid, settings, log) -> dict:
    """The time the tracks add to the pair and their errors against the truth."""
    from pipelines.studies.tracking import associate_tracks, rms_per_axis
    from plenopiv.camera.resolution import resolution_cell

    lat, dep = resolution_cell(cal.effective_camera, settings.f_number)
    scale = np.array([lat, lat, dep * vols["A"].correction.scale])
    ja = associate_tracks(tracks.position_a, tracks.position_b, pa, pb, scale)
    ok = ja >= 0
    vox = np.asarray(grid.voxel)
    true = (pb[ja[ok]] - pa[ja[ok]]) / vox
    measured = tracks.displacement[ok] / vox
    err = measured - true
    fit = gain_bias_rms(measured.T, true.T)
    return {"gain": [round(v, 4) for v in fit["gain"]],
            "bias_vox": [round(v, 4) for v in fit["bias"]],
            "seconds": log["track"]["seconds"], "cpu_seconds": log["track"]["cpu_seconds"],
            "load": log["track"]["load"], "peak_gb": log["track"]["peak_gb"],
            "n_tracks": len(tracks), "tracked_fraction": float(len(np.unique(ja[ok])) / len(pa)),
            "wrong_match_rate": float((~ok).mean()) if len(ok) else None,
            "rms_vox": [round(v, 4) for v in rms_per_axis(err)], "counts": tracks.counts}


def parser() -> argparse.ArgumentParser:
    """The benchmark's command line (also the defaults of ``bench_real_lattice.py``'s case)."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--particles", type=int, default=20000)
    p.add_argument("--rays", type=int, default=2048, help="rays per particle")
    p.add_argument("--iterations", type=int, default=5, help="SMART sweeps after MLOS")
    p.add_argument("--displacement-vox", type=float, default=3.0,
                   help="largest displacement, lateral voxels")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--lateral-subdivision", default="auto",
                   help="[reconstruction] lateral_subdivision: auto (the library default) or "
                        "an int; 1 reconstructs on the footprint voxels themselves")
    p.add_argument("--depth-binning", default="auto",
                   help="[reconstruction] depth_binning: auto (the library default) or an int; "
                        "1 reconstructs on the grid's own depth slices")
    p.add_argument("--skip-patch", action="store_true")
    p.add_argument("--voxel-depth-factor", type=float, default=1.0,
                   help="depth voxel over the lateral one (default 1: cubic voxels); the PIV "
                        "windows keep their depth in millimetres")
    p.add_argument("--no-continuity", action="store_true",
                   help="keep the field's w as correlated (and corrected by the tracks), not "
                        "fitted to continuity ([piv] continuity = false)")
    p.add_argument("--no-track-correction", action="store_true",
                   help="report the correlation field as it is, not corrected by the pair's "
                        "tracks (plenopiv run's [tracking] correct_vectors = false)")
    p.add_argument("--track", action="store_true",
                   help="also track the particles (ray bundles + PIV predictor): added time")
    p.add_argument("--geometry", choices=sorted(GEOMETRIES), default="aligned",
                   help="lenslet array: aligned (the preset), rotated (2 mrad, offset 3, -2 µm), "
                        "hexagonal (222 x 287, 1 mrad)")
    p.add_argument("--grid-offset-vox", type=float, nargs=2, default=(0.37, 0.21),
                   help="lateral shift of the grid off the footprints, voxels (x, y)")
    p.add_argument("--lenslets", type=int, nargs=2, default=None, metavar=("ROWS", "COLS"),
                   help="a central patch of ROWS x COLS lenslets (of the square array's 193 x "
                        "287; hexagonal rows scaled to its 222) at the same seeding density and "
                        "depth, for a measurement that scales to the full sensor")
    p.add_argument("--projector", choices=("auto", "sparse", "lattice"), default="auto",
                   help="[reconstruction] projector; \"lattice\" (matrix-free) keeps a "
                        "--lenslets patch, whose explicit weights would fit, on the projector "
                        "of the full sensor")
    p.add_argument("--solver", choices=("smart", "fista", "sirt", "cgls"), default="smart",
                   help="the default SMART sweeps, or a least-squares solver of "
                        "plenopiv.reconstruction.least_squares on the same rows, ceilings and "
                        "support, for --iterations iterations (the solver study at full size)")
    p.add_argument("--call-times", action="store_true",
                   help="time every call of the per-lenslet projector (forward, back, fused "
                        "SMART sweep) in each volume (benchmarks/bench_real_lattice.py)")
    p.add_argument("--json", action="store_true", help="end with one JSON line")
    return p


def main(argv=None) -> dict:
    args = parser().parse_args(argv)
    own_process_memory()            # as the plenopiv command and batch workers do
    if args.lenslets:
        args.particles = int(round(args.particles * args.lenslets[0] * args.lenslets[1]
                                   / (193 * 287)))
    log: dict = {}

    cam, cal, case, grid, box, flow = full_case(args)
    print(f"grid {grid.shape} (z, y, x), voxel {np.round(np.array(grid.voxel) * 1e3, 4)} mm; "
          f"{args.particles} particles", file=sys.stderr)
    k = args.lateral_subdivision
    kz = args.depth_binning
    settings = ReconstructionSettings(iterations=args.iterations, projector=args.projector,
                                      lateral_subdivision=k if k == "auto" else int(k),
                                      depth_binning=kz if kz == "auto" else int(kz))
    particles = ParticleSettings()
    try:
        with stage("weights (light field)", log):
            w, _ = weights_for(cal, grid, settings)
            _ = w.normalised
    except ReconstructionError as exc:
        result = {"geometry": args.geometry, "refused": str(exc), "stages": log}
        print(dumps(result, default=_json_default))
        return result
    with stage("render pair", log):
        ia, ib, pa, pb, cached = render_pair(cam, flow, case, box, args.particles, args.rays)
    log["render pair"]["cached"] = cached

    print(f"projector: {type(w.projector).__name__}"
          f"{' (matrix-free)' if w.matrix_free else ''}, working grid {w.grid.shape} "
          f"(depth binning, lateral subdivision {working_factors(w.grid, grid)})",
          file=sys.stderr)
    vols = {}
    calls = None
    if args.call_times:
        from bench_real_lattice import CallLog

        calls = CallLog()
        calls.coarse_shape = w.grid.shape
        calls.install()
    for name, img in (("A", ia), ("B", ib)):
        if calls is not None:
            calls.rows.clear()
        with stage(f"reconstruct {name}", log):
            vols[name] = reconstruct_volume(
                cal, img, grid, settings=settings, particles=particles, weights=w,
                solver=None if args.solver == "smart" else args.solver)
        log[f"reconstruct {name}"]["timings"] = {k: round(v, 2) for k, v in
                                                 vols[name].timings.items()}
        print(f"  {log[f'reconstruct {name}']['timings']}", file=sys.stderr)
        if calls is not None:
            log[f"reconstruct {name}"]["projector_calls"] = calls.table()
            print(dumps(calls.table()), file=sys.stderr)
    if calls is not None:
        calls.uninstall()
        calls.last.clear()
    sigma = fq.cell_sigma(grid, cal.effective_camera)
    truth = gaussian_truth_volume(grid, pa, sigma_vox=sigma)
    q = reconstruction_quality(vols["A"].volume, truth)
    breakdown = q_breakdown(vols["A"], truth, pa, cal, grid, ia, settings)
    # the windows keep their physical depth on a grid of deeper voxels
    windows = tuple((max(2, int(round(w / args.voxel_depth_factor))), w, w) for w in (32, 16))
    piv = PIVSettings(windows=windows, overlap=0.5, passes=3)
    with stage("PIV", log):
        vec = correlate(vols["A"], vols["B"], piv)      # displacements (no dt given)
    tracks = None
    if args.track or not args.no_track_correction:
        tracks = pair_tracks(cal, ia, ib, vols, vec, settings, log, lf=w.geometry.light_field)
    correlation_err = compare_with_truth(vec, flow, case.dt, grid, windows[-1])
    err = correlation_err
    if not args.no_track_correction:
        # as plenopiv run does by default ([tracking] correct_vectors)
        from plenopiv.tracking.correction import correct_with_tracks
        from plenopiv.tracking.settings import PRIOR_TRACKS

        vec, _ = correct_with_tracks(vec, tracks, prior_tracks=PRIOR_TRACKS)
        err = compare_with_truth(vec, flow, case.dt, grid, windows[-1])
    before_continuity, continuity = err, None
    if not args.no_continuity:
        # as plenopiv run does by default ([piv] continuity), on this field's correlation
        # uncertainties (run's default adds the chain's measured response)
        from plenopiv.workflow.correlation import fitted_to_continuity

        with stage("continuity", log):
            vec, continuity = fitted_to_continuity(vec, piv)
        err = compare_with_truth(vec, flow, case.dt, grid, windows[-1])
    rec_s = [log[f"reconstruct {n}"]["seconds"] for n in "AB"]
    result = {
        "camera": "auburn_135mm", "grid_shape": list(grid.shape),
        "particles": args.particles, "iterations": args.iterations, "solver": args.solver,
        "projector": type(w.projector).__name__,
        "reconstruct_cpu_seconds": round(float(np.mean(
            [log[f"reconstruct {n}"]["cpu_seconds"] for n in "AB"])), 2),
        "weights_seconds": log["weights (light field)"]["seconds"],
        "reconstruct_seconds": round(float(np.mean(rec_s)), 2),
        "reconstruct_peak_gb": max(log[f"reconstruct {n}"]["peak_gb"] for n in "AB"),
        "q": round(q, 4),
        "pair_seconds": round(log["weights (light field)"]["seconds"] + sum(rec_s)
                              + log["PIV"]["seconds"]
                              + sum(log[k]["seconds"] for k in ("track", "continuity")
                                    if k in log), 2),
        "track_correction": not args.no_track_correction,
        "piv_seconds": log["PIV"]["seconds"],
        "lateral_subdivision": list(working_factors(w.grid, grid)[1:]),
        "depth_binning": working_factors(w.grid, grid)[0],
        "velocity_rms_vox": [round(v, 4) for v in err["rms_vox"]],
        "velocity_bias_vox": [round(v, 4) for v in err["bias_vox"]],
        "velocity_gain": [round(v, 4) for v in err["gain"]],
        "velocity_by_depth": [{"abs_z_mm": [round(v, 2) for v in b["abs_z_mm"]],
                               **{k: [round(v, 4) for v in b[k]]
                                  for k in ("gain", "bias_vox", "rms_vox")}}
                              for b in err["by_depth"]],
        "valid_fraction": err.get("valid_fraction"),
        "continuity": continuity,
        "before_continuity_velocity_rms_vox": [round(v, 4)
                                               for v in before_continuity["rms_vox"]],
        "before_continuity_velocity_gain": [round(v, 4) for v in before_continuity["gain"]],
        "correlation_velocity_rms_vox": [round(v, 4) for v in correlation_err["rms_vox"]],
        "correlation_velocity_gain": [round(v, 4) for v in correlation_err["gain"]],
        "particles_found_a": len(vols["A"].particle_position),
        "geometry": args.geometry, "grid_offset_vox": list(args.grid_offset_vox),
        "lenslets": args.lenslets, "rays": int(w.pixel.shape[0]),
        **breakdown,
        "stages": log,
    }
    if args.track:
        result["track"] = track_study(cal, tracks, vols, pa, pb, grid, settings, log)
    if not args.skip_patch:
        result["patch"] = patch_study(args, log)
    if args.json:
        print(dumps(result, default=_json_default))
    else:
        print(dumps(result, indent=1, default=_json_default))
    return result


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, float) and math.isnan(o):
        return None
    return str(o)


if __name__ == "__main__":
    main()
