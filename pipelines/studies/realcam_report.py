"""The page of :mod:`pipelines.studies.realcam`: JSON, Markdown and one figure.

:func:`run` runs every case and writes ``realcam.json``, ``realcam.md`` and
``realcam_rms.png`` to the output folder.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipelines.studies.output import fmt, pyplot, savefig, section, table, write_json, write_text
from pipelines.studies.realcam import (
    ALL,
    IDEAL,
    StudyCase,
    calibration_figures,
    cases,
    record_calibration,
    recording,
    run_case,
    truth,
)

COMMAND = "python pipelines/validate_realcam.py --out docs/validation"


def run(out: str | Path, *, setup: StudyCase | None = None, seeds=(1, 2), effects=None,
        progress=print, figures: bool = True) -> dict:
    """Run the ideal case, each effect and all together for each seed; write the page.

    ``setup``: the shared set-up (its ``seed`` replaced by each of ``seeds``). Returns the
    result written to ``realcam.json``.
    """
    setup = StudyCase() if setup is None else setup
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runs = []
    work = Path(tempfile.mkdtemp(prefix="realcam_"))
    try:
        for seed in seeds:
            one = replace(setup, seed=int(seed))
            t = truth(one)
            rows = []
            for effect in cases(effects):
                r = run_case(one, effect, t, work / f"seed_{seed}_case_{len(rows)}")
                rows.append(r)
                progress(f"seed {seed}, {effect}: S_i error "
                         f"{fmt(r['image_distance_error_mm'], '.4f')} mm, rms raw "
                         f"{_rms(r, 'raw')}, preprocessed {_rms(r, 'preprocessed')}, "
                         f"{r['seconds']} s")
            runs.append({"seed": int(seed), "n_particles": len(t.positions_a), "cases": rows,
                         "shortfalls": shortfalls(rows)})
    finally:
        shutil.rmtree(work, ignore_errors=True)
    settings = {k: v for k, v in setup.__dict__.items() if k != "seed"}
    result = {"setup": {**settings, "seeds": [int(x) for x in seeds],
                        "true_image_distance_mm": runs[0]["cases"][0]["true_image_distance_mm"]},
              "runs": runs, "seconds": round(time.perf_counter() - t0, 1)}
    write_json(out / "realcam.json", result, default=str)
    names = [rms_figure(runs[0], out / "realcam_rms.png").name] if figures else []
    write_text(out / "realcam.md", markdown(result, names))
    return result


def rerun_calibration(out: str | Path, *, setup: StudyCase | None = None,
                      progress=print) -> dict:
    """Recalibrate every case of ``out/realcam.json`` and rewrite its S_i and the page.

    Only the calibration images, dark and white are recorded again (from the same streams of
    each seed as :func:`run` records them); the pair's figures are kept as they were.
    """
    setup = StudyCase() if setup is None else setup
    out = Path(out)
    result = json.loads((out / "realcam.json").read_text(encoding="utf-8"))
    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix="realcam_si_"))
    try:
        for run_ in result["runs"]:
            one = replace(setup, seed=int(run_["seed"]))
            for k, r in enumerate(run_["cases"]):
                frames = record_calibration(one, recording(r["effect"]))
                _, figures = calibration_figures(one, r["effect"], frames,
                                                 work / f"seed_{one.seed}_case_{k}")
                for key in [k_ for k_ in r if k_.startswith(("image_distance",
                                                             "calibration_"))]:
                    del r[key]
                r.update(figures)
                progress(f"seed {one.seed}, {r['effect']}: S_i error "
                         f"{fmt(r['image_distance_error_mm'], '+.4f')} mm, as recorded "
                         f"{fmt(r.get('image_distance_raw_error_mm'), '+.4f')}, without the "
                         f"white {fmt(r.get('image_distance_no_white_error_mm'), '+.4f')}")
            run_["shortfalls"] = shortfalls(run_["cases"])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result["calibration_seconds"] = round(time.perf_counter() - t0, 1)
    write_json(out / "realcam.json", result, default=str)
    names = ["realcam_rms.png"] if (out / "realcam_rms.png").exists() else []
    write_text(out / "realcam.md", markdown(result, names))
    return result


def _rms(r: dict, chain: str) -> str:
    c = r.get(chain)
    if c is None:
        return "–"
    return "/".join(fmt(v, ".3f") for v in c["rms_vox"])


def _by_name(rows: list[dict]) -> dict:
    return {r["effect"]: r for r in rows}


def shortfalls(rows: list[dict]) -> list[dict]:
    """Where a realistic case ends worse than the ideal one: S_i error and velocity rms.

    Per case: the S_i error against the ideal's; per chain (raw, preprocessed) the rms of each
    component over the ideal's and the detection and ghost rates beside the ideal's. A
    component is listed where its rms exceeds the ideal's by more than 10 %.
    """
    by = _by_name(rows)
    ideal = by.get(IDEAL)
    if ideal is None or "raw" not in ideal:
        return []
    ref = ideal["raw"]
    out = []
    for r in rows:
        if r["effect"] == IDEAL:
            continue
        item = {"effect": r["effect"],
                "image_distance_error_mm": r["image_distance_error_mm"],
                "ideal_image_distance_error_mm": ideal["image_distance_error_mm"],
                "image_distance_raw_error_mm": r.get("image_distance_raw_error_mm"),
                "image_distance_no_white_error_mm": r.get("image_distance_no_white_error_mm")}
        for chain in ("raw", "preprocessed"):
            c = r.get(chain)
            if c is None:
                continue
            ratio = [a / b if b else float("nan") for a, b in zip(c["rms_vox"], ref["rms_vox"],
                                                                     strict=True)]
            item[chain] = {"rms_ratio": ratio,
                           "worse": ["uvw"[k] for k in range(3) if ratio[k] > 1.1],
                           "detection_rate": c["particles"]["detection_rate"],
                           "ghost_rate": c["particles"]["ghost_rate"],
                           "warned": c["warned"]}
        out.append(item)
    return out


# ---- Markdown ---------------------------------------------------------------------------------


def _chain_row(r: dict, chain: str) -> list:
    c = r[chain]
    p = c["particles"]
    g = c["gain"]
    return [r["effect"] if chain == "raw" else "", chain,
            fmt(r["image_distance_error_mm"], "+.4f") if chain == "raw" else "",
            f"{p['detected']}/{p['n_true']}", f"{p['ghosts']}",
            f"{fmt(g[0], '.3f')} / {fmt(g[2], '.3f')}",
            " / ".join(fmt(v, "+.3f") for v in c["bias_vox"]),
            " / ".join(fmt(v, ".3f") for v in c["rms_vox"]),
            "yes" if c["warned"] else "no"]


def markdown(result: dict, figures: list[str]) -> str:
    s = result["setup"]
    runs = result["runs"]
    seeds = ", ".join(str(r["seed"]) for r in runs)
    n_particles = " and ".join(sorted({str(r["n_particles"]) for r in runs}))
    lines = ["# A real recording: the chain on a real camera's frames", "",
             f"Made by `{COMMAND}` (about {result['seconds'] / 60:.0f} minutes on two cores)"
             + (f", its S_i by `{COMMAND} --calibration-only` (about "
                f"{result['calibration_seconds'] / 60:.0f} minutes; the pair's figures from "
                "the calibration before it)" if "calibration_seconds" in result else "")
             + "; the figures are in [realcam.json](realcam.json).", "",
             f"One camera, `{s['camera']}` (the demo's: 41 × 61 lenslets, 50 mm lens at "
             f"M = −1, f/2.2, S_i = {s['true_image_distance_mm']:g} mm), records a Lamb-Oseen "
             f"pair ({n_particles} particles, {s['particles_per_lenslet']} per lenslet, "
             "±3 mm in depth, 0.25 mm at most, the demo's case with correlation "
             "uncertainties) and its calibration images (focal-point at f/16, alignment) twice "
             "from the same particles and seeds (seeds "
             f"{seeds}, camera seed {s['camera_seed']}): ideal, and through a real camera "
             "(`plenopiv.synthetic.sensor`, docs/methods.md#a-real-recording) with one effect "
             "of `REALISTIC` at a time (the sensor's on its 12-bit ADC, whose counts they are) "
             "and all of them together. Every frame has photon noise "
             "(20 000 electrons at full scale, 16-bit files) from its own stream of the seed, "
             "the same in every case. Each realistic case has its dark (8 frames, where the "
             "sensor has an effect: a dark of an ideal sensor is zero) and its white (4 "
             "frames at the recording's f/2.2), as `plenopiv simulate dark|white` writes "
             "them.", "",
             "Each case runs as `plenopiv calibrate --dark --white` and `plenopiv run` would: the "
             "calibration images with the master dark subtracted and its hot and cold pixels "
             "repaired, divided by the white, calibrated by the focal-point method (S_i, "
             "offset and rotation); then "
             "the pair as recorded (**raw**: no `[preprocess]` table) and with `[preprocess]` "
             "dark, white and `hot_pixels = \"auto\"` (**preprocessed**). Particles of "
             "volume A are matched one-to-one to the true ones within the resolution cell "
             "(detected/true inside the volume; ghosts: found and unmatched); gain (u / w), "
             "bias and rms (u / v / w) in voxels over the valid vectors half a window inside "
             "the volume (`compare_with_truth`, the vortex page's figures); *warned*: the "
             "preprocessing stage's warning about the image (black level above the dark "
             "threshold, hot pixels, saturation).", ""]
    lines += section("Summary over the seeds")
    lines += summary_lines(runs)
    for k, run in enumerate(runs):
        lines += seed_lines(run, figures if k == 0 else [])
    lines += section("Warnings")
    lines += warning_lines(runs[0]["cases"])
    return "\n".join(lines).rstrip() + "\n"


def seed_lines(run: dict, figures: list[str]) -> list[str]:
    """The tables and the shortfalls of one seed."""
    rows = run["cases"]
    by = _by_name(rows)
    lines = section(f"Seed {run['seed']}: ideal against realistic, per effect and all "
                    "together")
    cols = ["case", "chain", "S_i error (mm)", "detected/true", "ghosts", "gain u / w",
            "bias u / v / w (vox)", "rms u / v / w (vox)", "warned"]
    body = []
    for r in rows:
        if "raw" not in r:
            body.append([r["effect"], "–", fmt(r["image_distance_error_mm"], "+.4f"),
                         "calibration failed: " + str(r.get("calibration_error")), "", "", "",
                         "", ""])
            continue
        body.append(_chain_row(r, "raw"))
        if "preprocessed" in r:
            body.append(_chain_row(r, "preprocessed"))
    lines += table(cols, body) + [""]
    lines += ["S_i error: the calibration from the dark-subtracted images (the ideal case and "
              "the optics' and light's cases have no dark). Beside it the same calibration "
              "images as recorded (without their dark, with the white), and without the "
              "case's white (the images not divided by it: what the lenslets' throughput and "
              "the micro-images' vignetting do to S_i):",
              ""]
    cal = [[r["effect"], fmt(r["image_distance_error_mm"], "+.4f"),
            fmt(r.get("image_distance_raw_error_mm"), "+.4f"),
            fmt(r.get("image_distance_no_white_error_mm"), "+.4f"),
            "; ".join(x for x in (r.get("calibration_error"), r.get("calibration_raw_error"),
                                  r.get("calibration_no_white_error")) if x)]
           for r in rows if r["effect"] != IDEAL]
    lines += table(["case", "S_i error (mm)", "as recorded (mm)", "without the white (mm)",
                    "refusal or warning"], cal) + [""]
    for name in figures:
        lines += [f"![rms per component, ideal, raw and preprocessed]({name})", ""]
    lines += section(f"Seed {run['seed']}: where the realistic case falls short", 3)
    lines += shortfall_lines(run["shortfalls"], by)
    return lines


def summary_lines(runs: list[dict]) -> list[str]:
    """Per case and seed: S_i error, the preprocessed rms over the ideal's, the raw warning."""
    lines = ["Per case, one value per seed: the S_i error of the calibration with its dark, "
             "the rms of u / v / w over the ideal case's (as recorded; preprocessed) and "
             "whether the image as recorded warned.", ""]
    items = [{it["effect"]: it for it in run["shortfalls"]} for run in runs]
    ideal = [_by_name(run["cases"])[IDEAL] for run in runs]
    body = [[IDEAL, "; ".join(fmt(r["image_distance_error_mm"], "+.4f") for r in ideal),
             "; ".join(" / ".join(fmt(v, ".3f") for v in r["raw"]["rms_vox"]) + " vox"
                       for r in ideal), "", "; ".join("yes" if r["raw"]["warned"] else "no"
                                                      for r in ideal)]]
    for name in [it["effect"] for it in runs[0]["shortfalls"]]:
        its = [m.get(name) for m in items]

        def ratios(chain, its=its):
            return "; ".join(" / ".join(fmt(v, ".2f") for v in it[chain]["rms_ratio"])
                             if it and chain in it else "–" for it in its)
        body.append([name, "; ".join(fmt(it["image_distance_error_mm"], "+.4f") if it else "–"
                                     for it in its),
                     ratios("raw"), ratios("preprocessed"),
                     "; ".join(("yes" if it["raw"]["warned"] else "no") if it and "raw" in it
                               else "–" for it in its)])
    return lines + table(["case", "S_i error (mm)", "rms / ideal's, as recorded (ideal: rms)",
                          "rms / ideal's, preprocessed", "warned as recorded"], body) + [""]


