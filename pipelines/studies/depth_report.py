"""Rendering of the depth study (:mod:`pipelines.studies.depth`): Figs 5.2-5.4 and Markdown.

The functions here draw and write what :func:`run` measured with the study's stage
functions (this module imports the study, never the other way round); the straight-line fits
drawn through the points come from the study's own
:func:`~pipelines.studies.depth.linear_fit`, the curves from its paraxial model.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pipelines.studies.depth import (
    DEPTHS,
    HALF_XY,
    MARGIN,
    STUDY_PARTICLES,
    THESIS_DISCONTINUITY,
    THESIS_TABLE_5_2,
    VOXEL,
    DepthCase,
    expected_effective_depth,
    focus_crossing_depth,
    focus_region,
    image_distance_of,
    linear_fit,
    measure_depths,
    study_cases,
    table_5_1,
    table_5_2,
)
from pipelines.studies.output import (
    fmt,
    pyplot,
    savefig,
    section,
    table,
    table_header,
    table_row,
    write_json,
    write_text,
)
from plenopiv.settings import as_dict

#: Colour and marker of each case in the figures.
STYLE = {"none": ("tab:blue", "o"), "external": ("tab:red", "s"),
         "plate_thesis": ("tab:green", "^"), "plate_physical": ("tab:purple", "D"),
         "plate_thesis_default_aperture": ("tab:olive", "v")}


# --------------------------------------------------------------------------------------------
# figures
# --------------------------------------------------------------------------------------------


def _depth_panel(ax, by: dict, measured: dict, names, corr_of, lim, title) -> None:
    """Corrected against true depth for ``names`` within ±``lim`` mm, each with its fit."""
    ax.plot([-lim, lim], [-lim, lim], "k-", lw=1, label="ideal")
    for name in names:
        if name not in measured:
            continue
        m, c = measured[name], by[name]
        z = m["depth_m"]
        sel = np.abs(z) <= lim * 1e-3 + 1e-12
        corr = corr_of(c)
        zc = c.corrections[corr].depth(m["effective_m"])
        fit = linear_fit(z[sel], zc[sel])
        col, mk = STYLE.get(name, ("k", "x"))
        ax.plot(z[sel] * 1e3, zc[sel] * 1e3, mk, color=col, ms=5,
                label=f"{c.label}: slope {fit['slope']:.4f}")
        xx = np.array([-lim, lim])
        ax.plot(xx, fit["slope"] * xx + fit["intercept_mm"], "-", color=col, lw=0.8)
    ax.set_xlabel("true depth Z (mm)")
    ax.set_ylabel("reconstructed depth (mm)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")


def _corrected(c: DepthCase) -> str:
    """The correction a case's "corrected" panel applies."""
    return "corrected" if "corrected" in c.corrections else (
        "corrected (1/n)" if c.name.startswith("plate_thesis") else "uncorrected")


def _uncorrected(c: DepthCase) -> str:
    return "uncorrected"


def fig_5_2(by: dict, measured: dict, path: Path) -> Path:
    """Fig 5.2: the external interface, uncorrected and corrected by n1/n2."""
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.8), sharey=True)
    _depth_panel(ax[0], by, measured, ("none", "external"), _uncorrected, 10,
                 "(a) uncorrected (effective depth)")
    _depth_panel(ax[1], by, measured, ("none", "external"), _corrected, 10,
                 "(b) corrected, Z = (n1/n2) ΔS_eff (Eq. 4.7)")
    fig.suptitle("Fig 5.2: external interface (water, n1 = 1.33, l1 = 40 mm), 50 mm lens, M = -1")
    return savefig(fig, path)


def fig_5_3(by: dict, measured: dict, path: Path) -> Path:
    """Fig 5.3: the plate, both back sides, uncorrected and corrected, ±5 mm."""
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.8), sharey=True)
    names = ("none", "plate_thesis", "plate_physical")
    _depth_panel(ax[0], by, measured, names, _uncorrected, 5, "(a) uncorrected (effective depth)")
    _depth_panel(ax[1], by, measured, names, _corrected, 5,
                 '(b) corrected: "thesis" ÷ n (Eq. 5.1), "physical" none (auto)')
    fig.suptitle("Fig 5.3: plate t = 6.3 mm, n = 1.46 in front of the lenslets, ±5 mm")
    return savefig(fig, path)


