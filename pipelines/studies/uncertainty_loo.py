"""Coverage of the per-vector uncertainty on cases left out of its development.

The uncertainty model (:mod:`plenopiv.piv.uncertainty`) was developed on the cases of
:mod:`pipelines.studies.uncertainty`: Oseen with its axis along y and Hill with its axis
along x, on the M = -1 camera, noise on, 0.15-0.3 particles per lenslet. Each case here
differs from them along one axis: the vortex turned (axis x, y, z), the seeding (0.1,
0.3 per lenslet on footprint voxels), the noise (ideal render), another camera (S_i 105 mm,
the lattice rotated and offset). For each case the share of true errors within ±2σ per
component is reported with the default model and with each of its terms removed in turn
(ablation), so that a term kept only because it fixed one case shows.

``python pipelines/validate_uncertainty_loo.py --out docs/validation`` writes
``uncertainty_loo.json`` and ``uncertainty_loo.md``.
"""

from __future__ import annotations

import json
import pickle
import re
import time
from pathlib import Path

import numpy as np

from pipelines.studies import uncertainty
from pipelines.studies.output import write_json, write_text
from plenopiv.workflow.vortex_case import VortexCase, coverage

#: The issue's band for the share of true errors within ±2σ on held-out data.
BAND = (0.85, 0.99)

#: A camera that differs from the development cases' (``small_m1``): the image distance
#: 105 mm instead of 100 mm (M about -1.1), the lattice rotated 1.5 mrad and offset.
OTHER_CAMERA = """name = "small camera, S_i 105 mm, lattice rotated 1.5 mrad"

[sensor]
rows = 700
cols = 1040
pixel_pitch_um = 7.4

[microlens_array]
rows = 41
cols = 61
pitch_um = 125.0
focal_length_um = 500.0
sensor_distance_um = 500.0
grid = "square"
back_side = "physical"
offset_um = [3.0, -2.0]
rotation_rad = 0.0015

[main_lens]
focal_length_mm = 50.0
f_number = 2.2
image_distance_mm = 105.0
"""

#: (label, what is left out, case keywords); ``camera = "other"`` is :data:`OTHER_CAMERA`.
CASES = (
    ("Oseen, axis x", "orientation", dict(flow="oseen", flow_axis="x")),
    ("Oseen, axis z", "orientation", dict(flow="oseen", flow_axis="z")),
    ("Hill, axis y", "orientation", dict(flow="hill", flow_axis="y")),
    ("Hill, axis z", "orientation", dict(flow="hill", flow_axis="z")),
    ("Oseen, 0.1 per lenslet", "density", dict(flow="oseen", particles_per_lenslet=0.1)),
    ("Oseen, 0.3 per lenslet", "density", dict(flow="oseen", particles_per_lenslet=0.3)),
    ("Oseen, no noise", "noise", dict(flow="oseen", noise=False)),
    ("Oseen, other camera", "camera", dict(flow="oseen", camera="other")),
    ("Oseen, axis x, other camera", "orientation and camera",
     dict(flow="oseen", flow_axis="x", camera="other")),
    ("Oseen, axis x, other camera, no noise", "orientation, camera and noise",
     dict(flow="oseen", flow_axis="x", camera="other", noise=False)),
    ("Oseen, axis y, 0.3 per lenslet, 0.5 px blur (development)", "none (development)",
     dict(flow="oseen", particles_per_lenslet=0.3, blur_px=0.5)),
    ("Oseen, axis x, 0.3 per lenslet, 0.5 px blur", "orientation",
     dict(flow="oseen", flow_axis="x", particles_per_lenslet=0.3, blur_px=0.5)),
)

#: The cases the model was developed on (:data:`pipelines.studies.uncertainty.CASES`), with
#: the same ablation: a term that only one of them needs shows there.
DEVELOPMENT = tuple((label, "none (development)", kw) for label, kw in uncertainty.CASES)

