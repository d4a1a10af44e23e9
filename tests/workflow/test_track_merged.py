"""Tracks of two particles seen as one (both ends bright) are refused; the rest are kept."""

from types import SimpleNamespace

import numpy as np
import pytest

from plenopiv.tracking.settings import TrackingSettings
from plenopiv.workflow.tracking import TrackEnds, match_ends

CELL = np.array([0.125e-3, 0.125e-3, 0.55e-3])


def _ends(brightness_a, brightness_b):
    """Five particles 2 mm apart, at rest, each seen through 20 lenslets."""
    p = np.array([[i * 2e-3, 0.0, 0.0] for i in range(5)])
    fit = SimpleNamespace(converged=np.ones(5, bool), n_lenslets=np.full(5, 20))
    zero = np.zeros((5, 3))
    return TrackEnds(p, zero, fit, p.copy(), zero, fit, CELL, {},
                     np.asarray(brightness_a, float), np.asarray(brightness_b, float))


def _still():
    axis = np.linspace(-1e-3, 9e-3, 3)
    zero = np.zeros((3, 3, 3))
    return SimpleNamespace(x=axis, y=axis, z=axis, u=zero, v=zero, w=zero, dt=1e-3)


@pytest.mark.parametrize(("a", "b", "kept"), [
    ([1, 1, 2, 1, 1], [1, 1, 2, 1, 1], 4),      # bright at both ends: two particles as one
    ([1, 1, 2, 1, 1], [1, 1, 1, 1, 1], 5),      # bright once: resolved in B, kept
    ([1, 1, 1.3, 1, 1], [1, 1, 1.3, 1, 1], 5),  # within the brightness spread: kept
])
def test_a_track_bright_at_both_ends_is_refused(a, b, kept):
    t = match_ends(_ends(a, b), _still(), settings=TrackingSettings(min_lenslets=6))
    assert len(t) == kept and t.counts["rejected_merged"] == 5 - kept
    assert t.counts["tracks"] == kept


def test_merged_brightness_zero_keeps_every_track():
    t = match_ends(_ends([1, 1, 2, 1, 1], [1, 1, 2, 1, 1]), _still(),
                   settings=TrackingSettings(merged_brightness=0.0))
    assert len(t) == 5 and t.counts["rejected_merged"] == 0


def test_the_limit_follows_the_spread_of_brightness(rng):
    """Log-normal brightness of spread 0.3 (a real recording's): 2.5 robust deviations above
    the median is exp(0.75) = 2.1, so a particle twice the median (as bright as two merged
    ones, 0.6 % of such particles and more) is kept, while with all particles alike the
    1.45 limit refuses it."""
    from plenopiv.workflow.tracking import _merged

    n = 400
    spread = np.exp(0.3 * rng.standard_normal(n))
    spread[0] = 2.0
    alike = np.ones(n)
    alike[0] = 2.0
    fit = SimpleNamespace(converged=np.ones(n, bool), n_lenslets=np.full(n, 20))
    idx = np.arange(n)
    for b, refused in ((spread, False), (alike, True)):
        ends = SimpleNamespace(brightness_a=b, brightness_b=b, bundle_a=fit, bundle_b=fit)
        merged = _merged(ends, idx, idx, TrackingSettings(min_lenslets=6))
        assert bool(merged[0]) is refused
        assert merged.mean() <= (0.02 if not refused else 1.0 / n)
