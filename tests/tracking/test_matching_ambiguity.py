"""The matcher's ratio test and mutual check, and its wrong-match rate on a known field."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from plenopiv.tracking.matching import MatchSettings, match_particles
from plenopiv.tracking.settings import TrackingSettings

#: Distances in these tests are in resolution cells: a unit scale.
UNIT = np.ones(3)
STRICT = MatchSettings(ambiguity_ratio=0.7)


def _match(pa, pb, pred, settings=STRICT):
    return match_particles(np.asarray(pa, float), np.asarray(pb, float),
                           np.asarray(pred, float), UNIT, settings=settings)


def test_ratio_test_refuses_a_second_b_candidate_nearly_as_close():
    # two B particles 0.30 and 0.35 cell from the prediction: d1/d2 = 0.86 > 0.7
    m = _match([[0, 0, 0]], [[0.30, 0, 0], [-0.35, 0, 0]], [[0, 0, 0]])
    assert len(m) == 0 and m.rejected_ambiguous == 1


def test_ratio_test_accepts_a_clear_partner():
    # 0.10 against 0.90 cell: d1/d2 = 0.11
    m = _match([[0, 0, 0]], [[0.10, 0, 0], [-0.90, 0, 0]], [[0, 0, 0]])
    assert list(m.index_b) == [0] and m.rejected_ambiguous == 0
    np.testing.assert_allclose(m.quality, [1 - 0.1 / 0.9])


def test_ratio_test_refuses_a_b_particle_two_predictions_contest():
    # one B particle; the predictions of two A particles 0.30 and 0.35 cell from it
    pa = [[0, 0, 0], [5, 0, 0]]
    m = _match(pa, [[0, 0, 0]], [[0.30, 0, 0], [-0.35, 0, 0]])
    assert len(m) == 0 and m.rejected_ambiguous == 1 and m.rejected_mutual == 1


def test_the_runner_up_counts_beyond_the_search_radius():
    # the runner-up 1.2 cell away lies outside the 1-cell search but makes 0.9 ambiguous
    m = _match([[0, 0, 0]], [[0.9, 0, 0], [-1.2, 0, 0]], [[0, 0, 0]])
    assert len(m) == 0 and m.rejected_ambiguous == 1


def test_matching_is_mutual():
    # A0's nearest B is B0, but B0's nearest prediction is A1's: A0 keeps no partner
    m = _match([[0, 0, 0], [3, 0, 0]], [[0.5, 0, 0], [9, 9, 9]], [[0, 0, 0], [0.6, 0, 0]],
               settings=MatchSettings(ambiguity_ratio=1.0))
    assert list(m.index_a) == [1] and list(m.index_b) == [0] and m.rejected_mutual == 1


def test_ratio_one_keeps_every_mutual_nearest_pair():
    m = _match([[0, 0, 0]], [[0.30, 0, 0], [-0.35, 0, 0]], [[0, 0, 0]],
               settings=MatchSettings(ambiguity_ratio=1.0))
    assert list(m.index_b) == [0] and m.rejected_ambiguous == 0


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5, float("nan"), float("inf")])
def test_ambiguity_ratio_out_of_range_is_refused_by_name(bad):
    with pytest.raises(ValueError, match="ambiguity_ratio"):
        MatchSettings(ambiguity_ratio=bad)
    with pytest.raises(ValidationError, match="ambiguity_ratio"):
        TrackingSettings(ambiguity_ratio=bad)


def test_tracking_settings_pass_the_ratio_to_the_matcher():
    assert TrackingSettings(ambiguity_ratio=0.55).match_settings().ambiguity_ratio == 0.55


def _known_field(seed, density=0.2, side=20.0, predictor_cells=0.15, lost=0.15, ghosts=0.15):
    """Particles in a cube of ``side`` cells moved by a uniform flow.

    ``density`` particles per cubic cell (0.2: nearest neighbours 0.95 cell apart on
    average, denser than the 0.3-per-lenslet study case); the prediction errs by
    ``predictor_cells`` per axis (the correlation's error at the tracks, in cells); position
    noise 0.05 cell; a fraction ``lost`` of the particles is missing in B and ``ghosts``
    unrelated particles are added to it.
    """
    rng = np.random.default_rng(seed)
    n = int(density * side ** 3)
    pa = rng.uniform(0, side, (n, 3))
    flow = np.array([0.5, -0.3, 0.8])
    pb = pa + flow + rng.normal(0, 0.05, (n, 3))
    kept = rng.random(n) >= lost
    extra = rng.uniform(0, side, (int(ghosts * n), 3))
    b = np.concatenate([pb[kept], extra])
    owner = np.concatenate([np.flatnonzero(kept), np.full(len(extra), -1)])
    pred = pa + flow + rng.normal(0, predictor_cells, (n, 3))
    return pa, b, pred, owner


def _rates(settings, seeds=(1, 2, 3)):
    wrong = tracks = right = total = 0
    for seed in seeds:
        pa, b, pred, owner = _known_field(seed)
        m = _match(pa, b, pred, settings)
        w = owner[m.index_b] != m.index_a
        wrong, tracks = wrong + int(w.sum()), tracks + len(m)
        right, total = right + int((~w).sum()), total + len(pa)
    return wrong / tracks, right / total


def test_wrong_rate_on_a_known_field_stays_below_the_bar():
    wrong, tracked = _rates(MatchSettings(ambiguity_ratio=TrackingSettings().ambiguity_ratio))
    wrong_without, _ = _rates(MatchSettings(ambiguity_ratio=1.0))
    assert wrong <= 0.02 and tracked >= 0.5
    assert wrong < 0.75 * wrong_without          # the ratio test removes wrong matches


@pytest.mark.parametrize("n_a", [0, 1, 2, 5])
@pytest.mark.parametrize("n_b", [0, 1, 2, 5])
@pytest.mark.parametrize("offset", [0.0, 0.4, 3.0])
def test_every_count_of_particles_matches_without_error(n_a, n_b, offset):
    # every size of A and B, with their partners on, near or beyond the search radius
    # (3 cells: no prediction finds a partner): the matcher answers with a (maybe empty)
    # result, never an error from an empty selection
    rng = np.random.default_rng(n_a * 10 + n_b)
    pa = rng.uniform(0, 20, (n_a, 3))
    pb = np.vstack([pa[:n_b] + [offset, 0, 0], rng.uniform(40, 60, (max(n_b - n_a, 0), 3))])
    m = _match(pa, pb, pa)
    assert len(m) <= min(n_a, n_b)
    if offset == 3.0 or not n_a or not n_b:
        assert len(m) == 0
    elif offset == 0.0:
        assert len(m) == min(n_a, n_b)


@pytest.mark.parametrize("where", ["prediction", "position_a", "position_b"])
def test_a_particle_without_a_finite_prediction_or_position_is_matched_to_nothing(where):
    # a masked or rejected vector leaves NaN in the field, hence in the predictions of the
    # particles near it: they take no part, the others match as before, with their indices
    pa = np.array([[0.0, 0, 0], [5, 0, 0], [10, 0, 0]])
    pb = pa + [0.1, 0, 0]
    pred = pa.copy()
    if where == "prediction":
        pred[1] = np.nan
    elif where == "position_a":
        pa[1, 2] = np.inf
    else:
        pb[1] = np.nan
    m = _match(pa, pb, pred)
    assert list(m.index_a) == [0, 2] and list(m.index_b) == [0, 2]
