"""PNG figures for people: calibration reports, volume slices, validation plots.

Matplotlib with the non-interactive Agg backend; every function writes one PNG atomically and
returns its path. Nothing here is imported by the numerical stages.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plenopiv.products.files import atomic_path


def _figure(*args, margins=None, **kw):
    """A new figure: laid out by matplotlib's constrained layout, or by fixed ``margins``.

    ``margins`` (``Figure.subplots_adjust`` keywords, fractions of the figure) serve the
    figures drawn for every pair: the constrained layout measures every text of the figure
    and draws it twice, which is slow for figures drawn this often.
    """
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    if margins is None:
        return plt, plt.figure(*args, layout="constrained", **kw)
    fig = plt.figure(*args, **kw)
    fig.subplots_adjust(**margins)
    return plt, fig


def _save(plt, fig, path) -> Path:
    p = Path(path)
    with atomic_path(p) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return p


def calibration_report(report, image, path) -> Path:
    """Four panels: focal-spot residual map, residual histogram, lattice detail, S_i table.

    Parameters
    ----------
    report : plenopiv.calibration.calibrate.CalibrationReport
    image : ndarray
        The focal-point image (for the lattice detail).
    """
    plt, fig = _figure(figsize=(13, 9.5))
    _residual_map(fig, fig.add_subplot(2, 2, 1), report)
    _residual_histogram(fig.add_subplot(2, 2, 2), report)
    _lattice_detail(fig.add_subplot(2, 2, 3), report, image)
    _text_panel(fig, fig.add_subplot(2, 2, 4), _calibration_lines(report))
    return _save(plt, fig, path)


def _text_panel(fig, ax, lines, *, fontsize: float = 9.0, margin_pt: float = 6.0):
    """Monospace ``lines`` from the top-left corner of ``ax`` (axis off), wrapped to fit.

    The panel's width is measured once the figure is laid out: from the axes' left edge to
    the figure's right edge, less ``margin_pt`` (the text takes no part in the layout, which
    therefore stays as measured). A line too long for it wraps at spaces,
    its continuation indented two characters past the line's own indent.
    """
    import textwrap

    from matplotlib.font_manager import FontProperties

    ax.axis("off")
    fig.draw_without_rendering()          # the layout, so that the box is final
    renderer = fig.canvas.get_renderer()
    x0 = ax.get_window_extent(renderer).x0
    room = fig.bbox.width - x0 - margin_pt * fig.dpi / 72.0
    font = FontProperties(family="monospace", size=fontsize)
    char = renderer.get_text_width_height_descent("M" * 20, font, ismath=False)[0] / 20
    width = max(20, int(room // char))
    out = []
    for line in lines:
        indent = " " * (len(line) - len(line.lstrip(" ")) + 2)
        out += textwrap.wrap(line, width=width, subsequent_indent=indent,
                             break_on_hyphens=False) or [""]
    text = ax.text(0.0, 1.0, "\n".join(out), va="top", family="monospace", fontsize=fontsize,
                   transform=ax.transAxes)
    text.set_in_layout(False)     # the layout stays the one measured
    return text


def _residual_map(fig, ax, report) -> None:
    """Focal-spot residuals (pixels) over the sensor, coloured by their length."""
    cal, fit = report.calibration, report.focal_fit
    pp = cal.camera.sensor.pixel_pitch
    if fit is not None:
        spots = report.fit_spots_px
        res_px = np.hypot(*fit.residual.T) / pp
        sc = ax.scatter(spots[:, 1], spots[:, 0], c=res_px, s=2, cmap="viridis",
                        vmax=np.percentile(res_px, 99))
        fig.colorbar(sc, ax=ax, label="|residual| (px)")
        ax.set_ylim(cal.camera.sensor.rows, 0)
        ax.set_xlim(0, cal.camera.sensor.cols)
    ax.set_title("focal-spot residual (measured - fitted model)")
    ax.set_xlabel("col (px)")
    ax.set_ylabel("row (px)")
    ax.set_aspect("equal")


def _residual_histogram(ax, report) -> None:
    """Histograms of the row and column residuals, pixels."""
    cal, fit = report.calibration, report.focal_fit
    pp = cal.camera.sensor.pixel_pitch
    if fit is not None:
        ax.hist(fit.residual[:, 1] / pp, bins=80, alpha=0.6, label="col")
        ax.hist(fit.residual[:, 0] / pp, bins=80, alpha=0.6, label="row")
        ax.legend()
    ax.set_xlabel("residual (px)")
    ax.set_title(f"rms residual {cal.rms_residual_px:.4f} px")


def _lattice_detail(ax, report, image) -> None:
    """The image's centre with the measured spots and the fitted lattice over it."""
    lat = report.focal_lattice
    r0, c0 = (np.array(image.shape) // 2).astype(int)
    h = int(4 * lat.lenslet_pitch_px)
    crop = np.asarray(image, float)[r0 - h:r0 + h, c0 - h:c0 + h]
    ax.imshow(crop, cmap="gray", extent=(c0 - h - 0.5, c0 + h - 0.5, r0 + h - 0.5, r0 - h - 0.5))
    sel = (np.abs(lat.centres_px[:, 0] - r0) < h) & (np.abs(lat.centres_px[:, 1] - c0) < h)
    ax.plot(lat.centres_px[sel, 1], lat.centres_px[sel, 0], "r+", ms=8, label="measured spot")
    pred = lat.predict(lat.grid_index[sel])
    ax.plot(pred[:, 1], pred[:, 0], "c.", ms=4, label="fitted lattice")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"{lat.grid} lattice, pitch {lat.lenslet_pitch_px:.4f} px, "
                 f"rotation {lat.rotation_rad * 1e3:.3f} mrad")


