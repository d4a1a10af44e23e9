"""Report of the tracking study: ``tracking.json``, ``tracking.md`` and figures.

Runs :mod:`pipelines.studies.tracking` and writes its numbers (I/O only).

``python pipelines/validate_tracking.py --out docs/validation``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pipelines.studies.output import write_json, write_text
from pipelines.studies.tracking import measure_case, measure_single_particles
from plenopiv.workflow.vortex_case import VortexCase

#: Seeding densities of the sweep, particles per lenslet.
DENSITIES = (0.05, 0.1, 0.15, 0.2, 0.3)
#: The issue's targets at 0.15 particles per lenslet.
TARGET = {"tracked": 0.5, "wrong": 0.02, "lateral_vox": 0.1, "depth_vox": 0.4,
          "depth_goal_vox": 0.15}
#: Depths of the single-particle series (thesis §5.1), metres.
SINGLE_DEPTHS = np.round(np.arange(-10, 11) * 1e-3, 12)


def run(out: str | Path, *, densities=DENSITIES, seeds=(1,), extra_seeds=(2, 3),
        single_depths=SINGLE_DEPTHS, progress=print) -> dict:
    """Measure and write the report; returns the paths and the run time."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = []
    for flow in ("oseen", "hill"):
        for ppl in densities:
            for seed in seeds + (extra_seeds if ppl == 0.15 else ()):
                r = measure_case(VortexCase(flow=flow, particles_per_lenslet=ppl, seed=seed))
                rows.append(r)
                progress(f"{flow} {ppl} seed {seed}: tracked {r['tracked_fraction']:.2f}, "
                         f"wrong {r['wrong_match_rate']:.3f}, rms {np.round(r['track_rms_vox'], 3)}"
                         f" vs PIV {np.round(r['piv_grid_rms_vox'], 3)}")
    single = measure_single_particles(single_depths)
    progress(f"single particles: rms mm {single['rms_mm']}")
    result = {"cases": rows, "single": _jsonable(single), "target": TARGET,
              "seconds": round(time.perf_counter() - t0, 1)}
    write_json(out / "tracking.json", result, default=str)
    figs = _figures(result, out)
    write_text(out / "tracking.md", markdown(result, [f.name for f in figs]))
    return {"json": str(out / "tracking.json"), "markdown": str(out / "tracking.md"),
            "figures": [str(f) for f in figs], "seconds": result["seconds"]}


def _jsonable(d: dict) -> dict:
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in d.items()}


# ---- figures ---------------------------------------------------------------------------------