#: The terms of :func:`plenopiv.piv.uncertainty.combine` (``uncertainty_parts`` names) and
#: ``"iteration"``, the iteration tail of :func:`~plenopiv.piv.uncertainty.iteration_uncertainty`.
TERMS = ("iteration", "response_random", "response_gain", "unresolved_gradient",
         "rejected_neighbour", "location")
TERM_LABELS = {"iteration": "iteration tail", "response_random": "response excess",
               "response_gain": "gain", "unresolved_gradient": "curvature",
               "rejected_neighbour": "rejected neighbour", "location": "location"}


NOTES = [
    "## What fell short out of sample, and the two changes",
    "",
    "The coverage \"before\" is the model the development cases chose; \"now\" the same "
    "fields and measured responses under the two changes below (`--before`). Neither change "
    "adds a constant or is fitted to a case: each replaces a step whose assumption a left-out "
    "case broke.",
    "",
    "1. **The depth component's shared error was fitted along x and y apart** "
    "(`Response.excess`, term 3 of `uncertainty.md`). The response's test pairs move "
    "laterally along x alone (1.25 footprints) or diagonally (0.5, 1.25, 1.75 footprints "
    "along x and y at once), never along y alone. Their w excess does not grow from the pair "
    "along x to the diagonal ones (on the CI camera, Oseen about x: 0.31 depth voxel along x "
    "alone; 0.27, 0.30, 0.33 for the diagonal pairs; 0.25 for depth alone), so the "
    "non-negative fit a_x t_x + a_y t_y + a_z t_z gave w the whole lateral error along x and "
    "a_y = 0 in every layer. The development flows move along x (Oseen about y) or all ways "
    "(Hill about x) and did not show it; a vortex about x moves its particles along y and z, "
    "and its w got no shared error from the lateral motion: Oseen about x 90 %, Hill about y "
    "80 % (now 95 and 90 %). The depth component has no lateral direction of its own: a "
    "lattice symmetric in x "
    "and y changes the depth error of a particle by as much whichever way it moves "
    "laterally, so w is now fitted in the lateral motion's magnitude |(t_x, t_y)| and t_z "
    "(`EXCESS_MOTION_LEVELS`); u and v keep the per-axis fit, which the pairs along x tell "
    "apart (a lateral component's error follows the motion along its own axis). A y-only "
    "test pair would measure the same thing at two more reconstructions per experiment.",
    "2. **The gain term took the error at the mean gain** (`Response.gain_error`). A "
    "displacement measured at gain g errs by (g - 1)/g of its value, and the gain depends on "
    "the displacement: near focus on the other camera the four test pairs that move in depth "
    "measure w at 2.15, 0.91, 0.85 and 1.01 times its size (0.1, 0.25, 0.5 diagonal and 0.5 "
    "depth cells alone, layer at Z = -0.4 mm). Their mean, 1.23, gave the term 0.19 |w|; "
    "where the gains lie either side of 1 the error at their mean vanishes although every "
    "pair errs. Which test displacement a vector's gain is nearest is not known, so the term "
    "is now the rms over the test pairs of (1 - g_j)/max(g_j, 0.1) (0.29 |w| in that layer).",
    "",
    "## Reading the ablation",
    "",
    "- The response's excess (term 3) and the curvature (term 4) carry w everywhere and the "
    "rejected neighbour (term 5) carries Hill's lateral components on every Hill case, "
    "left out or not: none is there for one case.",
    "- The gain term moves 1-4 points where the gain departs from 1 (the other camera, no "
    "noise, 0.1 per lenslet), left-out cases among them.",
    "- The iteration tail (term 2) is 0 on every case here (the passes converge to their "
    "noise) and the location term (term 6) changes no figure by more than a point: the case "
    "it was built for, a volume beyond the focal plane behind a 10.4 mm substrate, has a "
    "placement offset of 46-133 µm; these have under 20 µm (the CI camera) or up to 64 µm "
    "(the Auburn patch centred on focus). Both are measured from the run "
    "itself (the last corrections, the response's placement) and vanish where their cause "
    "does; they are kept, and no case here tests them.",
    "",
    "## What is not met",
    "",
    "- The uniform test pairs do not show the vortex's own loss of w near focus: on the other "
    "camera with the vortex about x the field's w gain is 0.62-0.70 in the layers within "
    "1.1 mm of focus (the test pairs' mean 1.04-1.23 there), and w's coverage in those layers "
    "is 0.71-0.84 while the outer layers are at 0.88-1.0. The modulation pairs measure the "
    "chain's spatial response over the whole volume, not per layer.",
    "- Hill about z (its axis along depth) has the lowest w, 88 % (85 % before): w reverses "
    "laterally within one window in the core (+1.7 depth voxels on the axis, -1.5 outside), "
    "the measured w is flat there, and neither the curvature of the measured field nor the "
    "rejected vectors' depth disagreements (below the spurious reach) see it.",
    "- The held-out pair of the products bar (u 98, v 93, w 79 %) is most like \"Oseen, "
    "axis x, other camera, no noise\" here (97, 93, 86 % before, 97, 96, 89 % now); it was "
    "not rerun.",
    "- Hill's u on half-footprint voxels, 98.7 %, is 0.3 points under the band's top (98.0 "
    "before): the gain term's rms adds to a σ that term 5 already makes conservative there "
    "(`uncertainty.md`, beside a rejected vector).",
    "- One realisation per case: a coverage over about 180 vectors has a binomial standard "
    "error of 1.5-2.5 points, and the vectors of overlapping windows are correlated "
    "(`uncertainty.md`, realisations).",
]