def _calibration_lines(report) -> list[str]:
    """The text panel: lenslets, both image distances with their uncertainties, lattices."""
    cal = report.calibration
    s = report.summary()
    lines = [f"camera: {cal.camera.name}", f"lenslets: {cal.n_lenslets} "
             f"({report.n_missing} missing, filled)", f"lenslet centres from: "
             f"{report.lenslet_source}", "", "image distance S_i,eff:"]
    if "focal_point" in s:
        f = s["focal_point"]
        lines.append(f"  focal-point method:   {f['image_distance_mm']:.3f} ± "
                     f"{f['sigma_mm']:.3f} mm ({f['back_side']} back side)")
        lines.append(f"    MLA offset {f['offset_um'][0]:.3f}, {f['offset_um'][1]:.3f} µm, "
                     f"rotation {f['rotation_rad'] * 1e6:.2f} µrad")
    if "magnification" in s:
        m = s["magnification"]
        lines.append(f"  magnification method: {m['image_distance_mm']:.3f} ± {m['sigma_mm']:.3f}"
                     f" mm  (M = {m['magnification']:.4f}, {m['n_ticks']} ticks)")
        lines.append(f"    depth of focus ± {m['sigma_depth_of_focus_mm']:.3f} mm, "
                     f"height ± {m['sigma_height_mm']:.3f} mm")
    lines += ["", f"kept: {s['image_distance_mm']:.3f} mm ({s['method']})", "",
              "lattice quality:"]
    for name, q in s.get("lattice", {}).items():
        lines.append(f"  {name}: {q['grid']}, rms {q['rms_residual_px']:.4f} px "
                     f"({100 * q['rms_residual_pitch']:.2f} % of pitch), "
                     f"{q['n_missing']} missing ({100 * q['missing_fraction']:.1f} %)")
        lines.append(f"    {q['n_fitted']} of {q['n_spots']} spots fitted, "
                     f"{q['n_off_lattice']} off-lattice, spot centres: "
                     f"{q.get('spot_method', '?')}, phase bias {q['phase_bias_px']:.4f} px")
    for n in report.notes:
        lines += ["", "note: " + n[:110]]
    return lines


