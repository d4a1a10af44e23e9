"""Solver study: SMART against non-negative least squares (FISTA, SIRT, clipped CGLS).

On one set of weights (a patch of the 50 mm camera, the grid and scoring of
:mod:`pipelines.studies.field_quality`) the same ray-traced images with photon noise, at
several densities and seeds, are reconstructed by every solver and scored: Q against the
resolution-cell blobs, detection, ghosts and position error of the particles found, the
velocity error of a pair (a second exposure moved uniformly by :data:`PAIR_SHIFT_VOX`),
seconds. The best iteration count of FISTA and CGLS is chosen on the first seed (Q at every
iteration, from the callback) and then run on every seed, so the later seeds are held out.
``subdivision="auto"`` reconstructs on the working grid the defaults choose and scores the
volume as it is returned (:func:`~pipelines.studies.field_quality.study_setup`).
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from pipelines.studies.field_quality import (
    cell_sigma,
    render,
    score,
    seed_field,
    study_setup,
)
from plenopiv.errors import PlenopivError, ReconstructionError
from plenopiv.piv import correlate_volumes
from plenopiv.piv.settings import PIVSettings
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.solve import solve_volume
from plenopiv.reconstruction.subdivision import to_volume_grid
from plenopiv.synthetic.truth import gaussian_truth_volume
from plenopiv.workflow.volume import reconstruct_volume

#: Densities, particles per lenslet.
DENSITIES = (0.1, 0.2, 0.3, 0.5)
#: The solvers at 10 iterations: name -> (solver or None for the default SMART, options).
SOLVERS = {
    "smart (default)": (None, {}),
    "fista": ("fista", {}),
    "sirt": ("sirt", {}),
    "cgls (line of sight)": ("cgls", {}),
    "cgls (textbook)": ("cgls", {"support": None}),
}
#: Solvers whose best iteration count is searched, up to this many iterations.
TUNED = ("fista", "cgls (line of sight)", "cgls (textbook)")
MAX_ITERATIONS = 40


def q_trace(setup, image, positions, solver, options, iterations: int) -> list[float]:
    """Q (cell blobs, evaluated region) after each iteration of one solver."""
    sigma = cell_sigma(setup.grid, setup.camera)
    s = setup.region.slices
    truth = gaussian_truth_volume(setup.grid, positions, sigma_vox=sigma)[s].astype(np.float64)
    tt = float(np.sum(truth * truth))
    trace = []

    def record(_iteration, volume):
        if setup.weights.grid != setup.grid:        # the working grid's volume as returned
            volume = to_volume_grid(volume, setup.weights.grid, setup.grid)
        e = np.asarray(volume, np.float64).reshape(setup.grid.shape)[s]
        ee = float(np.sum(e * e))
        trace.append(float(np.sum(e * truth)) / np.sqrt(ee * tt) if ee > 0 else 0.0)

    settings = ReconstructionSettings(iterations=iterations)
    solve_volume(setup.weights, np.asarray(image, np.float64), settings, solver=solver,
                 solver_options=options, callback=record)
    return trace


def run_solver(setup, image, positions, solver, options, iterations: int,
               pair=None) -> dict:
    """Reconstruct one image with one solver and score it (:func:`score`) with its seconds.

    ``pair``: ``(image B, positions B)`` of :func:`second_exposure`; B is reconstructed with
    the same solver and the pair's velocity error added (:func:`pair_error`).
    """
    sigmas = {"cell": cell_sigma(setup.grid, setup.camera)}
    settings = ReconstructionSettings(iterations=iterations)
    t0 = time.perf_counter()

    def reconstruct(img):
        return reconstruct_volume(setup.calibration, img, setup.grid, settings=settings,
                                  particles=setup.particles, weights=setup.weights,
                                  solver=solver, solver_options=options)
    try:
        res = reconstruct(image)
    except ReconstructionError as exc:
        return {"error": str(exc), "time_s": time.perf_counter() - t0}
    row = {"time_s": res.timings["mart_s"], "total_s": time.perf_counter() - t0}
    row.update(score(res, positions, tolerance=setup.tolerance, sigmas=sigmas,
                     region=setup.region))
    if pair is not None:
        try:
            row.update(pair_error(setup, res.volume, reconstruct(pair[0]).volume))
        except PlenopivError as exc:
            row["pair_error"] = str(exc)
    return row


#: The pair's uniform displacement, voxels of the study grid (x, y, z): a fraction of a
#: lateral voxel and of the depth cell, so that neither component is a whole voxel.
PAIR_SHIFT_VOX = (0.6, -0.4, 1.2)
#: The pair's PIV: windows (z, y, x voxels) that give several vectors across the patch.
PAIR_PIV = PIVSettings(windows=((24, 12, 12), (16, 8, 8)), passes=3, overlap=0.5,
                       uncertainty="correlation", min_particles_per_window=1)


def second_exposure(setup, positions, density: float, seed: int):
    """``(noisy image, positions)`` of the pair's second exposure: all moved by the shift."""
    moved = positions + np.asarray(PAIR_SHIFT_VOX) * np.asarray(setup.grid.voxel)
    rng = np.random.default_rng([seed, int(round(density * 1000)), 1])
    return render(setup.camera, moved, seed=seed + 1, noise=True, rng=rng), moved


