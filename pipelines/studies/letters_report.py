"""Rendering of the letters study (:mod:`pipelines.studies.letters`): figures and Markdown.

Draws what :func:`pipelines.studies.letters.analyse` computed and writes the numbers of its
:func:`~pipelines.studies.letters.summary`; the secondary α axis uses the study's own
conversions (:func:`~pipelines.studies.letters.source_alpha`,
:func:`~pipelines.studies.letters.plenopiv_alpha`). :func:`run` runs the study and writes
the files (this module imports the study, never the other way round).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipelines.studies.letters import (
    ALPHAS,
    LETTERS_ROI,
    SOURCE_ALPHA,
    analyse,
    plenopiv_alpha,
    refocused_planes,
    source_alpha,
    summary,
)
from pipelines.studies.letters_data import load_letters
from pipelines.studies.output import pyplot, savefig, write_json, write_text

#: Where each perspective view sits in the 3 × 3 panel grid of the views figure.
VIEW_LAYOUT = {"top": (0, 1), "left": (1, 0), "centre": (1, 1), "right": (1, 2),
               "bottom": (2, 1)}


def _view_panels(axes, res: dict, summ: dict) -> None:
    """The five perspective views around the centre, the letters ROI on the centre view."""
    from matplotlib.patches import Rectangle

    views = res["views"]
    valid = np.concatenate([v[np.isfinite(v)] for v in views.values()])
    lo, hi = np.percentile(valid, [1, 99])
    for ax in axes.ravel():
        ax.axis("off")
    for name, (i, j) in VIEW_LAYOUT.items():
        ax = axes[i, j]
        ax.imshow(views[name], cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
        u = summ["views"]["u_mm"][name]
        ax.set_title(f"{name}: u = ({u[0]:+.2f}, {u[1]:+.2f}) mm")
        ax.axis("on")
        ax.set_xticks([])
        ax.set_yticks([])
    r = LETTERS_ROI
    axes[1, 1].add_patch(Rectangle((r[1].start - 0.5, r[0].start - 0.5), r[1].stop - r[1].start,
                                   r[0].stop - r[0].start, fill=False, ec="tab:red", lw=1))


def _raw_panel(ax, image) -> None:
    """A crop of the flat-fielded raw image (the upper 'ab')."""
    raw = np.asarray(image)
    crop = np.nan_to_num(raw[130:350, 420:800], nan=0.0)
    ax.imshow(crop, cmap="gray", vmin=0, vmax=np.nanpercentile(raw, 99))
    ax.set_title("flat-fielded raw, rows 130-350, cols 420-800\n(upper 'ab'; NaN: black)",
                 fontsize=9)
    ax.axis("on")
    ax.set_xticks([])
    ax.set_yticks([])


def _parallax_panel(ax, res: dict) -> None:
    """View shifts against aperture position, with the fitted slopes."""
    ax.axis("on")
    par = res["parallax"]
    ax.plot(par.u * 1e3, par.shift_x, "o", label="x: column shift, views (u, 0)")
    ax.plot(par.u * 1e3, par.shift_y, "s", label="y: row shift, views (0, u)")
    pitch = res["lattice_pitch"]
    for slope, p, st in zip(par.slope, pitch[::-1], ("C0-", "C1-"), strict=True):
        ax.plot(par.u * 1e3, slope * par.u / p, st, lw=0.8)
    ax.set_xlabel("aperture position u (mm)")
    ax.set_ylabel("shift vs centre view (lenslets)")
    ax.set_title(f"parallax of the letters: α = {par.alpha_mean:.4f}")
    ax.legend(fontsize=7)


def views_figure(res: dict, summ: dict, path: Path) -> Path:
    """Perspective views, a raw crop and the parallax of the letters."""
    plt = pyplot()
    fig, axes = plt.subplots(3, 3, figsize=(12.5, 9.6), gridspec_kw={"hspace": 0.35,
                                                                      "wspace": 0.3})
    _view_panels(axes, res, summ)
    _raw_panel(axes[0, 0], res["image"])
    _parallax_panel(axes[0, 2], res)
    fig.suptitle("plenoptomos letters: perspective views (20 × 26 lenslets; red: letters ROI)")
    return savefig(fig, path)


def focus_curve_figure(res: dict, path: Path) -> Path:
    """Sharpness of the refocused letters against α, with the peak, parallax and source's α."""
    plt = pyplot()
    geo = res["geometry"]
    par = res["parallax"]
    sweep = res["sweep"]
    a = np.asarray(sweep["alpha"])
    fig, ax = plt.subplots(figsize=(8.5, 4.8))
    g = np.asarray(sweep["gradient"])
    lap = np.asarray(sweep["laplacian"])
    ax.plot(a, g / g.max(), "-", color="C0", label="gradient energy, letters (Fourier refocus)")
    ax.plot(a, lap / lap.max(), "--", color="C0", lw=1,
            label="variance of Laplacian, letters (Fourier)")
    ga = np.asarray(sweep["gradient_all"])
    ax.plot(a, ga / ga.max(), ":", color="C2", label="gradient energy, whole view (Fourier)")
    if res["splat"] is not None:
        sg = np.asarray(res["splat"]["gradient"])
        ax.plot(a, sg / sg.max(), "-", color="C3", lw=1,
                label="gradient energy, letters (splat refocus)")
    peak = res["peak"]
    src_in = plenopiv_alpha(SOURCE_ALPHA, **geo)
    ax.axvline(peak, color="C0", lw=0.8)
    ax.axvline(par.alpha_mean, color="C1", lw=0.8, ls="--")
    ax.axvline(src_in, color="k", lw=0.8, ls=":")
    ax.axvline(1.0, color="0.6", lw=0.5)
    ymin = ax.get_ylim()[0]
    ax.text(peak, ymin, f" peak {peak:.4f}\n (source α {source_alpha(peak, **geo):.3f})",
            color="C0", fontsize=8, va="bottom")
    ax.text(par.alpha_mean, 0.55, f" parallax\n {par.alpha_mean:.4f}", color="C1", fontsize=8)
    ax.text(src_in, 0.4, f" source's α = {SOURCE_ALPHA}\n = {src_in:.4f} here", fontsize=8)
    ax.set_xlabel("plenopiv α (synthetic lenslet plane at α S_i; > 1: in front)")
    ax.set_ylabel("sharpness / its maximum")
    sec = ax.secondary_xaxis("top", functions=(lambda x: source_alpha(x, **geo),
                                               lambda x: plenopiv_alpha(x, **geo)))
    sec.set_xlabel("source's α (plenoptomos, object space, cone)")
    ax.legend(fontsize=7, loc="lower left")
    return savefig(fig, path)