def volume_slices(volume, x, y, z, path, *, particles=None, title="") -> Path:
    """Plot the x-y slice nearest Z = 0 and the x-z slice through the brightest row.

    Each slice has a colour bar of the reconstructed intensity; the particles found within
    one voxel of each slice are marked and named in a legend.

    ``volume`` is ``[z, y, x]``; x, y, z are voxel-centre coordinates in metres (the
    volume's grid); ``particles`` (N, 3) are (x, y, z) in metres on the same grid.
    """
    plt, fig = _figure(figsize=(13, 5.5), margins=dict(left=0.06, right=0.97, bottom=0.11,
                                                       top=0.86, wspace=0.28))
    v = np.asarray(volume, float)
    x, y, z = (np.asarray(a, float) for a in (x, y, z))
    iz = int(np.argmin(np.abs(z)))
    iy = int(np.argmax(v.sum(axis=(0, 2))))
    ext_xy = (x[0] * 1e3, x[-1] * 1e3, y[-1] * 1e3, y[0] * 1e3)
    ext_xz = (x[0] * 1e3, x[-1] * 1e3, z[-1] * 1e3, z[0] * 1e3)
    vmax = float(np.percentile(v[v > 0], 99.9)) if (v > 0).any() else 1.0
    p = np.asarray(particles, float).reshape(-1, 3) if particles is not None else np.zeros((0, 3))

    def step(a):
        return abs(a[1] - a[0]) if len(a) > 1 else np.inf

    ax = fig.add_subplot(1, 2, 1)
    im = ax.imshow(v[iz], cmap="magma", extent=ext_xy, aspect="equal", vmin=0, vmax=vmax)
    fig.colorbar(im, ax=ax, label="reconstructed intensity (image counts per voxel)")
    near = np.abs(p[:, 2] - z[iz]) <= step(z)
    if near.any():
        ax.plot(p[near, 0] * 1e3, p[near, 1] * 1e3, "c+", ms=7,
                label=f"particles within one voxel of Z = {z[iz] * 1e3:.2f} mm ({near.sum()})")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"x-y slice at Z = {z[iz] * 1e3:.2f} mm")
    ax.set_xlabel("X (mm)")
    ax.set_ylabel("Y (mm)")
    ax = fig.add_subplot(1, 2, 2)
    im = ax.imshow(v[:, iy, :], cmap="magma", extent=ext_xz, aspect="auto", vmin=0, vmax=vmax)
    fig.colorbar(im, ax=ax, label="reconstructed intensity (image counts per voxel)")
    near = np.abs(p[:, 1] - y[iy]) <= step(y)
    if near.any():
        ax.plot(p[near, 0] * 1e3, p[near, 2] * 1e3, "c+", ms=7,
                label=f"particles within one voxel of Y = {y[iy] * 1e3:.2f} mm ({near.sum()})")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_title(f"x-z slice at Y = {y[iy] * 1e3:.2f} mm (brightest row)")
    ax.set_xlabel("X (mm)")
    ax.set_ylabel("Z (mm), + away from camera")
    if title:
        fig.suptitle(title_text(title))
    return _save(plt, fig, path)


def _nice(value: float) -> float:
    """A round number (1, 2 or 5 times a power of ten) near ``value`` (> 0)."""
    if not (np.isfinite(value) and value > 0):
        return 1.0
    e = np.floor(np.log10(value))
    m = value / 10**e
    return float((1 if m < 1.5 else 2 if m < 3.5 else 5 if m < 7.5 else 10) * 10**e)