def _positive_depths(z) -> np.ndarray:
    """Mask of the depths in 0 … 10 mm (Fig 5.4's range)."""
    return (z >= -1e-12) & (z <= 10e-3 + 1e-12)


def _plate_focus_curves(ax, by: dict, measured: dict) -> float | None:
    """Fig 5.4's measured depths, predictions, split fits and residuals; return Z* (m)."""
    zstar = None
    for name in ("plate_thesis", "plate_physical"):
        if name not in measured:
            continue
        m, c = measured[name], by[name]
        zstar = focus_crossing_depth(c.camera)
        z = m["depth_m"]
        sel = _positive_depths(z)
        col, mk = STYLE[name]
        ax[0].plot(z[sel] * 1e3, m["effective_m"][sel] * 1e3, mk, color=col, ms=5,
                   label=f"{c.label}")
        zz = np.linspace(0, 10e-3, 101)
        ax[0].plot(zz * 1e3, expected_effective_depth(c.camera, zz) * 1e3, ":", color=col,
                   lw=1, label="paraxial prediction")
        for part in (z[sel] <= zstar, z[sel] > zstar):
            fit = linear_fit(z[sel][part], m["effective_m"][sel][part])
            xx = z[sel][part] * 1e3
            ax[0].plot(xx, fit["slope"] * xx + fit["intercept_mm"], "-", color=col, lw=0.8)
        ax[1].plot(z[sel] * 1e3, (m["effective_m"][sel] - m["expected_effective_m"][sel]) * 1e3,
                   mk + "-", color=col, ms=5, lw=0.8, label=c.label)
    if "none" in measured:
        m = measured["none"]
        z = m["depth_m"]
        sel = _positive_depths(z)
        col, mk = STYLE["none"]
        ax[1].plot(z[sel] * 1e3, (m["effective_m"][sel] - m["expected_effective_m"][sel]) * 1e3,
                   mk + "--", color=col, ms=4, lw=0.8, alpha=0.8, label="no interface (control)")
    return zstar


def fig_5_4(by: dict, measured: dict, path: Path) -> Path:
    """Fig 5.4: the plate over 0-10 mm, focus behind or in front of the plate's front face."""
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.8))
    zstar = _plate_focus_curves(ax, by, measured)
    (sb, ib, _), (sf, i_f, _) = THESIS_TABLE_5_2["behind"], THESIS_TABLE_5_2["in_front"]
    xb, xf = np.array([0.0, 7.0]), np.array([7.0, 10.0])
    ax[0].plot(xb, sb * xb + ib, "--", color="tab:orange", lw=1.2,
               label="thesis Table 5.2 fits (ALFA)")
    ax[0].plot(xf, sf * xf + i_f, "--", color="tab:orange", lw=1.2)
    ax[0].plot([0, 10], [0, 10], "k-", lw=1, label="ideal")
    for a in ax:
        if zstar is not None:
            a.axvline(zstar * 1e3, color="0.4", ls="--", lw=1)
        a.axvline(THESIS_DISCONTINUITY * 1e3, color="tab:orange", ls="-.", lw=1)
        a.set_xlabel("true depth Z (mm)")
        a.grid(alpha=0.3)
    ax[1].axhspan(-VOXEL * 1e3, VOXEL * 1e3, color="0.85", zorder=0, label="± 1 voxel")
    ax[0].set_ylabel("reconstructed (effective) depth (mm)")
    ax[1].set_ylabel("reconstructed − paraxial prediction (mm)")
    ax[0].set_title("(a) uncorrected; lines: fits either side of Z*")
    ax[1].set_title(f"(b) residual; dashed: Z* = {zstar * 1e3:.2f} mm, dash-dot: thesis's 7 mm"
                    if zstar is not None else "(b) residual")
    ax[0].legend(fontsize=7, loc="upper left")
    ax[1].legend(fontsize=7)
    fig.suptitle("Fig 5.4: plate, 0-10 mm: focus behind (Z < Z*) or in front of (Z > Z*) the "
                 "plate's front face")
    return savefig(fig, path)


