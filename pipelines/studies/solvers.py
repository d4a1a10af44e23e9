"""Solver study: SMART against non-negative least squares (FISTA, SIRT, clipped CGLS).

On one set of weights (a patch of the 50 mm camera, the grid and scoring of
:mod:`pipelines.studies.field_quality`) the same ray-traced images with photon noise, at
several densities and seeds, are reconstructed by every solver and scored: Q against the
resolution-cell blobs, detection, ghosts and position error of the particles found, seconds.
The best iteration count of FISTA and CGLS is chosen on the first seed (Q at every iteration,
from the callback) and then run on every seed, so the later seeds are held out.
"""

from __future__ import annotations

import time

import numpy as np

from pipelines.studies.field_quality import (
    cell_sigma,
    render,
    score,
    seed_field,
    study_setup,
)
from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.solve import solve_volume
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
        e = np.asarray(volume, np.float64).reshape(setup.grid.shape)[s]
        ee = float(np.sum(e * e))
        trace.append(float(np.sum(e * truth)) / np.sqrt(ee * tt) if ee > 0 else 0.0)

    settings = ReconstructionSettings(iterations=iterations)
    solve_volume(setup.weights, np.asarray(image, np.float64), settings, solver=solver,
                 solver_options=options, callback=record)
    return trace


def run_solver(setup, image, positions, solver, options, iterations: int) -> dict:
    """Reconstruct one image with one solver and score it (:func:`score`) with its seconds."""
    sigmas = {"cell": cell_sigma(setup.grid, setup.camera)}
    settings = ReconstructionSettings(iterations=iterations)
    t0 = time.perf_counter()
    try:
        res = reconstruct_volume(setup.calibration, image, setup.grid, settings=settings,
                                 particles=setup.particles, weights=setup.weights,
                                 solver=solver, solver_options=options)
    except ReconstructionError as exc:
        return {"error": str(exc), "time_s": time.perf_counter() - t0}
    row = {"time_s": res.timings["mart_s"], "total_s": time.perf_counter() - t0}
    row.update(score(res, positions, tolerance=setup.tolerance, sigmas=sigmas,
                     region=setup.region))
    return row


def fields(setup, density: float, seed: int):
    """``(positions, noisy image)`` of one density and seed."""
    rng = np.random.default_rng([seed, int(round(density * 1000))])
    pos = seed_field(setup.grid, setup.camera, density, rng)
    return pos, render(setup.camera, pos, seed=seed, noise=True, rng=rng)


def study(rows: int, cols: int, seeds, densities=DENSITIES, progress=print, *,
          preset: str = "auburn_50mm") -> dict:
    """Every solver, density and seed: the rows of the study and the tuned iteration counts.

    ``preset``: the camera a patch is cut from (the 16 MP ``auburn_135mm``'s lenslets and
    optics at a patch's size, for the full camera).
    """
    setup = study_setup(rows, cols, preset=preset)
    out = {"camera": f"{preset} patch {rows} x {cols} lenslets",
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
            cases = [(name, *SOLVERS[name], 10) for name in SOLVERS]
            cases += [(f"{name} (best)", *SOLVERS[name],
                       out["best_iterations"][f"{name} @ {density}"]) for name in TUNED]
            for name, solver, options, iterations in cases:
                row = run_solver(setup, img, pos, solver, options, iterations)
                row.update(solver=name, density_ppl=density, seed=seed, iterations=iterations,
                           held_out=seed != seeds[0])
                out["rows"].append(row)
                progress(f"{density} seed {seed} {name} {iterations} it: "
                         f"Q {row.get('q', {}).get('cell', float('nan')):.3f} "
                         f"det {row.get('detection_rate', float('nan')):.3f} "
                         f"ghost {row.get('ghost_rate', float('nan')):.3f} "
                         f"{row['time_s']:.2f} s")
    return out


#: The equal-cost comparison: SMART and FISTA at the same number of iterations.
EQUAL_COST_ITERATIONS = 40
#: Fractions of λ_max of FISTA's L1 term, tuned on the first seed.
L1_FRACTIONS = (0.003, 0.01, 0.03)


def equal_cost_study(rows: int, cols: int, seeds, densities=DENSITIES, progress=print, *,
                     preset: str = "auburn_50mm") -> dict:
    """SMART and FISTA (with and without the L1 term) at :data:`EQUAL_COST_ITERATIONS`.

    The L1 fraction is chosen per density on the first seed (largest Q at the last
    iteration), and every solver is scored on the other seeds only.
    """
    setup = study_setup(rows, cols, preset=preset)
    n = EQUAL_COST_ITERATIONS
    out = {"camera": f"{preset} patch {rows} x {cols} lenslets", "iterations": n,
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
                 preset: str = "auburn_50mm") -> dict:
    """FISTA's volume as SMART's first guess (:data:`HYBRIDS`), on the held-out seeds."""
    setup = study_setup(rows, cols, preset=preset)
    out = {"camera": f"{preset} patch {rows} x {cols} lenslets", "seeds": list(seeds[1:]),
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
                  "| solver | it | Q | detection | ghosts | rms x, y, z (µm) | s |",
                  "|---|---|---|---|---|---|---|"]
        rows = [r for r in result["rows"] if r["density_ppl"] == density and "error" not in r
                and (r["held_out"] or not held_out_only)]
        for name in dict.fromkeys(r["solver"] for r in rows):
            mine = [r for r in rows if r["solver"] == name]
            rms = np.nanmean([r["rms_m"] for r in mine], axis=0) * 1e6
            lines.append(
                f"| {name} | {mine[0]['iterations']} | {_cell(r['q']['cell'] for r in mine)} "
                f"| {_cell(r['detection_rate'] for r in mine)} "
                f"| {_cell(r['ghost_rate'] for r in mine)} "
                f"| {rms[0]:.0f}, {rms[1]:.0f}, {rms[2]:.0f} "
                f"| {_cell(r['time_s'] for r in mine)} |")
        lines.append("")
    return "\n".join(lines)
