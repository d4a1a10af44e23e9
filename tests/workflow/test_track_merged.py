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