def figures(cases: list[DepthCase], measured: dict, out: Path) -> list[Path]:
    """Draw Figs 5.2-5.4 of the measured depths into ``out``; return the PNG paths."""
    by = {c.name: c for c in cases}
    return [fig_5_2(by, measured, out / "fig_5_2_external.png"),
            fig_5_3(by, measured, out / "fig_5_3_internal.png"),
            fig_5_4(by, measured, out / "fig_5_4_internal_focus.png")]


# --------------------------------------------------------------------------------------------
# Markdown
# --------------------------------------------------------------------------------------------
def _fit(results: dict, case: str, correction: str, fit_range: str = "±10 mm") -> dict:
    """The Table 5.1 row of one case, correction and fit range (NaN fit if absent)."""
    for r in results["table_5_1"]:
        if (r["case"], r["correction"], r["fit_range"]) == (case, correction, fit_range):
            return r
    return {"slope": np.nan, "intercept_mm": np.nan, "rms_residual_mm": np.nan}


def _summary(results: dict) -> list[str]:
    """Put the findings in words, every number taken from ``results``."""
    f, meas = _fit, results["measured"]
    rec = results["cases"]["none"]["reconstruction"]
    out = ["## Summary", ""]
    out.append(f"- No interface: slope {f(results, 'none', 'uncorrected')['slope']:.4f} "
               "(thesis 0.9925).")
    if "external" in meas:
        out.append(
            f"- External window: uncorrected {f(results, 'external', 'uncorrected')['slope']:.4f}"
            f" (n2/n1 = {1 / 1.33:.4f}; thesis 0.7563), corrected by n1/n2 "
            f"{f(results, 'external', 'corrected')['slope']:.4f} (thesis 1.0059).")
    if "plate_physical" in meas:
        out.append(
            '- Plate, "physical" back side: uncorrected '
            f"{f(results, 'plate_physical', 'uncorrected')['slope']:.4f}; S_i,eff accounts for "
            "the plate and the light field is exact, so no correction is needed (the 1/n of "
            f"Eq. 5.1 would give {f(results, 'plate_physical', 'corrected (1/n)')['slope']:.4f}).")
    if "plate_thesis" in meas:
        u10, u5 = (f(results, "plate_thesis", "uncorrected", r) for r in ("±10 mm", "±5 mm"))
        c10, c5 = (f(results, "plate_thesis", "corrected (1/n)", r) for r in ("±10 mm", "±5 mm"))
        ex = f(results, "plate_thesis", "exact inverse of u/n (not in the library)")
        out.append(
            f'- Plate, "thesis" back side: uncorrected {u10["slope"]:.4f} over ±10 mm, '
            f'{u5["slope"]:.4f} over ±5 mm (thesis 1.4265); after the 1/n of Eq. 5.1 '
            f'{c10["slope"]:.4f} and {c5["slope"]:.4f} (thesis 0.9770). The 1/n is the '
            "linear part of Z' = n S_o Z/(S_o - (n-1) Z): the corrected fit over ±10 mm keeps an "
            f'intercept of {c10["intercept_mm"]:+.3f} mm and an rms residual of '
            f'{c10["rms_residual_mm"]:.3f} mm, against {ex["intercept_mm"]:+.3f} mm and '
            f'{ex["rms_residual_mm"]:.3f} mm through the exact inverse.')
    if "plate_thesis_default_aperture" in meas:
        m = meas["plate_thesis_default_aperture"]
        d = np.asarray(m["dark_fraction"], float)
        split = int(np.sum(np.asarray(m["n_particles"]) > 1))
        out.append(
            '- The "thesis" back side with the default light-field aperture: the micro-images '
            "are n times smaller than the light field assumes, so at the particle's own voxel "
            f"{np.nanmin(d):.2f}-{np.nanmax(d):.2f} of the weight falls on dark pixels, against "
            f"the soft mask's `dark_tolerance` = {rec['dark_tolerance']:g} (with the matched "
            "aperture: "
            f"{np.nanmin(meas['plate_thesis']['dark_fraction']):.3f}-"
            f"{np.nanmax(meas['plate_thesis']['dark_fraction']):.3f}); {split} of "
            f"{len(d)} depths give a second particle, and the uncorrected slope is "
            f"{f(results, 'plate_thesis_default_aperture', 'uncorrected')['slope']:.4f}.")
    for r in results["table_5_2"]:
        if r["split"] != "geometric Z*":
            continue
        out.append(f"- Table 5.2, {r['label']}: the two fits differ by {r['jump_mm']:+.3f} mm at "
                   f"Z* = {r['split_mm']:.2f} mm (paraxial curvature alone: "
                   f"{r['expected_jump_mm']:+.3f} mm).")
    out.append("- The no-interface rows of Table 5.2 are the control: the same split without a "
               "plate shows what the scatter of single depths near the focal plane does alone.")
    t = THESIS_TABLE_5_2
    out.append("- The thesis's fits differ by "
               f"{(t['in_front'][0] - t['behind'][0]) * 7 + t['in_front'][1] - t['behind'][1]:+.2f}"
               " mm at 7 mm.")
    worst = []
    for name, m in meas.items():
        e = np.abs(np.asarray(m["effective_m"], float) - np.asarray(m["expected_effective_m"]))
        if np.all(np.isnan(e)):
            continue
        i = int(np.nanargmax(e))
        worst.append(f"{results['cases'][name]['label']}: {e[i] * 1e3:.2f} mm at "
                     f"Z = {m['depth_m'][i] * 1e3:+.0f} mm (effective "
                     f"{m['expected_effective_m'][i] * 1e3:+.2f} mm)")
    out.append("- Largest single-depth errors (against the paraxial expectation): "
               + "; ".join(worst) + ".")
    return out + [""]


