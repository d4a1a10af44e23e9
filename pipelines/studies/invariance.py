"""Invariance of the chain to the camera and to the flow's orientation, one property at a time.

Each variation is the demo's Oseen case (``VortexCase`` of plenopiv.workflow.vortex_case,
camera ``small_m1``, correlation uncertainty) with one thing changed from a reference: the
vortex's axis (x, y, z, oblique) or its centre, the recording's f-number (micro-images that
fill or under-fill their cells), the image distance (a magnification other than -1), the
lenslet array's rotation or offset, a hexagonal array, voxels off or unlike the footprints;
and all of a second camera's changes together. Every case runs calibrate -> reconstruct ->
correlate and is scored against the truth: gain, bias and rms per component, the
calibration's S_i, lenslet centres and focal spots, and the particles of volume A against the
true positions (rms and scale per axis), which locate a lateral error before the PIV.
``pipelines/validate_invariance.py`` writes ``docs/validation/invariance.*``.
"""

from __future__ import annotations

import shutil
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np

from pipelines.studies.field_quality import match_particles
from pipelines.studies.output import (
    fmt,
    pyplot,
    savefig,
    section,
    table,
    write_json,
    write_text,
)
from plenopiv.calibration.model import Calibration
from plenopiv.camera.resolution import footprint, resolution_cell
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume
from plenopiv.workflow.vortex_case import VortexCase, aligned_grid, case_camera, run_case

__all__ = ["REFERENCE", "VARIATIONS", "base_case", "markdown", "measure", "particle_errors",
           "run", "summarise"]

#: The second camera: S_i 105 mm (M = -1.1), f/2.2, the lattice rotated 1.5 mrad and offset
#: a few micrometres, the vortex about x.
OTHER_CAMERA = {"image_distance": 105e-3, "f_number": 2.2, "lattice_rotation": 1.5e-3,
                "lattice_offset": (4e-6, -3e-6)}
#: The reference of the camera's variations: the preset, the vortex about x (v carries the
#: lateral motion, u is the vortex's axis).
REFERENCE = "axis x (reference)"
#: Each variation: the fields of :class:`VortexCase` it sets.
VARIATIONS = {
    "axis y (preset)": {"flow_axis": "y"},
    REFERENCE: {"flow_axis": "x"},
    "axis z": {"flow_axis": "z"},
    "axis oblique (1, 1, 1)": {"flow_axis": (1.0, 1.0, 1.0)},
    "axis x, off-centre (0.31, 0.23, 0.17) mm": {"flow_axis": "x",
                                                 "centre_offset": (0.31e-3, 0.23e-3, 0.17e-3)},
    "f/2.0 (filled)": {"flow_axis": "x", "f_number": 2.0},
    "f/2.8 (under-filled)": {"flow_axis": "x", "f_number": 2.8},
    "S_i 105 mm (M = -1.1)": {"flow_axis": "x", "image_distance": 105e-3},
    "rotated 1.5 mrad": {"flow_axis": "x", "lattice_rotation": 1.5e-3},
    "offset (4, -3) um": {"flow_axis": "x", "lattice_offset": (4e-6, -3e-6)},
    "hexagonal": {"flow_axis": "x", "lattice": "hexagonal"},
    "voxel 1.1 footprints": {"flow_axis": "x", "voxel_lateral_factor": 1.1},
    "grid off the footprints by half a voxel": {"flow_axis": "x",
                                                "grid_shift": (0.5, 0.5, 0.5)},
    "S_i 105 mm, voxel 0.125 mm (1.1 footprints)": {"flow_axis": "x", "image_distance": 105e-3,
                                                   "voxel_lateral_factor": 1.1},
    "other camera (all of them)": {"flow_axis": "x", **OTHER_CAMERA},
    "other camera, voxel 0.125 mm": {"flow_axis": "x", **OTHER_CAMERA,
                                     "voxel_lateral_factor": 1.1},
}


def base_case(seed: int = 1) -> VortexCase:
    """The demo's Oseen case with correlation uncertainty (the response is not the subject)."""
    return VortexCase(uncertainty="correlation", seed=int(seed))