def _slug(label: str) -> str:
    return re.sub(r"[^0-9A-Za-z]+", "_", label).strip("_").lower()


def resolve(kw: dict, work: Path) -> VortexCase:
    """The case of ``kw``, ``camera = "other"`` written to ``work`` as :data:`OTHER_CAMERA`."""
    if kw.get("camera") == "other":
        path = work / "other_camera.toml"
        work.mkdir(parents=True, exist_ok=True)
        path.write_text(OTHER_CAMERA)
        kw = {**kw, "camera": str(path)}
    return VortexCase(**kw)


def run_chain(case: VortexCase, out: Path) -> Path:
    """The case's chain (as :func:`~plenopiv.workflow.vortex_case.run_case`), its parts kept.

    Writes ``chain.pkl`` to ``out``: the uncombined vector field (effective coordinates), the
    measured response, the depth correction, the physical grid, the flow and the window, so
    that the uncertainty can be evaluated again without running the chain.
    """
    from plenopiv.piv.uncertainty import combine
    from plenopiv.workflow.pair import PairProcessor, correlate
    from plenopiv.workflow.vortex_case import (
        _calibration,
        _case_pair,
        case_camera,
        case_experiment,
    )

    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(case.seed)
    truth_cam = case_camera(case)
    cal, _ = _calibration(case, truth_cam, rng, out, lambda *a: None)
    exp = case_experiment(case, cal, out)
    ia, ib, _, flow, _ = _case_pair(case, exp.volume, truth_cam, rng, out, lambda *a: None)
    processor = PairProcessor(exp, cal)
    res = processor(ia, ib)
    response = processor.response().response
    captured = {}

    def capture(field):
        captured["field"] = field
        return response

    vec = correlate(res.volume_a, res.volume_b, exp.piv, response=capture, names=None)
    # the product's u keeps the correlation's uncertainty (its w has the continuity fit's)
    assert np.allclose(np.nan_to_num(vec.u_uncertainty),
                       np.nan_to_num(res.vectors.u_uncertainty))
    combine(captured["field"], response)          # the same terms as the product's
    path = out / "chain.pkl"
    with open(path, "wb") as fh:
        pickle.dump({"field": captured["field"], "response": response.to_dict(),
                     "correction": res.volume_a.correction, "grid": res.vectors.grid,
                     "flow": flow, "dt": case.dt, "window_vox": case.windows_vox[-1],
                     "product": res.vectors, "continuity": res.continuity}, fh)
    return path