def shortfall_lines(items: list[dict], by: dict) -> list[str]:
    """Plain sentences with the measured figures (rms ratios over the ideal's)."""
    if not items:
        return ["No ideal case to compare with.", ""]
    ideal = by[IDEAL]
    out = [f"Against the ideal case (S_i error {fmt(ideal['image_distance_error_mm'], '+.4f')} "
           "mm, rms u / v / w " + " / ".join(fmt(v, ".3f") for v in ideal["raw"]["rms_vox"])
           + " voxel, detected "
           f"{ideal['raw']['particles']['detected']}/{ideal['raw']['particles']['n_true']}, "
           f"{ideal['raw']['particles']['ghosts']} ghosts); a component is listed where its "
           "rms exceeds the ideal's by more than 10 %:", ""]
    for it in items:
        parts = [f"S_i error {fmt(it['image_distance_error_mm'], '+.4f')} mm"]
        if it.get("image_distance_raw_error_mm") is not None:
            parts[-1] += (f" ({fmt(it['image_distance_raw_error_mm'], '+.4f')} mm without the "
                          "dark)")
        if it.get("image_distance_no_white_error_mm") is not None:
            parts[-1] += (f" ({fmt(it['image_distance_no_white_error_mm'], '+.4f')} mm without "
                          "the white)")
        for chain in ("raw", "preprocessed"):
            c = it.get(chain)
            if c is None:
                continue
            ratio = " / ".join(fmt(v, ".2f") for v in c["rms_ratio"])
            worse = ", ".join(c["worse"]) if c["worse"] else "none"
            parts.append(f"{chain}: rms over the ideal's {ratio} (worse: {worse}), detection "
                         f"{c['detection_rate']:.2f}, ghosts {c['ghost_rate']:.2f}")
        out.append(f"- **{it['effect']}**: " + "; ".join(parts) + ".")
    out.append("")
    single = [it for it in items if it["effect"] != ALL and it.get("preprocessed")
              and it["preprocessed"]["worse"]]
    if single:
        out += ["Single effects whose preprocessed rms exceeds the ideal's by more than 10 %: "
                + "; ".join(f"{it['effect']} (" + ", ".join(
                    f"{c} {it['preprocessed']['rms_ratio']['uvw'.index(c)]:.2f}"
                    for c in it["preprocessed"]["worse"]) + ")" for it in single)
                + ". Single effects whose S_i error exceeds the ideal's by more than 0.05 mm: "
                + ("; ".join(f"{it['effect']} ({it['image_distance_error_mm']:+.4f} mm)"
                             for it in items if it["effect"] != ALL
                             and abs(it["image_distance_error_mm"]
                                     - it["ideal_image_distance_error_mm"]) > 0.05)
                   or "none") + ".", ""]
    a = by.get(ALL)
    if a is not None and "preprocessed" in a:
        ratio = [p / q for p, q in zip(a["preprocessed"]["rms_vox"], ideal["raw"]["rms_vox"],
                                       strict=True)]
        out += [f"All effects together, preprocessed: rms u / v / w "
                f"{' / '.join(fmt(v, '.2f') for v in ratio)} times the ideal's; S_i "
                f"{fmt(a['image_distance_error_mm'], '+.4f')} mm off with the dark "
                f"subtracted, {fmt(a.get('image_distance_raw_error_mm'), '+.4f')} mm without "
                f"it, {fmt(a.get('image_distance_no_white_error_mm'), '+.4f')} mm without the "
                f"white, against {fmt(ideal['image_distance_error_mm'], '+.4f')} mm ideal. "
                "Without the white the lenslets' throughput and the vignetting stay in the "
                "focal-point and alignment spots, and what they do to S_i stays in the vectors "
                "of every case run with that calibration.", ""]
    return out