def refocused_figure(planes: list[tuple], path: Path) -> Path:
    """The refocused images ``(title, image)`` side by side, one grey scale for all."""
    plt = pyplot()
    imgs = [im for _, im in planes]
    fin = np.concatenate([i[np.isfinite(i)] for i in imgs])
    lo, hi = np.percentile(fin, [1, 99])
    fig, axes = plt.subplots(1, len(planes), figsize=(3.2 * len(planes), 3.0))
    for ax, (title, im) in zip(axes, planes, strict=True):
        ax.imshow(im, cmap="gray", vmin=lo, vmax=hi, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle("Fourier shift-and-add refocus (plenopiv α)")
    return savefig(fig, path)


def figures(res: dict, summ: dict, planes: list[tuple], out: Path) -> list[Path]:
    """Write the views, focus-curve and refocused-images figures to ``out``; return paths.

    ``planes`` are :func:`pipelines.studies.letters.refocused_planes` of ``res``.
    """
    return [views_figure(res, summ, out / "letters_views.png"),
            focus_curve_figure(res, out / "letters_focus_curve.png"),
            refocused_figure(planes, out / "letters_refocused.png")]


def _preprocess_lines(p: dict | None) -> list[str]:
    """What the preprocess stage did to the raw image (:func:`~pipelines.studies.letters.
    preprocessed_image`)."""
    if not p:
        return []
    fl = p["flat"]
    return [f"- the raw image through `plenopiv.preprocess` as `[preprocess]` dark, white and "
            f"`hot_pixels = \"auto\"` would: the dark frame subtracted, {p['dark_hot']} hot and "
            f"{p['dark_cold']} cold pixels of the dark, {p['white_dead']} dead and "
            f"{p['white_stuck']} stuck pixels of the white and {p['hot_pixels_in_image']} of "
            f"the image repaired within their micro-images",
            f"- flat field of the white on micro-images of {2 * p['micro_image_radius_px']:.1f} px "
            f"(f/{p['f_number']:.1f}, the pupil the micro-images measure): each micro-image's "
            f"plateau over the median, {fl['reference_counts']:.1f} counts (throughput rms "
            f"{fl['throughput_rms']:.2%}), the white's gap level {fl['black_level_counts']:.0f} "
            f"counts taken off; {fl['masked_pixels']} pixels masked (gaps, rims below "
            f"{fl['rim_fraction']:.0%} of the plateau), left out of the light field; the "
            "image keeps its counts", ""]


def markdown(s: dict) -> str:
    """The study's Markdown report from its :func:`~pipelines.studies.letters.summary`."""
    c, f, p = s["calibration"], s["focus"], s["parallax"]
    lines = [
        "# Light field on the plenoptomos letters image (real plenoptic 1.0 camera)", "",
        "Generated by `python pipelines/validate_letters.py` (`pipelines.studies.letters`). "
        "Data: `shared/data/plenoptomos_letters_ULF` (cicwi/plenoptomos, GPL-3.0; not in this "
        "repository).", "",
        "## Calibration from the white image", "",
        f"- grid {c['grid']}, {c['n_spots']} micro-images ({c['n_complete']} complete), "
        f"lattice {c['lattice_shape'][0]} × {c['lattice_shape'][1]}",
        f"- pitch {c['pitch_px'][0]:.4f} × {c['pitch_px'][1]:.4f} px "
        f"(± {c['pitch_std_px'][0]:.4f}), rotation {c['rotation_rad'] * 1e3:.2f} mrad, "
        f"rms residual {c['rms_residual_px']:.3f} px",
        f"- k = pitch · p_p / p_m = {c['k']:.5f} → S = f̄/(k − 1) = "
        f"{c['image_distance_from_pitch_mm']:.1f} mm (used); nominal lens-to-MLA "
        f"{c['image_distance_nominal_mm']:.0f} mm would give a pitch of "
        f"{c['pitch_px_if_nominal']:.3f} px",
        f"- micro-image diameter {c['micro_image_diameter_px']:.1f} px; a 6.6 mm stop seen from "
        f"S would make {c['micro_image_diameter_px_if_6p6mm_stop']:.1f} px: the effective pupil "
        f"is {c['pupil_diameter_from_micro_images_mm']:.2f} mm. The light field uses "
        f"f/{c['f_number_used']:.1f} (6.6 mm), i.e. the well-lit inner pixels.", "",
        "## Preprocessing", "",
        *_preprocess_lines(s.get("preprocess")),
        "## Views and parallax", "",
        f"- views {s['light_field']['views_shape'][0]} × {s['light_field']['views_shape'][1]} "
        f"lenslets; letters ROI rows {s['views']['roi'][0]}, cols {s['views']['roi'][1]}",
        "- NCC with the central view: " + ", ".join(
            f"{k} {v:.3f}" for k, v in s["views"]["ncc_with_centre"].items()),
        f"- parallax slope ds/du = {p['slope'][0]:.4f} (x), {p['slope'][1]:.4f} (y) → "
        f"α = {p['alpha'][0]:.4f}, {p['alpha'][1]:.4f} (source's α {p['alpha_source']:.4f})", "",
        "## Focus sweep (Fourier shift-and-add refocus, letters ROI)", "",
        f"- peak α (gradient energy) = {f['peak']['gradient']:.4f} → source's α "
        f"{f['peak_alpha_source']['gradient']:.4f}; Laplacian {f['peak']['laplacian']:.4f}; "
        f"whole view {f['peak']['gradient_all']:.4f}",
        f"- with the nominal S = 400 mm the same plane is α = {f['peak_alpha_if_nominal_S']:.4f}",
        f"- the source's α = {f['source_alpha']} is α = {f['source_alpha_in_plenopiv']:.4f} here",
        f"- peak plane: α S_i = {f['peak_plane']['refocus_image_distance_mm']:.1f} mm, object "
        f"distance {f['peak_plane']['object_distance_mm']:.1f} mm, Z = "
        f"{f['peak_plane']['depth_mm']:.1f} mm (thin lens, f = 200 mm, S_i from the pitch)", "",
        "| α (plenopiv) | source's α | gradient energy | variance of Laplacian |"
        + (" splat gradient energy |" if "focus_splat" in s else ""),
        "|---|---|---|---|" + ("---|" if "focus_splat" in s else ""),
    ]
    for i, a in enumerate(f["alpha"]):
        row = (f"| {a:.3f} | {f['alpha_source'][i]:.4f} | {f['gradient'][i]:.5g} | "
               f"{f['laplacian'][i]:.5g} |")
        if "focus_splat" in s:
            row += f" {s['focus_splat']['gradient'][i]:.5g} |"
        lines.append(row)
    if "focus_splat" in s:
        sp = s["focus_splat"]
        top = sp["alpha"][int(np.argmax(sp["gradient"]))]
        lines += ["", f"The splat refocus (bilinear onto a fixed grid) has its maximum at "
                  f"α = {top:.3f}, on a kink: at α = 1 all rays of a lenslet land on one point, "
                  "so its resampling changes character there and pulls the peak onto α = 1 "
                  "whatever the depth (see `plenopiv.lightfield.refocus`; the ray-traced "
                  "particle test in `tests/studies/test_letters.py` shows the Fourier "
                  "refocus returning a known plane to 0.001 in α)."]
    return "\n".join(lines) + "\n"


def run(out_dir: str | Path, *, data_dir: str | Path | None = None, alphas=ALPHAS) -> dict:
    """Run the study; write ``letters.json``, ``letters.md`` and PNG figures to ``out_dir``.

    Returns a short summary (paths and the headline numbers).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    data = load_letters(data_dir)
    res = analyse(data, alphas=alphas)
    summ = summary(res, data.optics)
    write_json(out / "letters.json", summ)
    write_text(out / "letters.md", markdown(summ))
    paths = figures(res, summ, refocused_planes(res), out)
    return {"out": str(out), "figures": [str(p) for p in paths],
            "pitch_px": summ["calibration"]["pitch_px"],
            "image_distance_from_pitch_mm": summ["calibration"]["image_distance_from_pitch_mm"],
            "peak_alpha": summ["focus"]["peak"]["gradient"],
            "peak_alpha_source": summ["focus"]["peak_alpha_source"]["gradient"],
            "parallax_alpha": summ["parallax"]["alpha_mean"]}