def evaluate(chain_path: Path) -> dict:
    """Coverage of the default model and of each term removed, from a saved chain."""
    from plenopiv.piv.response import Response
    from plenopiv.piv.uncertainty import combine
    from plenopiv.products.vectors import VectorResult
    from plenopiv.workflow.accuracy import gain_bias_rms
    from plenopiv.workflow.compare import inner_vectors, true_displacement

    with open(chain_path, "rb") as fh:
        saved = pickle.load(fh)
    field, correction = saved["field"], saved["correction"]
    response = Response.from_dict(saved["response"])
    combined = combine(field, response)
    vec = VectorResult.from_field(combined, correction, grid=saved["grid"])
    grid = saved["grid"]
    truth = true_displacement(vec, saved["flow"], saved["dt"])
    ok = (np.asarray(vec.valid, bool) & inner_vectors(vec, grid, saved["window_vox"])
          & np.all(np.isfinite(np.stack([vec.u, vec.v, vec.w])), axis=0))
    measured = np.stack([vec.u, vec.v, vec.w])[:, ok]
    err = measured - truth[:, ok]
    scale = np.array([1.0, 1.0, abs(correction.scale)])[:, None]
    vox = np.asarray(grid.voxel, float)[:, None]
    total = np.stack([vec.u_uncertainty, vec.v_uncertainty, vec.w_uncertainty])[:, ok]
    parts = combined.uncertainty_parts
    own = {name: np.nan_to_num(np.asarray(parts[name], float)[:, ok]) * scale
           for name in TERMS if name != "iteration"}
    from plenopiv.piv.uncertainty import iteration_uncertainty

    tail = iteration_uncertainty(field)
    corr = np.asarray(parts["correlation"], float)
    own["iteration"] = np.sqrt(np.maximum(
        np.nan_to_num(tail[:, ok]) ** 2 - np.nan_to_num(corr[:, ok]) ** 2, 0.0)) * scale
    ablation = {name: coverage(err.T, np.sqrt(np.maximum(total**2 - own[name] ** 2, 0.0)).T)
                .tolist() for name in TERMS}
    rms = {name: np.sqrt(np.mean((own[name] / vox) ** 2, axis=1)).tolist() for name in TERMS}
    rms["correlation"] = np.sqrt(np.mean((np.nan_to_num(corr[:, ok]) * scale / vox) ** 2,
                                         axis=1)).tolist()
    g = gain_bias_rms(measured / vox, truth[:, ok] / vox)
    return {"n_vectors": int(ok.sum()), "coverage": coverage(err.T, total.T).tolist(),
            "ablation": ablation, "rms_term_vox": rms,
            "rms_sigma_vox": np.sqrt(np.mean((total / vox) ** 2, axis=1)).tolist(),
            "rms_error_vox": np.sqrt(np.mean((err / vox) ** 2, axis=1)).tolist(),
            "gain": g["gain"], "bias_vox": g["bias"], **_product(saved)}