TABLE_5_1_COLUMNS = ("case", "correction", "fit range", "slope", "intercept (mm)", "R²",
                     "rms residual (mm)", "thesis slope", "thesis intercept (mm)", "thesis R²")
TABLE_5_2_COLUMNS = ("case", "split at (mm)", "behind: slope", "intercept (mm)", "R²",
                     "in front: slope", "intercept (mm)", "R²", "jump at split (mm)",
                     "expected jump, paraxial (mm)", "step in residual (mm)")
PER_DEPTH_COLUMNS = ("Z (mm)", "effective (mm)", "expected (mm)", "error (mm)", "particles",
                     "2nd/1st", "lateral (vox)", "dark fraction")


def _table_5_1_cells(r: dict) -> list[str]:
    """Cells of one Table 5.1 row: our fit and the thesis's."""
    t = r["thesis"] or {}
    return [r["label"], r["correction"], r["fit_range"], fmt(r["slope"], ".4f"),
            fmt(r["intercept_mm"], ".4f"), fmt(r["r2"], ".5f"), fmt(r["rms_residual_mm"], ".3f"),
            fmt(t.get("slope"), ".4f"), fmt(t.get("intercept_mm"), ".4f"),
            fmt(t.get("r2"), ".4f")]


def _table_5_2_cells(r: dict) -> list[str]:
    """Cells of one Table 5.2 row: the fits either side of the split and the jump."""
    b, f = r["behind"], r["in_front"]
    return [r["label"], f"{r['split_mm']:.2f} ({r['split']})", fmt(b["slope"], ".4f"),
            fmt(b["intercept_mm"], ".4f"), fmt(b["r2"], ".5f"), fmt(f["slope"], ".4f"),
            fmt(f["intercept_mm"], ".4f"), fmt(f["r2"], ".5f"), fmt(r["jump_mm"], "+.3f"),
            fmt(r["expected_jump_mm"], "+.3f"), fmt(r["residual_step_mm"], "+.3f")]


def _per_depth_lines(c: dict, m: dict) -> list[str]:
    """One case's section of per-depth measurements: grid, table, errors."""
    lines = [f"### {c['label']}", "", f"{c['note']}" if c["note"] else "",
             f"Grid z = {m['grid']['z_mm'][0]:.3f} … {m['grid']['z_mm'][1]:.3f} mm, shape "
             f"{m['grid']['shape']}; {m['seconds']:.0f} s.", "", *table_header(PER_DEPTH_COLUMNS)]
    for i, z in enumerate(m["depth_m"]):
        e, p = m["effective_m"][i], m["expected_effective_m"][i]
        lines.append(table_row([f"{z * 1e3:+.0f}", fmt(e * 1e3, "+.3f"), f"{p * 1e3:+.3f}",
                                fmt((e - p) * 1e3, "+.3f"), m["n_particles"][i],
                                f"{m['second_intensity'][i]:.2f}",
                                fmt(m["lateral_vox"][i], ".2f"),
                                fmt(m["dark_fraction"][i], ".3f")]))
    for err in m["errors"]:
        lines.append(f"\n- {err}")
    return lines + [""]