def particle_errors(found: np.ndarray, true: np.ndarray, voxel, tolerance) -> dict:
    """Found against true particle positions per axis, in voxels.

    ``found``, ``true`` (N, 3) metres; ``voxel`` (3,) metres; ``tolerance`` (3,) metres, the
    matching ellipsoid (:func:`pipelines.studies.field_quality.match_particles`). Returns the
    matched count, the bias and rms per axis and the ``scale_error`` per axis: the slope of the
    error against the true position (a lateral scale wrong by 1e-3 moves a particle 3 mm off
    the axis by 3 µm).
    """
    pairs = match_particles(true, found, tolerance)
    if len(pairs) < 3:
        return {"n_matched": int(len(pairs)), "bias_vox": [np.nan] * 3,
                "rms_vox": [np.nan] * 3, "scale_error": [np.nan] * 3}
    t, f = true[pairs[:, 0]], found[pairs[:, 1]]
    err = (f - t) / np.asarray(voxel, float)
    slope = [float(np.polyfit(t[:, k], f[:, k] - t[:, k], 1)[0]) for k in range(3)]
    return {"n_matched": int(len(pairs)), "bias_vox": err.mean(axis=0).tolist(),
            "rms_vox": np.sqrt((err ** 2).mean(axis=0)).tolist(), "scale_error": slope}


def _particles(out: Path, case: VortexCase, voxel) -> dict:
    with h5py.File(out / "pair_volume_A.h5", "r") as fh:
        found = np.asarray(fh["particles/position_m"], float).reshape(-1, 3)
    true = np.load(out / "truth_particles.npz")["positions_a"]
    b, z = resolution_cell(Calibration.from_camera(case_camera(case)).effective_camera)
    return particle_errors(found, true, voxel, (b, b, z))


def _calibration_errors(out: Path, case: VortexCase) -> dict:
    """The calibration against the true camera's: S_i, lenslet centres and focal spots, px."""
    cal = Calibration.load(out / "calibration.h5")
    true = Calibration.from_camera(case_camera(case))
    row = {tuple(g): k for k, g in enumerate(np.asarray(true.grid_index).tolist())}
    k = np.array([row.get(tuple(g), -1) for g in np.asarray(cal.grid_index).tolist()])
    ok = k >= 0
    d_centre = cal.centre_px[ok] - true.centre_px[k[ok]]
    d_spot = cal.focal_spot_px[ok] - true.focal_spot_px[k[ok]]
    return {"image_distance_error_mm": (cal.image_distance - true.image_distance) * 1e3,
            "centre_bias_px": d_centre.mean(axis=0).tolist(),
            "centre_rms_px": np.sqrt((d_centre ** 2).mean(axis=0)).tolist(),
            "focal_spot_bias_px": d_spot.mean(axis=0).tolist(),
            "focal_spot_rms_px": np.sqrt((d_spot ** 2).mean(axis=0)).tolist(),
            "n_matched_lenslets": int(ok.sum()), "rms_residual_px": cal.rms_residual_px}


def measure(name: str, seed: int = 1, work: Path | None = None, base=None) -> dict:
    """Run one variation with one seed; its accuracy per component and its diagnostics."""
    case = replace(base_case(seed) if base is None else replace(base, seed=int(seed)),
                   **VARIATIONS[name])
    t0 = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix="invariance_", dir=work))
    try:
        s = run_case(case, tmp)
        e = s["errors"]
        voxel = np.asarray(s["voxel_mm"]) * 1e-3
        return {"variation": name, "seed": int(seed), "changes": VARIATIONS[name],
                "gain": e["gain"], "bias_vox": e["bias_vox"], "rms_vox": e["rms_vox"],
                "true_rms_vox": e["true_rms_vox"], "n_vectors": e["n_vectors"],
                "valid_fraction": e["valid_fraction"], "voxel_mm": s["voxel_mm"],
                "grid_shape": s["grid_shape"], "n_particles": s["n_particles"],
                "calibration": _calibration_errors(tmp, case),
                "by_depth": [{"abs_z_mm": b["abs_z_mm"], "rms_vox": b["rms_vox"],
                              "gain": b["gain"]} for b in e["by_depth"]],
                "particles": _particles(tmp, case, voxel),
                "seconds": round(time.perf_counter() - t0, 1)}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