def pair_error(setup, volume_a, volume_b) -> dict:
    """The pair's velocity error against the uniform shift, voxels (x, y, z).

    ``velocity_rms_vox`` and ``velocity_bias_vox`` over the valid vectors whose window
    centres lie in the evaluated region; ``velocity_valid`` their share of those vectors.
    """
    field = correlate_volumes(volume_a, volume_b, setup.grid, settings=PAIR_PIV)
    zz, yy, xx = np.meshgrid(field.z, field.y, field.x, indexing="ij")
    inside = setup.region.contains(np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1))
    inside = inside.reshape(field.u.shape)
    use = inside & field.valid
    if not use.any():
        return {"pair_error": "no valid vector inside the region"}
    vox = np.asarray(setup.grid.voxel)
    err = np.stack([(c[use] / vox[i]) - PAIR_SHIFT_VOX[i]
                    for i, c in enumerate((field.u, field.v, field.w))], axis=1)
    return {"velocity_rms_vox": np.sqrt(np.mean(err ** 2, axis=0)).tolist(),
            "velocity_bias_vox": err.mean(axis=0).tolist(),
            "velocity_valid": float(use.sum() / inside.sum())}


def fields(setup, density: float, seed: int):
    """``(positions, noisy image)`` of one density and seed."""
    rng = np.random.default_rng([seed, int(round(density * 1000))])
    pos = seed_field(setup.grid, setup.camera, density, rng)
    return pos, render(setup.camera, pos, seed=seed, noise=True, rng=rng)


def study(rows: int, cols: int, seeds, densities=DENSITIES, progress=print, *,
          preset: str = "auburn_50mm", subdivision: int | str = 1) -> dict:
    """Every solver, density and seed: the rows of the study and the tuned iteration counts.

    ``preset``: the camera a patch is cut from (the 16 MP ``auburn_135mm``'s lenslets and
    optics at a patch's size, for the full camera).
    """
    setup = study_setup(rows, cols, preset=preset, subdivision=subdivision)
    out = {"camera": _label(preset, rows, cols, subdivision),
           "grid_shape": list(setup.grid.shape), "seeds": list(seeds),
           "densities": list(densities), "rows": [], "best_iterations": {}, "traces": {}}
    for density in densities:
        images = [fields(setup, density, seed) for seed in seeds]
        pos0, img0 = images[0]
        for name in TUNED:
            solver, options = SOLVERS[name]
            trace = q_trace(setup, img0, pos0, solver, options, MAX_ITERATIONS)
            best = int(np.argmax(trace)) + 1
            out["traces"][f"{name} @ {density}"] = trace
            out["best_iterations"][f"{name} @ {density}"] = best
            progress(f"{density} {name}: best {best} it, Q {max(trace):.3f}")
        for seed, (pos, img) in zip(seeds, images, strict=True):
            pair = second_exposure(setup, pos, density, seed)
            cases = [(name, *SOLVERS[name], 10) for name in SOLVERS]
            cases += [(f"{name} (best)", *SOLVERS[name],
                       out["best_iterations"][f"{name} @ {density}"]) for name in TUNED]
            for name, solver, options, iterations in cases:
                row = run_solver(setup, img, pos, solver, options, iterations, pair=pair)
                row.update(solver=name, density_ppl=density, seed=seed, iterations=iterations,
                           held_out=seed != seeds[0])
                out["rows"].append(row)
                progress(f"{density} seed {seed} {name} {iterations} it: "
                         f"Q {row.get('q', {}).get('cell', float('nan')):.3f} "
                         f"det {row.get('detection_rate', float('nan')):.3f} "
                         f"ghost {row.get('ghost_rate', float('nan')):.3f} "
                         f"velocity rms {np.round(row.get('velocity_rms_vox', []), 3)} "
                         f"{row['time_s']:.2f} s")
    return out


#: The equal-cost comparison: SMART and FISTA at the same number of iterations.
EQUAL_COST_ITERATIONS = 40
#: Fractions of λ_max of FISTA's L1 term, tuned on the first seed.
L1_FRACTIONS = (0.003, 0.01, 0.03)