def markdown(results: dict) -> str:
    """The study's Markdown report: summary, Tables 5.1 and 5.2, per-depth rows, figures."""
    geo = results["geometry"]
    rec = results["cases"]["none"]["reconstruction"]
    lines = [
        "# Depth study (thesis §5.1-5.2): Table 5.1, Table 5.2, Figs 5.2-5.4", "",
        "Generated by `python pipelines/validate_depth.py` (`pipelines.studies.depth`). One "
        "particle on the optical axis at Z = -10 … +10 mm (1 mm steps), rendered by plenopiv's ray "
        f"tracer ({results['rays_per_particle']} rays, exact refraction at the window and the "
        "plate), reconstructed by `pipeline.reconstruct_volume` (MLOS + soft line-of-sight mask + "
        f"{rec['method']}, {rec['iterations']} iterations, pixel_threshold "
        f"{rec['pixel_threshold']:g}, dark_tolerance {rec['dark_tolerance']:g}; the library's "
        "defaults except where a case says otherwise) with the exact calibration "
        "(`Calibration.from_camera`: the true S_i,eff), located by the brightest particle's "
        "position from the light field (the library's default, `[particles] position = "
        "\"light_field\"`: the ray-bundle fit seeded by the volume's centroid).", "",
        f"Camera: 50 mm lens, f/{geo['f_number']:g}, S_i,eff = S_o,eff = "
        f"{geo['si_eff_mm']:.2f} mm (M = -1), {geo['lenslets']} × {geo['lenslets']} lenslets of "
        "the Auburn MLA (125 µm, f̄ = 500 µm, 7.4 µm pixels). Volume as a user types it: x, y = "
        f"±{HALF_XY * 1e3:g} mm, 0.125 mm voxels whose edges run through the lenslet centres "
        "(every voxel straddles four lenslets; nothing aligns the grid with the footprints); "
        "each case's depth range covers its expected effective depths with "
        f"{MARGIN * 1e3:g} mm to spare, rounded out to whole millimetres (table below). "
        "External interface: "
        f"n1 = 1.33, l1 = 40 mm, l2 = {geo['l2_mm']:.2f} mm. Plate: t = 6.3 mm, n = 1.46, "
        f"l3 = {geo['l3_mm']:.2f} mm.", "", *_summary(results),
        *section("Table 5.1: reconstructed against true depth"),
        *table(TABLE_5_1_COLUMNS, map(_table_5_1_cells, results["table_5_1"]))]
    lines += ["", "## Table 5.2: plate, 0-10 mm, uncorrected; fits either side of the focus "
              "crossing", "",
              "The image of depth Z converges at S_i(Z) = 1/(1/f - 1/(S_o,eff + Z)); it reaches "
              f"the plate's front face (l3 = {geo['l3_mm']:.3f} mm) at Z* = "
              f"{geo['z_star_mm']:.3f} mm. "
              "For Z < 0 the image forms behind the lenslets, for 0 < Z < Z* inside the glass, for "
              "Z > Z* in the air in front of the plate (between lens and plate). The thesis saw a "
              "jump near 7 mm; Z = 7 mm images at S_i = "
              f"{geo['si_at_7mm_mm']:.2f} mm, which is S_i,eff - t = "
              f"{geo['si_eff_mm'] - 6.3:.2f} mm (a plate whose front face lies t, not t/n, before "
              "the effective lenslet plane) to within "
              f"{abs(geo['si_at_7mm_mm'] - geo['si_eff_mm'] + 6.3):.2f} mm.", "",
              *table(TABLE_5_2_COLUMNS, map(_table_5_2_cells, results["table_5_2"]))]
    t = THESIS_TABLE_5_2
    jump = (t["in_front"][0] - t["behind"][0]) * 7 + t["in_front"][1] - t["behind"][1]
    lines += [table_row(["thesis (ALFA)", "≈ 7", *t["behind"], *t["in_front"], f"{jump:+.3f}"])
              + " | |", ""]
    lines += ["## Per-depth measurements", "",
              "Effective depth of the brightest particle, the paraxial expectation, the number of "
              "particles found (and the 2nd brightest's intensity relative to the 1st), the "
              "largest lateral offset (voxels) and the dark fraction of the soft mask at the "
              "expected voxel, that of its best-lit sub-cell "
              "(`plenopiv.reconstruction.sightline`; the mask "
              f"empties a voxel above `dark_tolerance` = {rec['dark_tolerance']:g}).", ""]
    for name, m in results["measured"].items():
        lines += _per_depth_lines(results["cases"][name], m)
    lines += ["## Figures", ""] + [f"- `{Path(p).name}`" for p in results["figures"]]
    return "\n".join(lines) + "\n"


