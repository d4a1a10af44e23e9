"""The ratio-test study's classification of wrong tracks, on constructed tracks."""

import numpy as np

from pipelines.studies.tracking_ambiguity import _wrong, classify_wrong
from pipelines.studies.tracking_ambiguity_report import _pooled
from plenopiv.tracking.tracks import TrackResult

UNIT = np.ones(3)


def _tracks(pa, pb, quality, lenslets=20):
    pa, pb = np.asarray(pa, float), np.asarray(pb, float)
    n = len(pa)
    zero, index = np.zeros((n, 3)), np.arange(n)
    return TrackResult(pa, pb, zero, zero, np.asarray(quality, float), np.zeros(n), index,
                       index, np.full(n, lenslets), np.full(n, lenslets))


def test_an_unresolved_pair_is_an_identity_error_not_a_wrong_match():
    # two true particles 0.6 cell apart, moving together by (1, 0, 0); one track half-way
    # between them, its B end nearer the other particle
    true_a = np.array([[0.0, 0, 0], [0.6, 0, 0], [9, 9, 9]])
    true_b = true_a + [1.0, 0, 0]
    t = _tracks([[0.25, 0, 0]], [[1.35, 0, 0]], [0.9])
    wrong, ident = _wrong(t, true_a, true_b, UNIT)
    assert not wrong[0] and ident[0]
    (c,) = classify_wrong(t, np.array([[1.2, 0, 0]]), true_a, true_b, UNIT)
    assert c["criterion"] == "identity" and c["unresolved"] and not c["ambiguous"]
    assert not c["predictor"] and not c["depth"] and np.isclose(c["separation_cells"], 0.6)


def test_a_wrong_match_carries_its_causes():
    # the B end lies 2 cells from the true partner; the prediction missed it by 1.5 cells
    true_a = np.array([[0.0, 0, 0], [5, 5, 5]])
    true_b = true_a + [1.0, 0, 0]
    t = _tracks([[0.0, 0, 0]], [[1.0, 0, 2.0]], [0.1], lenslets=6)
    wrong, _ = _wrong(t, true_a, true_b, UNIT)
    assert wrong[0]
    (c,) = classify_wrong(t, np.array([[1.0, 0, 1.5]]), true_a, true_b, UNIT)
    assert c["criterion"] == "cell" and c["ambiguous"] and c["predictor"] and c["depth"]
    assert c["few_lenslets"]


def test_pooled_rates_weigh_cases_by_their_particles_and_tracks():
    rows = [{"n_true": 100, "curve": [{"ratio": 1.0, "n_tracks": 50, "tracked_fraction": 0.5,
                                       "wrong_rate": 0.02, "identity_rate": 0.04}]},
            {"n_true": 300, "curve": [{"ratio": 1.0, "n_tracks": 150, "tracked_fraction": 0.6,
                                       "wrong_rate": 0.0, "identity_rate": 0.0}]}]
    p = _pooled(rows, 1.0)
    assert np.isclose(p["tracked"], 0.575) and np.isclose(p["wrong"], 0.005)
    assert np.isclose(p["identity"], 0.01) and p["worst"] == 0.02 and p["n"] == 200
