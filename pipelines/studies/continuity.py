"""Study: the vector field before and after its depth component is fitted to continuity.

Each pair runs through :func:`plenopiv.workflow.pair.process_pair` as ``plenopiv run`` does
(tracked and corrected by its tracks) with ``[piv] continuity = false``; the field is then
fitted (:func:`plenopiv.workflow.correlation.fitted_to_continuity`) and both are scored
against the flow (:func:`plenopiv.workflow.vortex_case.compare_with_truth`: gain, bias and
rms per component in voxels over valid vectors half a window inside the volume, and the w
gain in three bands of distance from focus). Each pair twice: with the correlation
statistics as uncertainties (as the study pages run) and with the chain's response
(``[piv] uncertainty = "response"``, the default).

The pairs are the track-correction study's (:mod:`pipelines.studies.track_correction`): the
real-camera study's (`small_m1`, Lamb-Oseen, 0.15 particles per lenslet, ideal and every
effect preprocessed, seeds 1-6), the CI camera's at 0.3 particles per lenslet (Oseen and
Hill, seeds 1-3) and the vortex turned (0.15 ppl). See docs/methods.md#depth-from-continuity.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipelines.studies import track_correction as tc
from pipelines.studies.output import fmt, table, write_json, write_text
from plenopiv.workflow import vortex_case as vc
from plenopiv.workflow.correlation import fitted_to_continuity

#: The uncertainties the fit is weighted by, as ``[piv] uncertainty``.
UNCERTAINTIES = ("correlation", "response")


def _scores(vec, flow, dt, grid, window) -> dict:
    e = vc.compare_with_truth(replace(vec, dt=None), flow, dt, grid, window)
    return {"gain": e["gain"], "bias_vox": e["bias_vox"], "rms_vox": e["rms_vox"],
            "w_gain_by_depth": [b["gain"][2] for b in e["by_depth"]],
            "coverage_2sigma": e.get("coverage_2sigma")}


def _both(cal, res, exp, weights, flow, dt, window) -> dict:
    after, record = fitted_to_continuity(res.vectors, replace(exp.piv, continuity=True))
    return {"before": _scores(res.vectors, flow, dt, exp.volume, window),
            "after": _scores(after, flow, dt, exp.volume, window), "record": record}


def _settings(uncertainty: str):
    def settings(exp):
        return replace(exp, piv=replace(exp.piv, continuity=False, uncertainty=uncertainty))
    return settings


def run(out: str | Path, work: str | Path, **kw) -> dict:
    """Every pair of the track-correction study, with each of :data:`UNCERTAINTIES`;
    writes ``continuity.json`` and ``.md`` to ``out``."""
    out, work = Path(out), Path(work)
    t0 = time.perf_counter()
    result = {"uncertainties": list(UNCERTAINTIES), "groups": {}}
    for unc in UNCERTAINTIES:
        groups = tc.groups(**kw, realcam_pair=lambda s, e, w, u=unc: _both(
            *tc.realcam_run(s, e, w, _settings(u))), vortex_pair=lambda *a, u=unc: _both(
            *tc.vortex_run(*a, _settings(u))))
        for name, pairs in groups.items():
            rows = result["groups"].setdefault(name, {})
            for label, make in pairs:
                folder = f"{unc}_{name}_{label}".replace(" ", "_").replace(",", "")
                rows.setdefault(label, {})[unc] = make(work / folder)
                print(f"{unc}: {name}, {label}: done", flush=True)
    result["seconds"] = round(time.perf_counter() - t0, 1)
    write_json(out / "continuity.json", result)
    write_text(out / "continuity.md", markdown(result))
    return result


def _mean(values) -> float:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(values)) if values else float("nan")


def _low(values) -> float:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.min(values)) if values else float("nan")


def markdown(result: dict) -> str:
    """The page: per group and uncertainty the mean figures before and after, then every
    pair."""
    lines = ["# The depth component fitted to continuity", "",
             "Made by `python pipelines/validate_continuity.py --out docs/validation` "
             f"({result['seconds']:.0f} s); the method: "
             "[methods](../methods.md#depth-from-continuity). *Before*: the field of "
             "`plenopiv run` with `[piv] continuity = false` (tracked and corrected by its "
             "tracks); *after*: the same field fitted. Voxels; valid vectors half a window "
             "inside the volume; gain: least-squares slope of measured on true; the lowest "
             "pair's w gain in brackets; w within ±2σ: the share of the true errors of w within "
             "twice its uncertainty, lowest–highest pair (the fit's own uncertainty after); "
             "χ²: the fit's misfit per vector (the fit is kept up to 9).", ""]
    rows = []
    for unc in result["uncertainties"]:
        for name, g in result["groups"].items():
            pairs = [p[unc] for p in g.values()]
            cells = [name, unc, len(pairs)]
            for key in ("before", "after"):
                w = [p[key]["gain"][2] for p in pairs]
                cells.append(f"{fmt(_mean(w), '.3f')} ({fmt(_low(w), '.3f')})")
            for c in range(3):
                cells.append(f"{_mean([p['before']['rms_vox'][c] for p in pairs]):.3f} → "
                             f"{_mean([p['after']['rms_vox'][c] for p in pairs]):.3f}")
            cells.append(f"{_mean([p['before']['bias_vox'][2] for p in pairs]):+.3f} → "
                         f"{_mean([p['after']['bias_vox'][2] for p in pairs]):+.3f}")
            cells.append(" → ".join(
                f"{fmt(_low([p[k]['coverage_2sigma'][2] for p in pairs]), '.2f')}–"
                f"{fmt(max(p[k]['coverage_2sigma'][2] for p in pairs), '.2f')}"
                for k in ("before", "after")))
            chi = [p["record"].get("chi2_per_vector") for p in pairs]
            cells.append(f"{_low(chi):.2f}–{max(c for c in chi if c is not None):.2f}")
            cells.append(f"{sum(p['record']['applied'] for p in pairs)}/{len(pairs)}")
            rows.append(cells)
    lines += ["## Mean per group", ""]
    lines += table(["pairs", "uncertainty", "n", "w gain before", "w gain after", "rms u",
                    "rms v", "rms w", "bias w", "w within ±2σ", "χ²", "fitted"], rows)
    lines += ["", "## Every pair", "",
              "w gain before → after, by |Z| band (nearest focus first) after, rms u / w "
              "before → after, χ²:", ""]
    every = []
    for name, g in result["groups"].items():
        for label, p in g.items():
            for unc in result["uncertainties"]:
                b, a, r = p[unc]["before"], p[unc]["after"], p[unc]["record"]
                bands = " / ".join(fmt(x, ".2f") for x in a["w_gain_by_depth"])
                every.append([name, label, unc,
                              f"{fmt(b['gain'][2], '.3f')} → {fmt(a['gain'][2], '.3f')}",
                              bands,
                              f"{b['rms_vox'][0]:.3f} / {b['rms_vox'][2]:.3f} → "
                              f"{a['rms_vox'][0]:.3f} / {a['rms_vox'][2]:.3f}",
                              fmt(r.get("chi2_per_vector"), ".2f")])
    lines += table(["pairs", "pair", "uncertainty", "w gain", "w gain by |Z| band",
                    "rms u / w", "χ²"], every)
    return "\n".join(lines) + "\n"
