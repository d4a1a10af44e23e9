"""Whole-chain accuracy on vortex flows against the size of the flow, and the sub-voxel response
of footprint-sized voxels.

Three series, every case through the whole chain of :func:`plenopiv.validation.vortex.run_case`
(calibration images -> calibration -> pair -> volumes -> 3-D PIV), errors in voxels:

1. **scale**: Lamb-Oseen (axis y) and Hill (axis x) on growing patches of the Auburn camera
   with the 50 mm lens at M = -1 (the geometry of thesis §5.1; lateral voxel = lenslet
   footprint = 0.125 mm), windows fixed at 16³ -> 12³ voxels, so the vortex grows against the
   windows;
2. **lateral voxel**: the same flows on the larger patches with the footprint voxel halved;
3. **sub-voxel response**: a uniform shift along x of 1 to 2 footprints in quarter steps, with
   footprint voxels and with half-footprint voxels (peak locking shows as a bias that
   alternates in sign between the quarter steps).

``python pipelines/validate_vortex.py --out docs/validation`` writes ``vortex.json``,
``vortex.md`` and the measured-against-true figures of the cases.
"""

from __future__ import annotations

import json
import re
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from plenopiv.io import atomic_path
from plenopiv.pipeline import footprint
from plenopiv.validation.vortex import VortexCase, case_camera, run_case

#: (label, case keywords) of the scale series: the CI camera, then growing patches.
SCALES = (
    ("41 x 61 (CI)", dict(camera="small_m1")),
    ("61 x 91", dict(camera="auburn_50mm", lenslets=(61, 91))),
    ("81 x 121, depth ±4 mm", dict(camera="auburn_50mm", lenslets=(81, 121), depth=4e-3)),
)
#: (label, case keywords) of the lateral-voxel series: half-footprint voxels.
OVERSAMPLED = (
    ("61 x 91, half-footprint voxels",
     dict(camera="auburn_50mm", lenslets=(61, 91), lateral_oversampling=2)),
    ("81 x 121, depth ±4 mm, half-footprint voxels",
     dict(camera="auburn_50mm", lenslets=(81, 121), depth=4e-3, lateral_oversampling=2)),
)
#: Uniform shifts along x, lenslet footprints.
SHIFTS = (1.0, 1.25, 1.5, 1.75, 2.0)
#: The issue's targets: rms lateral, rms depth, voxels.
TARGET = (0.2, 1.0)


def _case_row(label: str, case: VortexCase, summary: dict, seconds: float) -> dict:
    e = summary["errors"]
    return {"label": label, "flow": case.flow, "lenslets": summary["lenslets"],
            "lateral_oversampling": case.lateral_oversampling,
            "grid_shape": summary["grid_shape"], "voxel_mm": summary["voxel_mm"],
            "n_particles": summary["n_particles"], "windows_vox": list(case.windows_vox),
            "rms_vox": e["rms_vox"], "bias_vox": e["bias_vox"], "n_vectors": e["n_vectors"],
            "valid_fraction": e["valid_fraction"], "by_depth": e["by_depth"],
            "true_max_displacement_vox": e["true_max_displacement_vox"],
            "coverage_2sigma": e.get("coverage_2sigma"),
            "png": summary["products"].get("png_truth"), "seconds": round(seconds, 1)}


def _run(label: str, case: VortexCase, work: Path, figures: Path | None) -> dict:
    t0 = time.perf_counter()
    tag = "_".join(label.split(",")[0].split()[:3])
    name = re.sub(r"[^0-9A-Za-z.]+", "_", f"{case.flow}_{tag}_k{case.lateral_oversampling}")
    summary = run_case(case, work / name)
    summary["lenslets"] = list(case.lenslets) if case.lenslets else None
    row = _case_row(label, case, summary, time.perf_counter() - t0)
    if figures is not None and row["png"]:
        dst = figures / f"vortex_{name}.png"
        shutil.copyfile(row["png"], dst)
        row["png"] = dst.name
    return row