def _product(saved: dict) -> dict:
    """The coverage of the field as ``plenopiv run`` writes it (the correlation corrected by
    the tracks, its w fitted to continuity, with the uncertainties it carries), where the
    chain kept it."""
    from plenopiv.workflow.accuracy import gain_bias_rms
    from plenopiv.workflow.compare import inner_vectors, true_displacement

    vec = saved.get("product")
    if vec is None:
        return {}
    grid = saved["grid"]
    truth = true_displacement(vec, saved["flow"], saved["dt"])
    ok = (np.asarray(vec.valid, bool) & inner_vectors(vec, grid, saved["window_vox"])
          & np.all(np.isfinite(np.stack([vec.u, vec.v, vec.w])), axis=0))
    err = np.stack([vec.u, vec.v, vec.w])[:, ok] - truth[:, ok]
    total = np.stack([vec.u_uncertainty, vec.v_uncertainty, vec.w_uncertainty])[:, ok]
    vox = np.asarray(grid.voxel, float)[:, None]
    g = gain_bias_rms(np.stack([vec.u, vec.v, vec.w])[:, ok] / vox, truth[:, ok] / vox)
    return {"product": {"n_vectors": int(ok.sum()), "coverage": coverage(err.T, total.T).tolist(),
                        "rms_sigma_vox": np.sqrt(np.mean((total / vox) ** 2, axis=1)).tolist(),
                        "rms_error_vox": np.sqrt(np.mean((err / vox) ** 2, axis=1)).tolist(),
                        "gain": g["gain"], "continuity": saved.get("continuity")}}


def run(out: str | Path, *, work: str | Path | None = None, cases=CASES, reuse: bool = False,
        before: str | Path | None = None, progress=print) -> dict:
    """Run (or, with ``reuse``, evaluate the saved chains again) and write JSON and Markdown.

    ``before``: an ``uncertainty_loo.json`` of the same chains under an earlier model, whose
    coverage is shown beside the current one.
    """
    out = Path(out)
    work = Path(work) if work is not None else out / "uncertainty_loo_cases"
    earlier = {} if before is None else {c["label"]: c for c in load(before)["cases"]}
    t0 = time.perf_counter()
    rows = []
    for label, axis, kw in cases:
        chain = work / _slug(label) / "chain.pkl"
        t1 = time.perf_counter()
        if not (reuse and chain.exists()):
            run_chain(resolve(kw, work), chain.parent)
        row = {"label": label, "left_out": axis, "case": dict(kw), **evaluate(chain),
               "seconds": round(time.perf_counter() - t1, 1)}
        if label in earlier:
            row["before"] = {k: earlier[label][k] for k in ("coverage", "ablation",
                                                            "rms_sigma_vox")}
        rows.append(row)
        progress(f"{label}: coverage u, v, w = {np.round(row['coverage'], 3).tolist()}")
    result = {"cases": rows, "band": list(BAND), "terms": list(TERMS),
              "seconds": round(time.perf_counter() - t0, 1)}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "uncertainty_loo.json", result, default=str)
    write_text(out / "uncertainty_loo.md", markdown(result, "\n".join(NOTES)))
    return {"json": str(out / "uncertainty_loo.json"), "seconds": result["seconds"]}


def _pct(v) -> str:
    return ", ".join(f"{x * 100:.0f}" for x in v)


def _vox(v) -> str:
    return ", ".join("–" if not np.isfinite(x) else f"{x:.2f}" for x in np.asarray(v, float))


