"""Wrong matches against the tracked fraction over the matcher's ratio test.

:func:`measure_ambiguity` runs one vortex pair of :mod:`pipelines.studies.tracking` (the vortex
axis along x, y or z), fits the particles' positions once and matches them at each ambiguity
ratio (:class:`plenopiv.tracking.settings.TrackingSettings` ``ambiguity_ratio``); each wrong
track is classified by what went wrong. Stage function: a case in, a dict of numbers out.
``pipelines/validate_tracking_ambiguity.py`` writes ``docs/validation/tracking_ambiguity.*``.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from pipelines.studies.tracking import _calibration, _simulate, associate_tracks
from plenopiv.config.experiment import Experiment, ImagesConfig, OutputConfig
from plenopiv.piv.settings import PIVSettings
from plenopiv.tracking.matching import predict_positions
from plenopiv.tracking.settings import TrackingSettings
from plenopiv.workflow.pair import process_pair
from plenopiv.workflow.tracking import match_ends, track_ends
from plenopiv.workflow.vortex_case import VortexCase

__all__ = ["AXES", "RATIOS", "classify_wrong", "measure_ambiguity"]

#: Ambiguity ratios of the curve (1: no ratio test).
RATIOS = (1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3)
#: Vortex axes of the study.
AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}
#: Thresholds of the classes, resolution cells (the predictor's and the positions' errors) and
#: lenslets (an end seen through few).
CLASS_LIMITS = {"ambiguous_quality": 0.3, "predictor_cells": 0.5, "depth_cells": 0.5,
                "few_lenslets": 10}


def _wrong(tracks, true_a, true_b, scale) -> tuple[np.ndarray, np.ndarray]:
    """Per track: no true particle within one cell of both ends (the study's criterion), and
    the ends' nearest true particles differ (identity)."""
    ja = associate_tracks(tracks.position_a, tracks.position_b, true_a, true_b, scale)
    if not len(tracks):
        return np.zeros(0, bool), np.zeros(0, bool)
    _, ka = cKDTree(true_a / scale).query(tracks.position_a / scale)
    _, kb = cKDTree(true_b / scale).query(tracks.position_b / scale)
    return ja < 0, ka != kb


def classify_wrong(tracks, predicted_b, true_a, true_b, scale) -> list[dict]:
    """What went wrong with each wrong track (either criterion of :func:`_wrong`).

    Flags (a track may carry several): ``ambiguous`` (match quality below
    ``CLASS_LIMITS['ambiguous_quality']``: a runner-up nearly as close), ``unresolved`` (the
    true particles nearest its two ends differ and lie within one cell of each other at A:
    two particles seen as one), ``predictor``
    (the prediction misses the true B position of the A end's particle by more than
    ``CLASS_LIMITS['predictor_cells']``), ``depth`` (an end's depth error beyond
    ``CLASS_LIMITS['depth_cells']``), ``few_lenslets`` (an end seen through fewer than
    ``CLASS_LIMITS['few_lenslets']`` lenslets). ``predicted_b`` (N, 3) metres, one per track.
    """
    sc = np.asarray(scale, float)
    wrong, ident = _wrong(tracks, true_a, true_b, sc)
    ta, tb = true_a / sc, true_b / sc
    out = []
    for k in np.flatnonzero(wrong | ident):
        pa, pb = tracks.position_a[k] / sc, tracks.position_b[k] / sc
        _, i = cKDTree(ta).query(pa)
        _, j = cKDTree(tb).query(pb)
        out.append({
            "criterion": "cell" if wrong[k] else "identity",
            "quality": float(tracks.quality[k]),
            "ambiguous": bool(tracks.quality[k] < CLASS_LIMITS["ambiguous_quality"]),
            "unresolved": bool(i != j and np.linalg.norm(ta[i] - ta[j]) <= 1.0),
            "predictor": bool(np.linalg.norm(predicted_b[k] / sc - tb[i])
                              > CLASS_LIMITS["predictor_cells"]),
            "depth": bool(max(abs(pa[2] - ta[i, 2]), abs(pb[2] - tb[j, 2]))
                          > CLASS_LIMITS["depth_cells"]),
            "few_lenslets": bool(min(tracks.n_lenslets_a[k], tracks.n_lenslets_b[k])
                                 < CLASS_LIMITS["few_lenslets"]),
            "separation_cells": float(np.linalg.norm(ta[i] - ta[j]))})
    return out


def measure_ambiguity(case: VortexCase, axis: str = "y", ratios=RATIOS) -> dict:
    """Tracked fraction and wrong rates of one pair at each ambiguity ratio.

    Returns
    -------
    dict
        ``curve``: per ratio (``merged_brightness`` at its default) ``tracked_fraction``
        (true particles with a correct track / true particles inside the volume),
        ``wrong_rate`` (no true particle within one cell of both ends / tracks),
        ``identity_rate`` (the ends' nearest true particles differ / tracks),
        ``n_tracks``, ``rejected_ambiguous``, ``rejected_merged``; ``without_tests`` the
        same for ratio 1 and ``merged_brightness`` 0; ``wrong_tracks`` (their classes,
        :func:`classify_wrong`) at each ratio and ``"plain"``; ``seconds``.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(case.seed)
    cam, cal = _calibration(case, rng)
    grid, _, pair, ia, ib = _simulate(case, cam, cal, rng, axis=AXES[axis])
    exp = Experiment(camera=cal.camera, volume=grid,
                     piv=PIVSettings(windows=tuple(case.windows_vox), overlap=0.5, passes=3,
                                     response_particles_per_lenslet=case.particles_per_lenslet),
                     images=ImagesConfig(dt_s=case.dt), output=OutputConfig(weights_cache=""))
    res = process_pair(cal, ia, ib, exp)
    ends = track_ends(cal, ia, ib, res.volume_a, res.volume_b, settings=exp.tracking)
    corr = res.volume_a.correction
    lo, hi = grid.bounds[:, 0].copy(), grid.bounds[:, 1].copy()
    lo[2], hi[2] = corr.depth(lo[2]), corr.depth(hi[2])
    true_a, true_b = pair.positions_a, pair.positions_b
    inside = np.all((true_a >= lo) & (true_a <= hi) & (true_b >= lo) & (true_b <= hi), axis=1)
    n_true = int(inside.sum())
    curve, classes = [], {}
    default = TrackingSettings().ambiguity_ratio
    plain = TrackingSettings(ambiguity_ratio=1.0, merged_brightness=0.0)
    for r in [None, *sorted(set(ratios) | {1.0, default}, reverse=True)]:
        st = plain if r is None else TrackingSettings(ambiguity_ratio=r)
        tracks = match_ends(ends, res.vectors, settings=st)
        wrong, ident = _wrong(tracks, true_a, true_b, ends.scale)
        ja = associate_tracks(tracks.position_a, tracks.position_b, true_a, true_b, ends.scale)
        good = ja[(ja >= 0)]
        tracked = np.unique(good[inside[good]])
        n = len(tracks)
        point = {"ratio": r, "n_tracks": n, "tracked_fraction": len(tracked) / n_true,
                 "wrong_rate": float(wrong.mean()) if n else 0.0,
                 "identity_rate": float(ident.mean()) if n else 0.0,
                 "rejected_ambiguous": tracks.counts["rejected_ambiguous"],
                 "rejected_merged": tracks.counts["rejected_merged"]}
        pred = predict_positions(res.vectors, tracks.position_a)
        key = "plain" if r is None else str(r)
        classes[key] = classify_wrong(tracks, pred, true_a, true_b, ends.scale)
        if r is None:
            without = point
        else:
            curve.append(point)
    return {"flow": case.flow, "axis": axis, "particles_per_lenslet": case.particles_per_lenslet,
            "seed": case.seed, "n_true": n_true, "curve": curve, "without_tests": without,
            "wrong_tracks": classes,
            "seconds": round(time.perf_counter() - t0, 1)}