def run(out: str | Path, *, work: str | Path | None = None, seed: int = 1,
        scales=SCALES, shifts=SHIFTS, oversampled=OVERSAMPLED,
        progress=print) -> dict:
    """Run the three series; write ``vortex.json``, ``vortex.md`` and figures to ``out``.

    ``work`` holds every case's products (default ``out/vortex_cases``).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    work = Path(work) if work is not None else out / "vortex_cases"
    t0 = time.perf_counter()
    scale_rows, voxel_rows, shift_rows = [], [], []
    for flow in ("oseen", "hill"):
        for label, kw in scales:
            case = VortexCase(flow=flow, seed=seed, **kw)
            scale_rows.append(_run(label, case, work, out))
            progress(f"{flow} {label}: rms {np.round(scale_rows[-1]['rms_vox'], 3)}")
        for label, kw in oversampled:
            case = VortexCase(flow=flow, seed=seed, **kw)
            voxel_rows.append(_run(label, case, work, out))
            progress(f"{flow} {label}: rms {np.round(voxel_rows[-1]['rms_vox'], 3)}")
    for k in (1, 2):
        for s in shifts:
            case = VortexCase(flow="uniform", seed=seed, lateral_oversampling=k)
            case = replace(case, max_displacement=s * footprint(case_camera(case)))
            row = _run(f"shift {s:g} footprints", case, work, None)
            row["shift_footprints"] = s
            shift_rows.append(row)
            progress(f"uniform {s:g} fp, k = {k}: bias x {row['bias_vox'][0] / k:+.3f} fp")
    result = {"scale": scale_rows, "lateral_voxel": voxel_rows, "shifts": shift_rows,
              "target_rms_vox": {"lateral": TARGET[0], "depth": TARGET[1]}, "seed": seed,
              "seconds": round(time.perf_counter() - t0, 1)}
    with atomic_path(out / "vortex.json") as tmp:
        tmp.write_text(json.dumps(result, indent=1, default=str))
    with atomic_path(out / "vortex.md") as tmp:
        tmp.write_text(markdown(result))
    return {"json": str(out / "vortex.json"), "markdown": str(out / "vortex.md"),
            "seconds": result["seconds"]}


# --------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------


def _f(v, n=3) -> str:
    return ", ".join(f"{x:.{n}f}" for x in v)


def _lateral_fp(row: dict) -> float:
    """Largest lateral rms error in lenslet footprints (the thesis's voxel)."""
    return max(row["rms_vox"][0], row["rms_vox"][1]) / row["lateral_oversampling"]


def _verdict(row: dict) -> str:
    """Against the targets, lateral in footprints (the thesis's voxel), depth in voxels."""
    ok = _lateral_fp(row) <= TARGET[0] and row["rms_vox"][2] <= TARGET[1]
    return "meets" if ok else "misses"


def _summary(r: dict) -> list[str]:
    out = ["## Summary", ""]
    for flow in ("oseen", "hill"):
        rows = [x for x in r["scale"] + r["lateral_voxel"] if x["flow"] == flow]
        if not rows:
            continue
        trend = " → ".join(f"{_lateral_fp(x):.3f}" for x in r["scale"] if x["flow"] == flow)
        best = min(rows, key=_lateral_fp)
        out.append(f"- {flow}: lateral rms (footprints) over the scale series {trend}; best "
                   f"{_lateral_fp(best):.3f} footprint with depth {best['rms_vox'][2]:.2f} "
                   f"voxel ({best['label']}, {best['lateral_oversampling']} voxel(s) per "
                   f"footprint): {_verdict(best)} the targets.")
        if best["by_depth"]:
            near, far = best["by_depth"][0], best["by_depth"][-1]
            out.append(f"  Depth component by distance from the focal plane: rms "
                       f"{near['rms_vox'][2]:.2f} voxel at |Z| < {near['abs_z_mm'][1]:.1f} mm "
                       f"against {far['rms_vox'][2]:.2f} at |Z| > {far['abs_z_mm'][0]:.1f} mm"
                       + (": near focus a particle's micro-image stays in one lenslet, so "
                          "depth motion there is under-measured (see the w panels of the "
                          "figures)." if near["rms_vox"][2] > far["rms_vox"][2] else
                          " (this flow's depth motion is largest away from the focal plane)."))
    for k in (1, 2):
        sh = [x for x in r["shifts"] if x["lateral_oversampling"] == k]
        if sh:
            worst = max(sh, key=lambda x: abs(x["bias_vox"][0]))
            rms = max(x["rms_vox"][0] / k for x in sh)
            out.append(f"- Uniform shifts, {k} voxel(s) per footprint: largest bias "
                       f"{worst['bias_vox'][0] / k:+.3f} footprint (at "
                       f"{worst['shift_footprints']:g}), largest rms {rms:.3f} footprint.")
    return out + [""]


def _case_table(rows: list[dict]) -> list[str]:
    lines = ["| flow | lenslets | grid (z, y, x) | voxel (mm) | particles | rms u, v, w (vox) | "
             "lateral rms (footprints) | bias u, v, w (vox) | valid | "
             "rms u, v, w by \\|Z\\| band (vox) | within ±2σ u, v, w (%) | target | figure |",
             "|" + "---|" * 13]
    for r in rows:
        bands = "; ".join(f"{b['abs_z_mm'][0]:.1f}-{b['abs_z_mm'][1]:.1f} mm: "
                          f"{_f(b['rms_vox'], 2)}" for b in r["by_depth"])
        fig = f"[png]({r['png']})" if r["png"] else ""
        c = r.get("coverage_2sigma")
        cov = ", ".join(f"{100 * x:.0f}" for x in c) if c else "–"
        lines.append(f"| {r['flow']} | {r['label']} | {r['grid_shape']} | "
                     f"{_f(r['voxel_mm'])} | {r['n_particles']} | {_f(r['rms_vox'])} | "
                     f"{_lateral_fp(r):.3f} | "
                     f"{_f(r['bias_vox'])} | {r['valid_fraction']:.2f} | {bands} | "
                     f"{cov} | {_verdict(r)} | {fig} |")
    return lines


def markdown(r: dict) -> str:
    """The study as Markdown."""
    lines = [
        "# Whole-chain accuracy on vortex flows (synthetic)", "",
        "Generated by `python pipelines/validate_vortex.py` "
        "(`plenopiv.validation.vortex_study`); numbers in `vortex.json`.", "",
        "## Setup", "",
        "- Every case runs the whole chain: focal-point, alignment and ruler images -> "
        "calibration (S_i by both methods) -> particle pair -> two SMART volumes (library "
        "defaults) -> 3-D PIV (16³ then 12³ voxels, 50 % overlap, 3 passes, window "
        "deformation) -> error against the flow's displacement at the window centres "
        "(valid vectors at least half a window inside the volume).",
        "- Camera: the Auburn optics with the 50 mm lens at M = -1 (thesis §5.1), f/2.2, "
        "0.15 particles per lenslet, Poisson noise; the CI camera has no substrate, the "
        "patches keep the 10.4 mm substrate of the preset. Voxels: the lenslet footprint "
        "(0.125 mm) in x, y and z unless stated. Particles in |Z| ≤ 3 mm (4 mm where "
        "stated), the largest displacement 2 footprints.",
        "- Oseen: Lamb-Oseen vortex with its axis along y (particles move in depth), core "
        "radius 0.6 × the smaller half-extent of the volume. Hill: Hill's spherical vortex, "
        "axis along x, radius 0.8 × the smaller half-extent, in the vortex frame.",
        f"- Targets: rms ≤ {TARGET[0]} voxel lateral and ≤ {TARGET[1]} voxel in depth, "
        "in voxels of the thesis's grid (lateral: the lenslet footprint).",
        "",
        *_summary(r),
        "## Scale: the vortex grows against fixed windows", "",
        *_case_table(r["scale"]), "",
    ]
    if r["lateral_voxel"]:
        lines += ["## Half-footprint lateral voxels", "",
                  "Windows keep their size in millimetres (twice the voxels laterally); errors "
                  "are in the finer voxels (halve them for footprints).", "",
                  *_case_table(r["lateral_voxel"]), ""]
    if r["shifts"]:
        lines += ["## Sub-voxel response: uniform shift along x (41 x 61 CI camera)", "",
                  "| shift (footprints) | voxels per footprint | bias x (footprints) | "
                  "rms x (footprints) | rms z (voxels) | valid |", "|---|---|---|---|---|---|"]
        for s in r["shifts"]:
            k = s["lateral_oversampling"]
            lines.append(f"| {s['shift_footprints']:g} | {k} | {s['bias_vox'][0] / k:+.3f} | "
                         f"{s['rms_vox'][0] / k:.3f} | {s['rms_vox'][2]:.3f} | "
                         f"{s['valid_fraction']:.2f} |")
        lines.append("")
    lines += [f"Study time: {r['seconds']:.0f} s.", ""]
    return "\n".join(lines)