def _coverage_table(cases, band) -> list[str]:
    """Coverage per case (Markdown lines), the earlier model's beside it where known."""
    lo, hi = band
    lines = ["| case | left out | vectors | rms error (vox) | gain | rms σ (vox) | coverage "
             "before | coverage | in band |", "|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        inside = all(lo <= x <= hi for x in c["coverage"])
        prior = _pct(c["before"]["coverage"]) if "before" in c else "–"
        lines.append(f"| {c['label']} | {c['left_out']} | {c['n_vectors']} | "
                     f"{_vox(c['rms_error_vox'])} | {_vox(c['gain'])} | "
                     f"{_vox(c['rms_sigma_vox'])} | {prior} | {_pct(c['coverage'])} | "
                     f"{'yes' if inside else 'no'} |")
    return lines + ["", _count("Now", [c["coverage"] for c in cases], band)
                    + (" " + _count("Before", [c["before"]["coverage"] for c in cases], band)
                       if all("before" in c for c in cases) else ""), ""]


def _count(what, coverages, band) -> str:
    cov = np.array(coverages)
    lo, hi = band
    return (f"{what}: {int(((cov >= lo) & (cov <= hi)).sum())} of {cov.size} case-components "
            f"in the band, {int((cov < lo).sum())} below, {int((cov > hi).sum())} above.")


def markdown(r: dict, notes: str = "") -> str:
    """The study as Markdown (``notes``: the analysis, appended)."""
    lo, hi = r["band"]
    held = [c for c in r["cases"] if "development" not in c["left_out"]]
    dev = [c for c in r["cases"] if "development" in c["left_out"]]
    lines = ["# Per-vector uncertainty on left-out cases (synthetic)", "",
             "Generated by `python pipelines/validate_uncertainty_loo.py --development` "
             "(`pipelines.studies.uncertainty_loo`); numbers in `uncertainty_loo.json`.", "",
             "Each left-out case differs from the development cases of `uncertainty.md` "
             "(Oseen about y, Hill about x, the M = -1 camera, noise on) along one axis. "
             "Coverage = share of the true errors within ±2σ over the valid vectors at least "
             f"half a window inside the volume; band {lo:.0%}-{hi:.0%}. \"before\": the same "
             "chains (same fields, same measured responses) under the model before the change "
             "below.", "", "## Coverage per left-out case (%, u, v, w)", "",
             *_coverage_table(held, r["band"])]
    if dev:
        lines += ["## Coverage on the development cases (%, u, v, w)", "",
                  *_coverage_table(dev, r["band"])]
    made = [c for c in held + dev if "product" in c]
    if made:
        lines += ["## Coverage of the product (%, u, v, w)", "",
                  "The same chains' fields as `plenopiv run` writes them: the correlation "
                  "corrected by the pair's tracks, its w fitted to continuity (`[piv] "
                  "continuity`, the fit's own uncertainty), against the truth as above.", "",
                  "| case | vectors | rms error (vox) | gain | rms σ (vox) | coverage | in band "
                  "| w fitted |", "|---|---|---|---|---|---|---|---|"]
        for c in made:
            pr = c["product"]
            inside = all(lo <= x <= hi for x in pr["coverage"])
            fitted = (pr.get("continuity") or {}).get("applied")
            lines.append(f"| {c['label']} | {pr['n_vectors']} | {_vox(pr['rms_error_vox'])} | "
                         f"{_vox(pr['gain'])} | {_vox(pr['rms_sigma_vox'])} | "
                         f"{_pct(pr['coverage'])} | {'yes' if inside else 'no'} | "
                         f"{'yes' if fitted else 'no'} |")
        lines += ["", _count("Product", [c["product"]["coverage"] for c in made], r["band"]),
                  ""]
    lines += ["## Ablation: coverage with one term removed (%, u, v, w)", "",
              "| case | default | " + " | ".join(f"without {TERM_LABELS[t]}" for t in r["terms"])
              + " |", "|---|---|" + "---|" * len(r["terms"])]
    for c in held + dev:
        lines.append(f"| {c['label']} | {_pct(c['coverage'])} | "
                     + " | ".join(_pct(c["ablation"][t]) for t in r["terms"]) + " |")
    lines += ["", "## Size of each term (rms over the vectors, voxels, u, v, w)", "",
              "| case | correlation | " + " | ".join(TERM_LABELS[t] for t in r["terms"]) + " |",
              "|---|---|" + "---|" * len(r["terms"])]
    for c in held + dev:
        lines.append(f"| {c['label']} | {_vox(c['rms_term_vox']['correlation'])} | "
                     + " | ".join(_vox(c["rms_term_vox"][t]) for t in r["terms"]) + " |")
    lines += ["", notes, "", f"Time of this evaluation: {r['seconds']:.0f} s (each chain, run "
              "once and saved: 1-4 minutes on two shared cores).", ""]
    return "\n".join(lines)


def load(path: Path) -> dict:
    """A result written by :func:`run`."""
    return json.loads(Path(path).read_text())


__all__ = ["BAND", "CASES", "TERMS", "evaluate", "markdown", "resolve", "run", "run_chain"]