def equal_cost_study(rows: int, cols: int, seeds, densities=DENSITIES, progress=print, *,
                     preset: str = "auburn_50mm", subdivision: int | str = 1) -> dict:
    """SMART and FISTA (with and without the L1 term) at :data:`EQUAL_COST_ITERATIONS`.

    The L1 fraction is chosen per density on the first seed (largest Q at the last
    iteration), and every solver is scored on the other seeds only.
    """
    setup = study_setup(rows, cols, preset=preset, subdivision=subdivision)
    n = EQUAL_COST_ITERATIONS
    out = {"camera": _label(preset, rows, cols, subdivision), "iterations": n,
           "seeds": list(seeds[1:]), "tuning_seed": seeds[0], "densities": list(densities),
           "rows": [], "l1": {}}
    for density in densities:
        pos0, img0 = fields(setup, density, seeds[0])
        q = {f: q_trace(setup, img0, pos0, "fista", {"l1": f}, n)[-1] for f in L1_FRACTIONS}
        best = max(q, key=q.get)
        out["l1"][str(density)] = {"q_by_fraction": q, "chosen": best}
        progress(f"{density}: L1 fractions {q}, chosen {best}")
        cases = [("smart (default)", None, {}), ("fista", "fista", {}),
                 (f"fista, l1 {best:g}", "fista", {"l1": best})]
        for seed in seeds[1:]:
            pos, img = fields(setup, density, seed)
            for name, solver, options in cases:
                row = run_solver(setup, img, pos, solver, options, n)
                row.update(solver=name, density_ppl=density, seed=seed, iterations=n,
                           held_out=True)
                out["rows"].append(row)
                progress(f"{density} seed {seed} {name} {n} it: Q {row['q']['cell']:.3f} "
                         f"det {row['detection_rate']:.3f} ghost {row['ghost_rate']:.3f} "
                         f"{row['time_s']:.2f} s")
    return out


#: FISTA as the first guess of SMART: (name, FISTA iterations, SMART sweeps).
HYBRIDS = (("smart (default)", 10, 0), ("fista 5 + smart 5", 5, 5),
           ("fista 20 + smart 5", 20, 5))


def hybrid_study(rows: int, cols: int, seeds, densities=DENSITIES, progress=print, *,
                 preset: str = "auburn_50mm", subdivision: int | str = 1) -> dict:
    """FISTA's volume as SMART's first guess (:data:`HYBRIDS`), on the held-out seeds."""
    setup = study_setup(rows, cols, preset=preset, subdivision=subdivision)
    out = {"camera": _label(preset, rows, cols, subdivision), "seeds": list(seeds[1:]),
           "densities": list(densities), "rows": []}
    for density in densities:
        for seed in seeds[1:]:
            pos, img = fields(setup, density, seed)
            for name, fista, sweeps in HYBRIDS:
                args = (None, {}, 10) if not sweeps else \
                    ("fista", {"smart_sweeps": sweeps}, fista)
                row = run_solver(setup, img, pos, *args)
                row.update(solver=name, density_ppl=density, seed=seed,
                           iterations=fista + sweeps, held_out=True)
                out["rows"].append(row)
                progress(f"{density} seed {seed} {name}: Q {row['q']['cell']:.3f} "
                         f"det {row['detection_rate']:.3f} ghost {row['ghost_rate']:.3f} "
                         f"{row['time_s']:.2f} s")
    return out


def _label(preset: str, rows: int, cols: int, subdivision: int | str) -> str:
    """The study's camera and grid in words."""
    cut = (", footprint voxels on the default working grid" if subdivision == "auto"
           else f", voxels a footprint / {subdivision}" if subdivision > 1 else "")
    return f"{preset} patch {rows} x {cols} lenslets{cut}"


def _velocity(rows) -> str:
    """Mean velocity rms (x, y, z voxels) of the rows that have one, or a dash."""
    v = [r["velocity_rms_vox"] for r in rows if "velocity_rms_vox" in r]
    return ", ".join(f"{x:.3f}" for x in np.mean(v, axis=0)) if v else "–"


def _cell(values) -> str:
    v = np.asarray([x for x in values if x == x], float)
    if not len(v):
        return "–"
    return f"{v.mean():.3f} ± {v.std():.3f}" if len(v) > 1 else f"{v[0]:.3f}"


def tables(result: dict, *, held_out_only: bool = False) -> str:
    """Markdown: one table per density, mean ± standard deviation over the seeds."""
    lines = []
    for density in result["densities"]:
        lines += [f"### {density} particles per lenslet", "",
                  "| solver | it | Q | detection | ghosts | rms x, y, z (µm) "
                  "| velocity rms x, y, z (vox) | velocity bias z (vox) | s |",
                  "|---|---|---|---|---|---|---|---|---|"]
        rows = [r for r in result["rows"] if r["density_ppl"] == density and "error" not in r
                and (r["held_out"] or not held_out_only)]
        for name in dict.fromkeys(r["solver"] for r in rows):
            mine = [r for r in rows if r["solver"] == name]
            rms_m = np.array([r["rms_m"] for r in mine], float)    # a JSON null is NaN
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)     # no particle: NaN
                rms = np.nanmean(rms_m, axis=0) * 1e6
            lines.append(
                f"| {name} | {mine[0]['iterations']} | {_cell(r['q']['cell'] for r in mine)} "
                f"| {_cell(r['detection_rate'] for r in mine)} "
                f"| {_cell(r['ghost_rate'] for r in mine)} "
                f"| {rms[0]:.0f}, {rms[1]:.0f}, {rms[2]:.0f} | {_velocity(mine)} "
                f"| {_cell(r['velocity_bias_vox'][2] for r in mine if 'velocity_bias_vox' in r)} "
                f"| {_cell(r['time_s'] for r in mine)} |")
        lines.append("")
    return "\n".join(lines)