#: The variations of the focus profile: what changes the band of single-lenslet particles.
FOCUS_VARIATIONS = ("axis y (preset)", "f/2.0 (filled)", "f/2.8 (under-filled)",
                    "S_i 105 mm (M = -1.1)", "rotated 1.5 mrad")
#: Depths of the focus profile, metres.
FOCUS_DEPTHS = tuple(np.round(np.arange(-1.5, 1.51, 0.25) * 1e-3, 6))


def single_lenslet_depth(camera) -> float:
    """Half depth about focus where a particle's blur on the lenslets is under one pitch, m.

    A point at Z focuses M²Z from the lenslets; its blur there is D·M²|Z|/S_i with D = f/N
    the pupil, under one pitch p for |Z| < p·S_i/(D·M²): one lenslet sees it, and its place
    within the footprint is lost.
    """
    lens = camera.main_lens
    return (camera.microlens_array.pitch * camera.image_distance
            / (lens.aperture_diameter * camera.magnification ** 2))


def focus_profile(name: str, depths=FOCUS_DEPTHS, lenslets=(25, 35), seed: int = 1) -> dict:
    """Lateral error of single particles against their depth, for one variation.

    30 particles a few footprints apart per depth (a 6 x 5 lattice with sub-voxel jitter),
    rendered without noise, reconstructed with the camera's exact calibration on the case's
    grid; rms and bias of x and y in lateral voxels, and :func:`single_lenslet_depth`.
    """
    case = replace(base_case(seed), lenslets=lenslets, depth=1.2 * max(np.abs(depths)),
                   **VARIATIONS[name])
    cam = case_camera(case)
    cal = Calibration.from_camera(cam)
    grid = aligned_grid(cal.effective_camera, case)
    vox = np.asarray(grid.voxel)
    (x0, x1), (y0, y1) = grid.bounds[0], grid.bounds[1]
    gx, gy = np.meshgrid(np.linspace(-0.7, 0.7, 6) * 0.5 * (x1 - x0),
                         np.linspace(-0.7, 0.7, 5) * 0.5 * (y1 - y0))
    rng = np.random.default_rng(seed)
    rows = []
    for z in depths:
        xy = np.stack([gx.ravel(), gy.ravel()], axis=1) + rng.uniform(-0.5, 0.5, (30, 2)) * vox[0]
        true = np.column_stack([xy, np.full(len(xy), z)])
        image = particle_image(cam, true, rays_per_particle=4096, seed=int(rng.integers(2**31)))
        found = np.asarray(reconstruct_volume(cal, image, grid).particle_position,
                           float).reshape(-1, 3)
        pairs = match_particles(true, found, vox * (1.0, 1.0, 3.0))
        err = (found[pairs[:, 1], :2] - true[pairs[:, 0], :2]) / vox[:2]
        rows.append({"z_mm": float(z * 1e3), "n_found": int(len(pairs)),
                     "rms_vox": np.sqrt((err ** 2).mean(axis=0)).tolist(),
                     "bias_vox": err.mean(axis=0).tolist()})
    return {"variation": name, "single_lenslet_depth_mm": single_lenslet_depth(cam) * 1e3,
            "footprint_mm": float(footprint(cal.effective_camera) * 1e3), "depths": rows}


