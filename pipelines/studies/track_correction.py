"""Study: the correlation field against the same field corrected by the pair's tracks.

Each pair runs through :func:`plenopiv.workflow.pair.process_pair` with
``[tracking] correct_vectors = false`` (the correlation field as it is), then is tracked and
corrected with each prior of ``PRIORS`` (:func:`plenopiv.workflow.pair.corrected_by_tracks`);
both fields are scored against the flow (:func:`plenopiv.workflow.vortex_case.compare_with_truth`:
gain, bias, rms per component in voxels over valid vectors half a window inside the volume).

The pairs: the real-camera study's (`small_m1`, Lamb-Oseen, 0.15 particles per lenslet, true
calibration; ideal, and every effect of a real camera preprocessed;
:mod:`pipelines.studies.realcam`), and the CI camera's at 0.3 particles per lenslet (Poisson
noise, 0.5 px blur; Oseen and Hill) and with the vortex turned (0.15 ppl). See
docs/methods.md#track-correction.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipelines.studies import realcam as rc
from pipelines.studies.output import fmt, table, write_json, write_text
from plenopiv.calibration.model import Calibration
from plenopiv.preprocess.settings import PreprocessSettings
from plenopiv.products.images import write_image_stack
from plenopiv.reconstruction.build import weights_for
from plenopiv.tracking.settings import PRIOR_TRACKS
from plenopiv.workflow import vortex_case as vc
from plenopiv.workflow.pair import process_pair
from plenopiv.workflow.tracking import corrected_by_tracks

#: The priors compared (tracks); the default is :data:`PRIOR_TRACKS`.
PRIORS = (0.25, 0.5, 1.0, 2.0)


def _scores(vec, flow, dt, grid, window) -> dict:
    e = vc.compare_with_truth(replace(vec, dt=None), flow, dt, grid, window)
    return {"gain": e["gain"], "bias_vox": e["bias_vox"], "rms_vox": e["rms_vox"]}


def _corrected(cal, res, exp, weights, flow, dt, window) -> dict:
    """The pair's field as correlated and corrected with each prior, scored."""
    images = (res.images[0].image, res.images[1].image)
    out = {"correlation": _scores(res.vectors, flow, dt, exp.volume, window)}
    for prior in PRIORS:
        e = replace(exp, tracking=replace(exp.tracking, prior_tracks=prior))
        vec, _, record = corrected_by_tracks(cal, images, (res.volume_a, res.volume_b),
                                             res.vectors, e, weights)
        out[f"prior {prior:g}"] = {**_scores(vec, flow, dt, exp.volume, window),
                                   "tracks": record.get("tracks", 0)}
    return out


def _uncorrected(exp):
    """The study's experiment, neither corrected by tracks nor fitted to continuity."""
    return replace(exp, tracking=replace(exp.tracking, correct_vectors=False),
                   piv=replace(exp.piv, continuity=False))


def realcam_pair(seed: int, effect: str, work: Path) -> dict:
    """One pair of the real-camera study (true calibration), scored both ways."""
    return _corrected(*realcam_run(seed, effect, work, _uncorrected))


def realcam_run(seed: int, effect: str, work: Path, settings) -> tuple:
    """One pair of the real-camera study (true calibration) run through ``process_pair``
    with the experiment ``settings(exp)`` makes of the study's own; returns
    ``(calibration, PairResult, experiment, weights, flow, dt, window_vox)``."""
    setup = rc.StudyCase(seed=seed, calibrate=False)
    t = rc.truth(setup)
    frames = rc.record_case(setup, rc.recording(effect), t)
    work.mkdir(parents=True, exist_ok=True)
    cal = Calibration.from_camera(setup.truth_camera())
    case = setup.vortex()
    exp = settings(replace(vc.case_experiment(case, cal, work), base_dir=work))
    if effect != rc.IDEAL:
        dark = None if frames.dark is None else write_image_stack(work / "dark.tif",
                                                                  frames.dark).name
        white = None if frames.white is None else write_image_stack(work / "white.tif",
                                                                    frames.white).name
        exp = replace(exp, preprocess=PreprocessSettings(dark=dark, white=white,
                                                         hot_pixels="auto"))
    weights, _ = weights_for(cal, exp.volume, exp.reconstruction)
    res = process_pair(cal, frames.image_a, frames.image_b, exp, weights=weights)
    return cal, res, exp, weights, t.flow, t.dt, case.windows_vox[-1]


def vortex_pair(flow: str, seed: int, ppl: float, axis, work: Path) -> dict:
    """One pair of the CI camera (true calibration, noise, 0.5 px blur), scored both ways."""
    return _corrected(*vortex_run(flow, seed, ppl, axis, work, _uncorrected))