def warning_lines(rows: list[dict]) -> list[str]:
    out = ["The first warning of each realistic case's raw image A (`PlenopivWarning` of the "
           "preprocessing stage), and whether the preprocessed pair still warned:", ""]
    body = []
    for r in rows:
        if r["effect"] == IDEAL or "raw" not in r:
            continue
        w = r["raw"]["warnings"]
        text = w[0].replace("|", "\\|") if w else "none"
        body.append([r["effect"], text,
                     "yes" if r.get("preprocessed", {}).get("warned") else "no"])
    return out + table(["case", "raw: warning", "preprocessed: warned"], body) + [""]


# ---- figure -----------------------------------------------------------------------------------


def rms_figure(run: dict, path: Path) -> Path:
    """rms of u, v, w per case of one seed: ideal, raw and preprocessed."""
    plt = pyplot()
    rows = [r for r in run["cases"] if "raw" in r]
    names = [r["effect"] for r in rows]
    x = np.arange(len(rows))
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2), constrained_layout=True, sharey=False)
    for k, ax in enumerate(axes):
        raw = [r["raw"]["rms_vox"][k] for r in rows]
        pre = [r["preprocessed"]["rms_vox"][k] if "preprocessed" in r else np.nan
               for r in rows]
        ax.bar(x - 0.2, raw, 0.4, label="raw (no [preprocess])")
        ax.bar(x + 0.2, pre, 0.4, label="preprocessed")
        ax.axhline(rows[0]["raw"]["rms_vox"][k], color="k", lw=0.8, ls="--", label="ideal")
        ax.set_xticks(x, names, rotation=60, ha="right", fontsize=8)
        ax.set_title(f"rms error of {'uvw'[k]} (voxels), seed {run['seed']}")
        ax.set_ylim(0, None)
    axes[0].legend(fontsize=8)
    return savefig(fig, path)