def focus_figure(profiles: list[dict], path: Path) -> Path:
    """Lateral rms of single particles against Z, one line per variation."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for p in profiles:
        z = [r["z_mm"] for r in p["depths"]]
        rms = [float(np.sqrt(np.mean(np.square(r["rms_vox"])))) for r in p["depths"]]
        line, = ax.plot(z, rms, "o-", ms=3, label=p["variation"])
        for s in (-1, 1):
            ax.axvline(s * p["single_lenslet_depth_mm"], color=line.get_color(), lw=0.8,
                       ls=":")
    ax.axhline(1 / np.sqrt(12), color="k", lw=0.8, ls="--", label="b/√12 (place in the "
               "footprint lost)")
    ax.set_xlabel("Z, mm (dotted: ± the single-lenslet depth)")
    ax.set_ylabel("lateral rms of single particles, voxel")
    ax.legend(fontsize=7)
    return savefig(fig, path)


def _stat(rows: list[dict], key: str) -> dict:
    """Mean and range over seeds of a per-component figure (NaN where not defined)."""
    a = np.array([r[key] for r in rows], float)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return {"mean": np.nanmean(a, axis=0).tolist(), "min": np.nanmin(a, axis=0).tolist(),
                "max": np.nanmax(a, axis=0).tolist()}


def _motion(row: dict) -> int:
    """The lateral component that carries the motion (0: u, 1: v): the larger true rms."""
    return int(np.argmax(row["true_rms_vox"][:2]))


def _by_depth(rows: list[dict]) -> list[float]:
    """Mean over seeds of the motion component's rms in each depth band (nearest focus first)."""
    k = _motion(rows[0])
    bands = [[b["rms_vox"][k] for b in r["by_depth"]] for r in rows if r.get("by_depth")]
    n = min((len(b) for b in bands), default=0)
    return [float(np.mean([b[i] for b in bands])) for i in range(n)]


def summarise(rows: list[dict]) -> list[dict]:
    """Per variation (in :data:`VARIATIONS`' order): seeds, mean and range of each figure."""
    out = []
    for name in VARIATIONS:
        mine = [r for r in rows if r["variation"] == name]
        if not mine:
            continue
        out.append({"variation": name, "changes": VARIATIONS[name],
                    "seeds": [r["seed"] for r in mine],
                    **{k: _stat(mine, k) for k in ("gain", "bias_vox", "rms_vox")},
                    "particle_rms_vox": _stat([r["particles"] for r in mine], "rms_vox"),
                    "particle_scale_error": _stat([r["particles"] for r in mine],
                                                  "scale_error"),
                    "motion_component": "uv"[_motion(mine[0])],
                    "motion_rms_by_depth": _by_depth(mine),
                    "motion_rms_um": float(np.mean([r["rms_vox"][_motion(r)]
                                                    * r["voxel_mm"][_motion(r)] * 1e3
                                                    for r in mine])),
                    "voxel_um": float(mine[0]["voxel_mm"][0] * 1e3),
                    "image_distance_error_mm": float(np.mean(
                        [r["calibration"]["image_distance_error_mm"] for r in mine]))})
    return out


def _cells(stat: dict, spec: str) -> list[str]:
    return [fmt(v, spec) for v in stat["mean"]]