def vortex_run(flow: str, seed: int, ppl: float, axis, work: Path, settings) -> tuple:
    """One pair of the CI camera (true calibration, noise, 0.5 px blur) run through
    ``process_pair`` with ``settings(exp)``; returns what :func:`realcam_run` does."""
    case = vc.VortexCase(flow=flow, particles_per_lenslet=ppl, seed=seed, blur_px=0.5,
                         uncertainty="correlation", calibrate=False, flow_axis=axis)
    work.mkdir(parents=True, exist_ok=True)
    cam = vc.case_camera(case)
    cal = Calibration.from_camera(cam)
    exp = settings(vc.case_experiment(case, cal, work))
    ia, ib, _, fl, _ = vc._case_pair(case, exp.volume, cam, np.random.default_rng(seed), work,
                                     lambda *a: None)
    weights, _ = weights_for(cal, exp.volume, exp.reconstruction)
    res = process_pair(cal, ia, ib, exp, weights=weights)
    return cal, res, exp, weights, fl, case.dt, case.windows_vox[-1]


#: The groups of pairs: name -> list of (label, callable(work) -> scores); ``realcam_pair``
#: and ``vortex_pair`` score one pair (another study passes its own).
def groups(seeds=(1, 2, 3, 4, 5, 6), ci_seeds=(1, 2, 3), realcam_pair=realcam_pair,
           vortex_pair=vortex_pair) -> dict:
    g = {"real-camera study, ideal": [(f"seed {s}", lambda w, s=s: realcam_pair(s, rc.IDEAL, w))
                                      for s in seeds],
         "real-camera study, every effect": [
             (f"seed {s}", lambda w, s=s: realcam_pair(s, rc.ALL, w)) for s in seeds],
         "CI camera, Oseen, 0.3 ppl": [(f"seed {s}", lambda w, s=s: vortex_pair(
             "oseen", s, 0.3, None, w)) for s in ci_seeds],
         "CI camera, Hill, 0.3 ppl": [(f"seed {s}", lambda w, s=s: vortex_pair(
             "hill", s, 0.3, None, w)) for s in ci_seeds],
         "turned, 0.15 ppl": [
             ("Hill about x", lambda w: vortex_pair("hill", 4, 0.15, "x", w)),
             ("Oseen about x", lambda w: vortex_pair("oseen", 4, 0.15, "x", w)),
             ("Oseen about z", lambda w: vortex_pair("oseen", 4, 0.15, "z", w))]}
    return g


def run(out: str | Path, work: str | Path, **kw) -> dict:
    """Every pair of :func:`groups`; writes ``track_correction.json`` and ``.md`` to ``out``."""
    out, work = Path(out), Path(work)
    t0 = time.perf_counter()
    result = {"priors": list(PRIORS), "default_prior": PRIOR_TRACKS, "groups": {}}
    for name, pairs in groups(**kw).items():
        rows = {}
        for label, make in pairs:
            rows[label] = make(work / f"{name}_{label}".replace(" ", "_").replace(",", ""))
            print(f"{name}, {label}: done", flush=True)
        result["groups"][name] = rows
    result["seconds"] = round(time.perf_counter() - t0, 1)
    write_json(out / "track_correction.json", result)
    write_text(out / "track_correction.md", markdown(result))
    return result


def _mean(rows: dict, key: str, what: str, c: int) -> float:
    return float(np.nanmean([r[key][what][c] for r in rows.values()]))


def markdown(result: dict) -> str:
    """The page: per group the mean figures before and after, and every pair."""
    d = f"prior {result['default_prior']:g}"
    lines = ["# The correlation field corrected by the pair's tracks", "",
             "Made by `python pipelines/validate_track_correction.py --out docs/validation` "
             f"({result['seconds']:.0f} s); the method and the reading: "
             "[methods](../methods.md#track-correction). Voxels; valid vectors half a "
             "window inside the volume; gain: least-squares slope of measured on true.", ""]
    rows = []
    for name, g in result["groups"].items():
        cells = [name, len(g)]
        for key in ("correlation", d):
            cells.append(fmt(_mean(g, key, "gain", 2), ".3f"))
        for c in range(3):
            cells.append(f"{_mean(g, 'correlation', 'rms_vox', c):.3f} → "
                         f"{_mean(g, d, 'rms_vox', c):.3f}")
        rows.append(cells)
    lines += ["## Mean per group, the default prior", ""]
    lines += table(["pairs", "n", "w gain, correlation", "w gain, corrected", "rms u",
                    "rms v", "rms w"], rows)
    lines += ["", "## Every pair and prior", ""]
    keys = ["correlation", *(f"prior {p:g}" for p in result["priors"])]
    every = []
    for name, g in result["groups"].items():
        for label, r in g.items():
            every.append([name, label, *(f"{fmt(r[k]['gain'][2], '.3f')} / "
                                         f"{r[k]['rms_vox'][2]:.3f}" for k in keys)])
    lines += table(["pairs", "pair", *(f"{k}: w gain / rms w" for k in keys)], every)
    return "\n".join(lines) + "\n"