def run(out: str | Path, *, depths=DEPTHS, rays_per_particle: int = 20000,
        diagnostics: bool = True, cache_dir: str | Path | None = None,
        progress=None) -> dict:
    """Run the depth study; write JSON, Markdown and Figs 5.2-5.4 (PNG) to ``out``.

    Files: ``depth_study.json``, ``depth_study.md``, ``fig_5_2_external.png``,
    ``fig_5_3_internal.png``, ``fig_5_4_internal_focus.png``.

    Parameters
    ----------
    out : path
        Output folder (created).
    depths : array_like
        True depths, metres (default -10 … +10 mm in 1 mm steps).
    rays_per_particle : int
        Ray-tracer samples per image.
    diagnostics : bool
        Also run the "thesis" back side with the default light-field aperture.
    cache_dir : path, optional
        Weight cache folder (default: none, weights built in memory).
    progress : callable, optional
        ``progress(case_name, seconds)`` after each case.

    Returns
    -------
    dict
        A summary: output paths, the slopes per case and correction (±10 mm), Z* and seconds.
    """
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cases = study_cases(diagnostics=diagnostics)
    measured = {}
    for case in cases:
        measured[case.name] = measure_depths(case, depths, rays_per_particle=rays_per_particle,
                                             cache_dir=cache_dir)
        if progress is not None:
            progress(case.name, measured[case.name]["seconds"])
    by = {c.name: c for c in cases}
    plate = by["plate_thesis"].camera
    cam0 = by["none"].camera
    geometry = {"f_number": cam0.main_lens.f_number, "si_eff_mm": cam0.image_distance * 1e3,
                "so_eff_mm": cam0.object_distance * 1e3,
                "lenslets": cam0.microlens_array.rows,
                "l2_mm": by["external"].camera.interface_distance * 1e3,
                "l3_mm": plate.l3 * 1e3, "z_star_mm": focus_crossing_depth(plate) * 1e3,
                "si_at_7mm_mm": float(image_distance_of(plate, THESIS_DISCONTINUITY)) * 1e3,
                "focus_region": dict(zip((np.asarray(depths) * 1e3).round(3).tolist(),
                                         focus_region(plate, depths).tolist(), strict=True))}
    results = {
        "study": "thesis §5.1-5.2 depth study", "rays_per_particle": rays_per_particle,
        "geometry": geometry,
        "cases": {c.name: {"label": c.label, "note": c.note, "camera": c.camera.to_dict(),
                           "reconstruction": as_dict(c.settings),
                           "particles": as_dict(STUDY_PARTICLES),
                           "corrections": {k: v.to_dict() for k, v in c.corrections.items()}}
                  for c in cases},
        "measured": measured,
        "table_5_1": table_5_1(cases, measured),
        "table_5_2": table_5_2(cases, measured),
    }
    results["figures"] = [str(p) for p in figures(cases, measured, out)]
    results["seconds"] = time.perf_counter() - t0
    write_json(out / "depth_study.json", results)
    write_text(out / "depth_study.md", markdown(results))
    slopes = {f"{r['case']} {r['correction']}": round(r["slope"], 4)
              for r in results["table_5_1"] if r["fit_range"] == "±10 mm"}
    return {"out": str(out), "figures": results["figures"],
            "json": str(out / "depth_study.json"), "markdown": str(out / "depth_study.md"),
            "slopes_10mm": slopes, "z_star_mm": round(geometry["z_star_mm"], 4),
            "errors": {k: v["errors"] for k, v in measured.items() if v["errors"]},
            "seconds": round(results["seconds"], 1)}