def vector_slices(vectors, path, *, title="") -> Path:
    """Plot in-plane vectors on the x-y plane nearest Z = 0 and the x-z plane through the middle.

    ``vectors`` is a :class:`~plenopiv.products.vectors.VectorResult`: displacements in
    metres, shown in mm, or velocities in m/s when it has ``dt``. Rejected vectors are drawn
    grey where they were replaced and left out where they are NaN. ``title`` names the pair.

    The x-y arrows are coloured by the depth component w, which they cannot show, on a
    diverging map centred at 0 (red away from the camera, blue towards it); the x-z arrows,
    which show the depth motion themselves, by the speed ``|(u, v, w)|`` on a perceptual
    map (viridis): the out-of-plane v of the flows the chain is validated on (vortices about
    y) is zero, and colouring by it showed noise near the grey centre of a diverging map.
    Both colour scales end at the 98th percentile of the valid vectors (symmetric about 0
    for w), so that a few outliers do not wash the colours out. The arrow scale (a round
    number near the 90th percentile of the speed) sits above each panel's top-left corner,
    outside the frame.
    """
    plt, fig = _figure(figsize=(14, 6), margins=dict(left=0.06, right=0.97, bottom=0.1,
                                                     top=0.82, wspace=0.25))
    x, y, z = (np.asarray(a) * 1e3 for a in (vectors.x, vectors.y, vectors.z))
    ok = np.asarray(vectors.valid, bool)
    iz = int(np.argmin(np.abs(z)))
    iy = len(y) // 2
    if vectors.dt is None:
        scale, unit, quantity = 1e3, "mm", "displacement"
    else:
        scale, unit, quantity = 1.0 / vectors.dt, "m/s", "velocity"
    u, v, w = (np.asarray(c, float) * scale for c in (vectors.u, vectors.v, vectors.w))
    finite = np.isfinite(u) & np.isfinite(v) & np.isfinite(w)
    speed = np.sqrt(u**2 + v**2 + w**2)
    good_speed = speed[finite & ok]
    key = _nice(float(np.percentile(good_speed, 90))) if good_speed.size else 1.0
    w_lim = _robust_limit(np.abs(w[finite & ok]))
    panels = (
        (1, "x-y", f"Z = {z[iz]:.2f} mm", x, y, (u[iz], v[iz]), w[iz], ok[iz],
         dict(cmap="RdBu_r", clim=(-w_lim, w_lim)),
         f"w, out-of-plane {quantity} ({unit})", "Y (mm)"),
        (2, "x-z", f"Y = {y[iy]:.2f} mm", x, z, (u[:, iy], w[:, iy]), speed[:, iy], ok[:, iy],
         dict(cmap="viridis", clim=(0.0, _robust_limit(good_speed))),
         f"speed |(u, v, w)| ({unit})", "Z (mm), + away from camera"),
    )
    for pos, plane, where, ha, va, (pu, pv), colour, good, cmap, clabel, ylabel in panels:
        ax = fig.add_subplot(1, 2, pos)
        H, V = np.meshgrid(ha, va, indexing="xy")
        q = ax.quiver(H[good], V[good], pu[good], pv[good], colour[good], angles="xy",
                      scale_units="xy", scale=key / (0.8 * _spacing(ha)), **cmap)
        bad = ~good & np.isfinite(pu) & np.isfinite(pv)
        if bad.any():
            ax.quiver(H[bad], V[bad], pu[bad], pv[bad], color="0.6", angles="xy",
                      scale_units="xy", scale=key / (0.8 * _spacing(ha)))
        fig.colorbar(q, ax=ax, label=clabel)
        ax.set_title(f"{plane} plane at {where}" + (" (grey: replaced)" if bad.any() else ""),
                     loc="left", pad=KEY_BAND_PT)
        ax.set_xlabel("X (mm)")
        ax.set_ylabel(ylabel)
        ax.invert_yaxis()
        if plane == "x-y":
            ax.set_aspect("equal")
        _arrow_key(fig, ax, q, key, 0.8 * _spacing(ha), f"{key:g} {unit}")
    fig.suptitle(title_text(title, f"{quantity} ({unit})"))
    return _save(plt, fig, path)


#: Points between a panel's frame and its title, where the arrow scale sits.
KEY_BAND_PT = 24.0
#: Points from the frame's top edge to the arrow scale's centre line.
KEY_GAP_PT = 9.0


def _arrow_key(fig, ax, q, key: float, length: float, label: str):
    """The arrow scale of ``q`` above the top-left corner of ``ax``, outside its frame.

    ``length``: the arrow's length in data units along x. The key is placed in figure
    coordinates once the axes has its final box (after its aspect), its tail over the
    frame's left edge and its label to the right, clearing the frame by the same few points
    on every panel shape.
    """
    ax.autoscale_view()
    ax.apply_aspect()
    box = ax.get_position()
    (x0, _), (x1, _) = ax.transData.transform([(0.0, 0.0), (length, 0.0)])
    dx = abs(x1 - x0) / fig.bbox.width            # the key's tip is at X (labelpos "E")
    dy = KEY_GAP_PT / 72.0 / fig.get_figheight()
    return ax.quiverkey(q, box.x0 + dx, box.y1 + dy, key, label, labelpos="E",
                        coordinates="figure")