def markdown(result: dict, command: str, figures=()) -> str:
    """The page: accuracy per component and the diagnostics, per variation."""
    lines = ["# Invariance to the camera and to the flow's orientation", "",
             __doc__.split("\n\n")[1].split("``pipelines/")[0].replace("\n", " ").strip(),
             "",
             f"Made by `{command}` in {result['seconds']} s; figures are means over the seeds "
             "listed (each seed a new particle field and new noise), in voxels (lateral voxel "
             "for u and v, depth voxel for w). The gain of a component that does not vary "
             "(the vortex's axis) is not defined (–).", ""]
    lines += section("Gain, bias and rms per component")
    rows = []
    for s in result["summary"]:
        rng = [f"{fmt(lo, '.3f')}–{fmt(hi, '.3f')}" for lo, hi in
               zip(s["rms_vox"]["min"], s["rms_vox"]["max"], strict=True)]
        rows.append([s["variation"], ",".join(map(str, s["seeds"])),
                     *_cells(s["gain"], ".3f"), *_cells(s["bias_vox"], "+.3f"),
                     *_cells(s["rms_vox"], ".3f"), " / ".join(rng)])
    lines += table(["variation", "seeds", "gain u", "gain v", "gain w", "bias u", "bias v",
                    "bias w", "rms u", "rms v", "rms w", "rms range u / v / w"], rows)
    lines += ["", *section("The lateral motion's error by distance from focus")]
    lines += ["Rms (voxels, mean over the seeds) of the lateral component that carries the "
              "motion, in three equal bands of |Z| from the focal plane, nearest first.", ""]
    lines += ["The last two columns give the whole field's rms of that component in "
              "micrometres and the lateral voxel it is measured in: a magnification of -1.1 "
              "makes the footprint, and the voxel, 10 % smaller.", ""]
    rows = [[s["variation"], s["motion_component"],
             *[fmt(v, ".3f") for v in s["motion_rms_by_depth"]],
             fmt(s.get("motion_rms_um"), ".1f"), fmt(s.get("voxel_um"), ".1f")]
            for s in result["summary"]]
    lines += table(["variation", "component", "near focus", "middle", "far", "all, µm",
                    "voxel, µm"], rows)
    lines += ["", *section("Diagnostics: calibration and particles of volume A")]
    lines += ["S_i error of the calibration, and the found particles against the true ones "
              "(matched within a resolution cell): rms per axis in voxels and the scale error "
              "per axis (slope of the error against the position, ×10⁻³).", ""]
    rows = [[s["variation"], fmt(s["image_distance_error_mm"], "+.4f"),
             *_cells(s["particle_rms_vox"], ".3f"),
             *[fmt(1e3 * v, "+.2f") for v in s["particle_scale_error"]["mean"]]]
            for s in result["summary"]]
    lines += table(["variation", "S_i error, mm", "particle rms x", "y", "z",
                    "scale error x", "y", "z"], rows)
    if result.get("before"):
        lines += ["", *section("Before and after: " + result["before"]["label"])]
        old = {s["variation"]: s for s in result["before"]["summary"]}
        rows = [[s["variation"], *[fmt(v, ".3f") for v in old[s["variation"]]["rms_vox"]["mean"]],
                 *[fmt(v, ".3f") for v in s["rms_vox"]["mean"]],
                 fmt(old[s["variation"]]["gain"]["mean"][2], ".3f"),
                 fmt(s["gain"]["mean"][2], ".3f")]
                for s in result["summary"] if s["variation"] in old]
        lines += table(["variation", "rms u before", "v", "w", "rms u after", "v", "w",
                        "gain w before", "after"], rows)
    if result.get("focus_profiles"):
        lines += ["", *section("Single particles against depth"), FOCUS_TEXT, ""]
        rows = [[p["variation"], fmt(p["single_lenslet_depth_mm"], ".3f"),
                 fmt(p["footprint_mm"], ".4f"),
                 *[fmt(float(np.sqrt(np.mean(np.square(r["rms_vox"])))), ".3f")
                   for r in p["depths"]]] for p in result["focus_profiles"]]
        z = [fmt(r["z_mm"], "+.2f") for r in result["focus_profiles"][0]["depths"]]
        lines += table(["variation", "single-lenslet depth, mm", "footprint, mm", *z], rows)
        lines += ["", *[f"![{n}]({n})" for n in figures]]
    return "\n".join([*lines, "", *result.get("notes", []), ""])


#: What the focus profile shows (the page's words).
FOCUS_TEXT = ("Lateral rms (x and y pooled, voxels) of 30 single particles per depth, rendered "
              "without noise and reconstructed with the exact calibration, against Z (mm). "
              "Within the single-lenslet depth a particle's blur on the lenslets is under one "
              "pitch: one lenslet sees it, and its place within the footprint is lost, b/√12 "
              "= 0.29 voxel rms; beyond it the position is sharp (0.01-0.03 voxel).")