def _figures(result: dict, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    s = result["single"]
    z = np.asarray(s["depth_m"]) * 1e3
    cen, bun = np.asarray(s["centroid_error_m"]) * 1e3, np.asarray(s["bundle_error_m"]) * 1e3
    sig = np.asarray(s["bundle_sigma_m"]) * 1e3
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    for k, ax in enumerate(axes):
        ax.plot(z, cen[:, k], "o-", label="volume centroid")
        ax.errorbar(z, bun[:, k], yerr=2 * sig[:, k], fmt="s-", capsize=2,
                    label="ray bundle (±2σ reported)")
        if "refined_error_m" in s:
            ax.plot(z, np.asarray(s["refined_error_m"], float)[:, k] * 1e3, "^-",
                    label="refined (forward model)")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("true depth Z (mm)")
        ax.set_ylabel(f"{'xyz'[k]} error (mm)")
        ax.set_title(f"single particle: {'xyz'[k]}")
    axes[0].legend(fontsize=8)
    p = out / "tracking_single_particles.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    fig, axes = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    for row, flow in enumerate(("oseen", "hill")):
        rs = _seed_mean([r for r in result["cases"] if r["flow"] == flow])
        d = [r["particles_per_lenslet"] for r in rs]
        ax = axes[row, 0]
        ax.plot(d, [r["tracked_fraction"] for r in rs], "o-", label="tracked fraction")
        ax.plot(d, [r["wrong_match_rate"] for r in rs], "s-", label="wrong-match rate")
        ax.axhline(TARGET["tracked"], color="C0", ls=":")
        ax.axhline(TARGET["wrong"], color="C1", ls=":")
        ax.set_title(f"{flow}: matching")
        ax.set_xlabel("particles per lenslet")
        ax.legend(fontsize=8)
        for col, (axis, lab) in enumerate(((0, "lateral x"), (2, "depth z")), start=1):
            ax = axes[row, col]
            ax.plot(d, [r["track_rms_vox"][axis] for r in rs], "o-", label="tracks")
            ax.plot(d, [r["piv_grid_rms_vox"][axis] for r in rs], "s-",
                    label="correlation (grid)")
            ax.plot(d, [r["piv_at_tracks_rms_vox"][axis] for r in rs], "^--",
                    label="correlation at the tracks")
            ax.plot(d, [r["position_rms_vox"]["bundle"][axis] for r in rs], "v:",
                    label="bundle position (A)")
            ax.plot(d, [r["position_rms_vox"]["centroid"][axis] for r in rs], "x:",
                    label="centroid position (A)")
            ax.axhline(TARGET["lateral_vox" if axis < 2 else "depth_vox"], color="k", ls=":")
            ax.set_title(f"{flow}: rms error, {lab} (voxels)")
            ax.set_xlabel("particles per lenslet")
            ax.set_yscale("log")
        axes[row, 1].legend(fontsize=7)
    p = out / "tracking_density.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths


def _seed_mean(rows: list[dict]) -> list[dict]:
    """Rows averaged over seeds per density (fractions and rms: mean; rms via mean square)."""
    out = []
    for d in sorted({r["particles_per_lenslet"] for r in rows}):
        g = [r for r in rows if r["particles_per_lenslet"] == d]
        m = {"particles_per_lenslet": d, "n_seeds": len(g), "flow": g[0]["flow"]}
        for k in ("tracked_fraction", "wrong_match_rate", "off_focus_fraction"):
            m[k] = float(np.mean([r[k] for r in g]))
        for k in ("track_rms_vox", "piv_grid_rms_vox", "piv_at_tracks_rms_vox",
                  "track_rms_vox_off_focus", "binned_rms_vox"):
            m[k] = np.sqrt(np.mean([np.square(r[k]) for r in g], axis=0)).tolist()
        m["position_rms_vox"] = {k: np.sqrt(np.mean([np.square(r["position_rms_vox"][k])
                                                     for r in g], axis=0)).tolist()
                                 for k in ("bundle", "centroid")}
        for k in ("track_within_2sigma", "within_2sigma"):
            m[k] = np.mean([r[k] for r in g], axis=0).tolist()
        m["n_true"] = int(sum(r["n_true"] for r in g))
        m["n_tracks"] = int(sum(r["n_tracks"] for r in g))
        m["track_s"] = float(np.mean([r["timings_s"]["track"] for r in g]))
        out.append(m)
    return out


# ---- markdown --------------------------------------------------------------------------------


def _v(x, n=3) -> str:
    return ", ".join(f"{a:.{n}f}" for a in x)


def _header(result: dict) -> list[str]:
    """Return the report's title and the paragraph on how it was generated."""
    ran = sorted({c["particles_per_lenslet"] for c in result["cases"]})
    seeds = sorted({c["seed"] for c in result["cases"]})
    full = tuple(ran) == tuple(DENSITIES)
    cmd = "python pipelines/validate_tracking.py --out docs/validation" + (
        "" if full else " --quick" if len(seeds) == 1 and ran == [0.15]
        else " --densities " + " ".join(f"{d:g}" for d in ran))
    lines = ["# Particle tracking from the light field", "",
             f"Generated by `{cmd}` ({result['seconds']:.0f} s"
             + ("" if full else "; " + ", ".join(f"{d:g}" for d in ran)
                + " particles per lenslet only, seed" + ("s " if len(seeds) > 1 else " ")
                + ", ".join(str(x) for x in seeds) + ": the sweep over "
                + ", ".join(f"{d:g}" for d in DENSITIES) + " was not rerun, the machine being "
                "loaded")
             + "). Whole chain of `docs/validation/vortex.md` on the "
             "CI camera (41 x 61 lenslets, 50 mm lens at M = -1, f/2.2, voxel = one lenslet "
             "footprint = 0.125 mm each way; depth resolution cell 0.55 mm), calibration from "
             "images, then `plenopiv.tracking`: ray-bundle positions of the particles of A and "
             "B, matched with the correlation field as predictor. Errors in voxels; "
             "a track is correct when one true particle lies within one resolution cell "
             "of both its ends (cells of 0.125, 0.125, 0.55 mm), wrong otherwise; the "
             "tracked fraction counts the true particles with a correct track.", ""]
    return lines


def _summary(result: dict) -> list[str]:
    """Return the summary section: each target per flow at 0.15 ppl, the single particles."""
    t = result["target"]
    lines = ["## Summary", ""]
    for flow in ("oseen", "hill"):
        rs = [r for r in _seed_mean([c for c in result["cases"] if c["flow"] == flow])
              if r["particles_per_lenslet"] == 0.15]
        if not rs:
            continue
        r = rs[0]
        checks = [("tracked", r["tracked_fraction"] >= t["tracked"],
                   f"{r['tracked_fraction']:.0%} tracked (≥ {t['tracked']:.0%})"),
                  ("wrong", r["wrong_match_rate"] <= t["wrong"],
                   f"{r['wrong_match_rate']:.1%} wrong matches (≤ {t['wrong']:.0%})"),
                  ("lateral", max(r["track_rms_vox"][:2]) <= t["lateral_vox"],
                   f"lateral rms {_v(r['track_rms_vox'][:2])} (≤ {t['lateral_vox']})"),
                  ("depth", r["track_rms_vox"][2] <= t["depth_vox"],
                   f"depth rms {r['track_rms_vox'][2]:.3f} (≤ {t['depth_vox']})"),
                  ("better", all(a < b for a, b in zip(r["track_rms_vox"],
                                                       r["piv_grid_rms_vox"], strict=True)),
                   f"better than the correlation's rms {_v(r['piv_grid_rms_vox'])} on every "
                   "axis")]
        per_seed = [c["track_rms_vox"][2] for c in result["cases"]
                    if c["flow"] == flow and c["particles_per_lenslet"] == 0.15]
        lines.append(f"- **{flow}, 0.15 particles per lenslet** ({r['n_seeds']} seeds, "
                     f"{r['n_true']} true particles): "
                     + "; ".join(f"{txt} — {'met' if ok else 'not met'}"
                                 for _, ok, txt in checks)
                     + f". Depth rms per seed {_v(per_seed)} (mean {np.mean(per_seed):.3f}, "
                     f"spread {np.ptp(per_seed):.3f}).")
    s = result["single"]
    lines += [f"- **Single particles** (thesis §5.1 geometry, Z = -10 … +10 mm, "
              f"{s['n_found']} found): rms error x, y, z (mm) centroid "
              f"{_v(s['rms_mm']['centroid'])}, "
              f"ray bundle {_v(s['rms_mm']['bundle'])}"
              + (f", refined (as the tracks) {_v(s['rms_mm']['refined'])}"
                 if "refined" in s["rms_mm"] else "")
              + "; bundle errors within ±2σ reported: "
              f"{_v(s['within_2sigma'], 2)} (x, y, z).", ""]
    return lines


#: The "Reading" section: what the figures mean and where the depth error came from.
READING = ["## Reading", "",
          "- Positions of the tracks are ray-bundle positions refined by the forward model "
          "(`plenopiv.particles.forward`, `[tracking] forward_refine`); the single-particle "
          "table gives both. The position columns below (A particles of the correct "
          "tracks) are the refined positions against the volume centroids. Within one "
          "depth cell of focus the refinement searches joint depth x lateral grids; beyond, "
          "Levenberg-Marquardt steps on the misfit (see the search below).",
          "- Where the depth error of the tracks came from (0.15 particles per lenslet, "
          "seeds 1-3, every track kept, `min_lenslets = 1`; depth rms in voxels, tracks in "
          "brackets): by the fewer lenslets of its two ends, Oseen 1.60 (33) through one "
          "lenslet, 0.92 (51) through 2-5, 0.22 (450) through 6 or more; Hill 0.33 (15), "
          "0.77 (34), 0.17 (422). By depth, Oseen 1.33 within 0.6 mm of focus, 0.50 at "
          "0.6-1 mm, 0.22 beyond. Not from the neighbours: tracks with no other particle "
          "within two footprints (and one depth cell) have the same rms as those with one or "
          "more (Oseen 0.52 / 0.57, Hill 0.25 / 0.33), and the worst tracks are isolated, "
          "with a unique match (quality 1). The fit's reported depth uncertainty grows "
          "towards focus but separates the bad tracks poorly (dropping ends with "
          "σ_z > 2.5 voxel left Oseen at 0.37 with the earlier search).",
          "- Why: near focus a particle's light falls in the 2 x 2 lenslets around a "
          "footprint corner, and the edge of its lit patch in each micro-image fixes only "
          "the ratio of its lateral offset from that corner to its depth: every point of "
          "the line from the corner through the particle lights the same pixels to the same "
          "fractions (`tests/tracking/test_tracking.py`, to 1e-13 over 0.2 mm). Only a "
          "particle whose blur spans three lenslets along an axis, two edges in one "
          "micro-image, has a depth in the image: at f/2.2 beyond b S_o / D = 0.55 mm from "
          "focus, seen through 6 or more lenslets. Tracks with an end seen through fewer are "
          "dropped (`[tracking] "
          "min_lenslets = 6`, counted as `rejected_few_lenslets`), the standard PTV gate on "
          "a track's own measurability; it keeps 0.54-0.61 of the true particles tracked at "
          "0.15 particles per lenslet (0.60-0.73 with every track).",
          "- The forward search was the other part: near focus depth and lateral position "
          "trade off along that slanted valley, which searches along one axis at a time "
          "(depth, then lateral) crossed without following it; on the worst Oseen seed the "
          "truth fitted the pixels better than the refined position for 18 of the 27 "
          "near-focus tracks off by more than half a voxel. Joint depth x lateral grids in "
          "every round took the 6-or-more-lenslet tracks within 1 mm of focus from 0.56 to "
          "0.25 voxel (Oseen) and the tracks' depth rms per seed (same gate) from 0.31, "
          "0.33, 0.20 to 0.22, 0.27, 0.17 (Hill 0.24, 0.21, 0.23 to 0.21, 0.14, 0.16).",
          "- Those grids cost ~850 misfit evaluations per particle, most of the tracking's "
          "time at 16 MP, where most particles lie far from focus. Beyond one depth cell "
          "the refinement now takes damped Gauss-Newton (Levenberg-Marquardt) steps on the "
          "misfit's analytic Jacobian, depth and lateral position moved together (the "
          "slanted valley), from the bundle position and, within 3 depth cells of focus, "
          "from +-0.3 depth cells around it, keeping the end of least misfit, in two rounds "
          "with the amplitude estimated again in between. Measured on the same 0.15 "
          "particles-per-lenslet pairs (seeds 1-3, depth rms of the tracks, Oseen / Hill): "
          "grids everywhere 0.222 / 0.172; local steps 0.219 / 0.183 (three starts for "
          "every particle 0.221 / 0.180, within 2 cells only 0.234 / 0.225, within 4 "
          "0.218 / 0.191); one start (the bundle position; grids within 2 cells) "
          "0.214 / 0.227 (in one round, on Hill seed 2, a quarter of the particles beyond 2 "
          "cells ended at a higher misfit than the grids', a tenth more than 5 % higher: "
          "local minima, which the two other starts get out of); three starts in one round "
          "0.220 / 0.220; no refinement beyond 2 depth cells 0.389 / 0.405, beyond 3 "
          "0.303 / 0.282 (the bundle alone is not enough out of focus either). Tracks with "
          "both ends seen through 6 or more lenslets lie beyond one depth cell (the grids "
          "within 0 or 1 cell gave the same tracks): here the grids refine no track, and of "
          "the single particles only those within 0.55 mm of focus.",
          "- At full size (`python benchmarks/full_camera.py --json --track "
          "--lateral-subdivision 1 --skip-patch`: Auburn camera, 16 MP, 20,000 particles, "
          "0.36 per lenslet, depth cell 2.24 mm, particles to 21 mm from focus) the tracking "
          "adds 67 s of CPU, 106 s wall to the pair (load average 5.8 on 2 cores; 213-235 s "
          "of CPU with the grids for every particle and the light field built again), "
          "4.0 GB peak for the process: 14,734 tracks, 73 % of the particles, 0.50 % wrong "
          "(0.23 % with the grids), displacement rms 0.068, 0.044, 0.88 voxel (0.062, 0.041, "
          "0.86); 24,110 and 23,916 particles took the local steps (most beyond 3 depth "
          "cells, one descent), 163 and 162 the grids. Measured again on the idle machine "
          "with NumPy's huge-page advice off (as the `plenopiv` command runs): 31.8 s wall, "
          "53.8 s of CPU (load 1.6), 4.4 GB peak, 14,706 tracks, 72.5 %, 0.50 % wrong, rms "
          "0.068, 0.044, 0.89 voxel, 6 % over the 30 s target. Since, the kernels take the "
          "particles in spatial order (neighbours find their lenslets' rays in cache), each "
          "bundle solve selects its rays once for its shares, normal equations and "
          "covariance, and the refinement's pixel selection scans only each lenslet's "
          "aperture window and gathers the pixels as it selects them: the same benchmark "
          "adds 34.5 s of CPU, 41.2 s wall (load 5.1), 4.56 GB peak, 14,706 tracks, "
          "72.5 %, 0.50 % wrong, rms 0.068, 0.044, 0.885 voxel, and on the idle machine "
          "19.9 s wall, 33.5 s of CPU (load 1.6-1.7), 4.6 GB peak, 14,705 tracks, 72.5 %, "
          "0.50 % wrong, rms 0.068, 0.044, 0.885 voxel: the 30 s target met; on the saved pair, "
          "tracking alone 59.2 -> 34.2 s of CPU at load 3-4 (14,734 tracks against "
          "14,735: the rays' shared sums add in another order, last-bit differences). "
          "README, full-camera section.",
          "- The single particle at Z = -5 mm, missing from an earlier report (0 "
          "lenslets, no centroid), was lost by the reconstruction, not by the bundle: the "
          "line-of-sight mask, then judged per whole voxel, emptied that volume; since "
          "the mask is judged on sub-voxel cells the particle is found.",
          "- A particle in focus lights one lenslet whatever its position on it: its "
          "lateral position is known to a footprint only (the off-focus column leaves out "
          "the tracks with such an end; with `min_lenslets = 6` there are none). The "
          "reported uncertainty stays the bundle fit's: it covers the refined positions "
          "with room to spare (all errors within ±2σ), so it is conservative.",
          ""]


def _density_table(result: dict) -> list[str]:
    """Return the density sweep's table (mean over seeds)."""
    lines = ["## Density sweep (mean over seeds)", "",
              "| flow | ppl | seeds | tracked | wrong | tracks rms x, y, z | off-focus tracks rms "
              "(fraction) | correlation rms (grid) | correlation at tracks | binned tracks rms "
              "| refined pos. rms (A) | centroid pos. rms (A) | tracks within ±2σ | track s |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for flow in ("oseen", "hill"):
        for r in _seed_mean([c for c in result["cases"] if c["flow"] == flow]):
            lines.append(
                f"| {flow} | {r['particles_per_lenslet']} | {r['n_seeds']} | "
                f"{r['tracked_fraction']:.2f} | {r['wrong_match_rate']:.3f} | "
                f"{_v(r['track_rms_vox'])} | {_v(r['track_rms_vox_off_focus'])} "
                f"({r['off_focus_fraction']:.2f}) | {_v(r['piv_grid_rms_vox'])} | "
                f"{_v(r['piv_at_tracks_rms_vox'])} | {_v(r['binned_rms_vox'])} | "
                f"{_v(r['position_rms_vox']['bundle'])} | "
                f"{_v(r['position_rms_vox']['centroid'])} | {_v(r['track_within_2sigma'], 2)} "
                f"| {r['track_s']:.1f} |")
    return lines


def _single_table(s: dict) -> list[str]:
    """Return the single particles' table (thesis §5.1)."""
    lines = ["", "## Single particles (thesis §5.1)", "",
              "| Z (mm) | centroid error x, y, z (µm) | bundle error x, y, z (µm) | refined "
              "error x, y, z (µm) | bundle σ x, y, z (µm) | lenslets |",
              "|---|---|---|---|---|---|"]
    refined = s.get("refined_error_m", np.full((len(s["depth_m"]), 3), np.nan))
    for i, z in enumerate(s["depth_m"]):
        lines.append(f"| {z * 1e3:+.0f} | {_v(np.asarray(s['centroid_error_m'][i]) * 1e6, 1)} | "
                     f"{_v(np.asarray(s['bundle_error_m'][i]) * 1e6, 1)} | "
                     f"{_v(np.asarray(refined[i], float) * 1e6, 1)} | "
                     f"{_v(np.asarray(s['bundle_sigma_m'][i]) * 1e6, 1)} | "
                     f"{s['n_lenslets'][i]} |")
    return lines


def markdown(result: dict, figures: list[str]) -> str:
    """Return the Markdown report of a :func:`run` result."""
    lines = (_header(result) + _summary(result) + READING + _density_table(result)
             + _single_table(result["single"]))
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures] + [""]
    return "\n".join(lines)