def _robust_limit(values) -> float:
    """The 98th percentile of ``values`` (ignoring NaN), or 1 where there is none or it is 0."""
    a = np.asarray(values, float)
    a = a[np.isfinite(a)]
    lim = float(np.percentile(a, 98)) if a.size else 0.0
    return lim if lim > 0 else (float(a.max()) if a.size and a.max() > 0 else 1.0)


def title_text(*parts: str, sep: str = ": ") -> str:
    """A title of ``parts`` (empty ones left out) in which no word follows itself.

    ``title_text("pair pair", "velocity (m/s)")`` is ``"pair: velocity (m/s)"``: a pair
    named "pair" is not the "pair pair" of ``f"pair {name}"``. Words compare without case;
    a word with punctuation after it ("pair:") ends the run.

    >>> title_text("pair pair: vectors")
    'pair: vectors'
    """
    text = sep.join(p for p in parts if p)
    out: list[str] = []
    for word in text.split(" "):
        bare = word.rstrip(":;,.")
        if out and out[-1].isalpha() and bare.isalpha() and bare.lower() == out[-1].lower():
            out[-1] = word
        else:
            out.append(word)
    return " ".join(out)


def _spacing(a) -> float:
    a = np.asarray(a, float)
    return float(abs(a[1] - a[0])) if a.size > 1 else 1.0


def vector_comparison(x, y, z, measured, truth, valid, path, *, voxel, title="") -> Path:
    """Measured against true displacement on the x-z plane through the middle of the volume.

    ``x, y, z``: window-centre coordinates, metres; ``measured``, ``truth``: displacement
    fields of shape (3, nz, ny, nx) in voxels (u, v, w); ``valid``: (nz, ny, nx) mask;
    ``voxel``: (dx, dy, dz), metres, for the axis labels. Rows: true, measured, error;
    columns: u (lateral) and w (depth), each with the in-plane vectors drawn on top.
    """
    plt, fig = _figure(figsize=(11, 11), margins=dict(left=0.08, right=0.97, bottom=0.05,
                                                      top=0.92, wspace=0.3, hspace=0.35))
    x, z = np.asarray(x) * 1e3, np.asarray(z) * 1e3
    iy = len(y) // 2
    ok = np.asarray(valid, bool)[:, iy]
    err = np.where(ok, measured[:, :, iy] - truth[:, :, iy], np.nan)
    rows = (("true", truth[:, :, iy]), ("measured", np.where(ok, measured[:, :, iy], np.nan)),
            ("measured - true", err))
    X, Z = np.meshgrid(x, z, indexing="xy")
    for r, (name, f) in enumerate(rows):
        for c, (comp, label) in enumerate(((0, "u"), (2, "w"))):
            ax = fig.add_subplot(3, 2, 2 * r + c + 1)
            if r < 2:
                lim = np.nanmax(np.abs(truth[comp])) or 1.0
            else:
                lim = max(np.nanmax(np.abs(err[comp])) if np.isfinite(err[comp]).any()
                          else 0.0, 0.1)
            m = ax.pcolormesh(X, Z, f[comp], cmap="coolwarm", vmin=-lim, vmax=lim,
                              shading="nearest")
            fig.colorbar(m, ax=ax, label=f"{label} (voxels)")
            if r < 2:
                ax.quiver(X, Z, np.nan_to_num(f[0]), np.nan_to_num(f[2]), angles="xy",
                          color="k", width=0.003)
            ax.set_title(f"{name} {label} at Y = {y[iy] * 1e3:.2f} mm")
            ax.set_xlabel("X (mm)")
            ax.set_ylabel("Z (mm), + away from camera")
            ax.invert_yaxis()
    if title:
        fig.suptitle(f"{title_text(title)}\nvoxel {voxel[0] * 1e3:.3f} x {voxel[1] * 1e3:.3f} x "
                     f"{voxel[2] * 1e3:.3f} mm")
    return _save(plt, fig, path)