def run(out: str | Path, *, seeds=(1,), variations=None, command: str = "",
        progress=print, focus: bool = True, notes=()) -> dict:
    """Measure every variation for every seed (and the focus profiles); write the page."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows = []
    for seed in seeds:
        for name in (VARIATIONS if variations is None else variations):
            r = measure(name, seed)
            rows.append(r)
            progress(f"seed {seed}, {name}: gain {[fmt(v, '.3f') for v in r['gain']]}, "
                     f"rms {[fmt(v, '.3f') for v in r['rms_vox']]} vox, {r['seconds']} s")
    profiles = [focus_profile(name) for name in FOCUS_VARIATIONS] if focus else []
    result = {"base_case": {k: v for k, v in base_case().__dict__.items()
                            if k not in ("seed", "reconstruction")},
              "seeds": [int(s) for s in seeds], "runs": rows, "summary": summarise(rows),
              "focus_profiles": profiles, "notes": list(notes),
              "seconds": round(time.perf_counter() - t0, 1)}
    write_report(out, result, command)
    return result


def write_report(out: Path, result: dict, command: str) -> None:
    """``invariance.json``, ``invariance.md`` and, with focus profiles, the figure."""
    names = []
    if result.get("focus_profiles"):
        names.append(focus_figure(result["focus_profiles"], out / "invariance_focus.png").name)
    write_json(out / "invariance.json", result, default=str)
    write_text(out / "invariance.md", markdown(result, command, names))


#: What the page's figures show (written under the tables).
FINDINGS: tuple[str, ...] = (
    "## What it shows",
    "",
    "- **No property of the camera or of the flow's orientation costs lateral accuracy "
    "beyond the seeds' scatter, except a smaller stop, and that cost is physical.** The "
    "lateral component that carries the motion errs 0.139 voxel rms about x (0.125-0.149 "
    "over three seeds); every other variation lies within 0.12-0.17 with ranges that overlap "
    "it. f/2.8 errs 0.184 (0.175-0.194) and measures w at a gain of 0.56.",
    "- **The lateral error lives at focus.** In the band of |Z| nearest the focal plane the "
    "motion component errs 0.18-0.26 voxel, in the farthest 0.08-0.14. A single particle "
    "within the single-lenslet depth p·S_i·N/(f_m·M²) of focus is seen by one lenslet: its "
    "place within the footprint is lost, b/√12 = 0.289 voxel rms at Z = 0 on every camera, "
    "0.005-0.03 voxel a millimetre away. That depth is 0.50 mm at f/2, 0.55 at f/2.2, 0.70 "
    "at f/2.8 (the micro-images under-fill their cells: fewer views), 0.48 at S_i 105 mm: a "
    "smaller stop widens the band where the footprint quantises the position, and the near "
    "band's error grows with it (0.26 against 0.18 voxel). This is the camera's optics, not "
    "a step of the chain; the lateral goal of 0.1 voxel is met beyond the band and not "
    "within it.",
    "- **A magnification other than -1 costs nothing in metres.** At S_i 105 mm (M = -1.1) "
    "the footprint, and the voxel, are 113.6 µm: the motion component errs 0.168 voxel, "
    "19 µm, against 17 µm at M = -1; on 0.125 mm voxels (1.1 footprints) 0.148 voxel.",
    "- **The calibration kept too few lenslets of a rotated or hexagonal array.** It dropped "
    "every lenslet whose focal spot lay less than a spot window from the sensor's edge: on "
    "the demo camera, whose outer spots sit 8 px from it, a rotation of 1.5 mrad lost 24 "
    "lenslets of the top row and a hexagonal array 41 at its row ends, and said nothing "
    "(n_missing 0). It now keeps every lenslet whose spot is on the sensor and predicts the "
    "spots it cannot measure from the fit (2501 of 2501; spots within 0.003 px rms of the "
    "truth; tests/calibration/test_edge_lenslets.py). The lost lenslets lay outside the "
    "reconstructed box, so the velocity hardly moves (table above).",
    "- **Lattice rotation, offset, packing, voxels off or unlike the footprints, the "
    "vortex's axis and centre**: gains of u and v 0.94-1.00, biases within ±0.03 voxel, "
    "particle positions of volume A 0.10-0.13 voxel rms laterally and S_i within 0.006 mm "
    "in every case. Off focus, single particles' lateral positions do not move with any of "
    "them (tests/workflow/test_camera_invariance.py).",
    "- **Cost that is not accuracy.** A lattice that is not axis-aligned and square takes "
    "explicit weights instead of the lattice projector (3.3 GB against 0.12 GB estimated on "
    "the demo camera, 3-5 times the time).",
    "- **A figure measured elsewhere is not reproduced here.** The second camera (S_i 105 mm, "
    "f/2.2, 1.5 mrad, a few µm of offset, vortex about x) was reported at v rms 0.270 voxel; "
    "this case gives 0.134-0.172 over three seeds, and the same camera through "
    "the chain of `pipelines/studies/realcam.py` (focal-point calibration without a ruler) "
    "0.148-0.180 against 0.136-0.187 for the demo camera. The depth of the seeded box "
    "decides the share of particles within the single-lenslet band, and with it the lateral "
    "rms: a thinner box or one centred on focus errs more.",
)
