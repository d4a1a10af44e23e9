"""Intensity capping before the correlation (``[piv] intensity_cap``).

A particle's brightness is the laser's, its size's and the reconstruction's, not the flow's:
with capping, a window follows its particles rather than its brightest few, so the field
of particles of unequal brightness is the field of the same particles equally bright.
"""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.camera.grid import VolumeGrid
from plenopiv.piv import PIVSettings, correlate_volumes
from plenopiv.piv.evidence import capped
from plenopiv.piv.settings import INTENSITY_CAP
from plenopiv.synthetic.truth import gaussian_truth_volume


def test_capped_is_the_fraction_of_the_median_particle_peak():
    volume = np.zeros((4, 5, 6), np.float32)
    index = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]])
    volume[tuple(index.T)] = [1.0, 4.0, 9.0, 16.0]          # median of the peaks: 6.5
    volume[0, 4, 5] = 30.0                                  # not a particle: capped too
    out = capped(volume, index, 0.5)
    assert out.max() == pytest.approx(3.25)
    np.testing.assert_array_equal(out[tuple(index.T)], [1.0, 3.25, 3.25, 3.25])
    assert volume.max() == 30.0                             # the input is not changed
    assert capped(volume, index, 0.0) is volume             # 0: not capped
    assert capped(volume, np.zeros((0, 3), int), 0.5) is volume   # no particle


def test_capping_scales_with_the_volume():
    """A weaker pulse (volume B times a constant) is capped at the same share of it."""
    rng = np.random.default_rng(3)
    volume = rng.random((6, 7, 8)).astype(np.float32)
    index = np.argwhere(volume > 0.9)
    np.testing.assert_allclose(capped(0.3 * volume, index, 0.5),
                               0.3 * capped(volume, index, 0.5), rtol=1e-6)


@pytest.mark.parametrize("value", [-0.1, float("nan"), float("inf"), "half", True])
def test_intensity_cap_is_a_fraction(value):
    with pytest.raises(ValueError, match="intensity_cap"):
        PIVSettings(intensity_cap=value)


def _sheared_pair(brightness, seed=0):
    """Particles in a shear u = 2 (z - z_mid) / depth voxels, rendered as elongated blobs."""
    voxel = (1e-4, 1e-4, 1e-4)
    grid = VolumeGrid.from_bounds((0.0, 48e-4), (0.0, 48e-4), (0.0, 48e-4), voxel=voxel)
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-4e-4, 52e-4, size=(700, 3))
    u = 2.0 * (pos[:, 2] - 24e-4) / 48e-4 * 1e-4
    moved = pos + np.stack([u, 0 * u, 0 * u], axis=1)
    sigma = (2.5, 0.9, 0.9)                                   # (z, y, x) voxels: a plenoptic blob
    weights = brightness(rng, len(pos))
    a = gaussian_truth_volume(grid, pos, weights, sigma_vox=sigma)
    b = gaussian_truth_volume(grid, moved, weights, sigma_vox=sigma)
    return grid, a, b, (pos, moved)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_brightness_spread_moves_the_capped_field_less(seed):
    """Lognormal brightness (σ_ln = 1, a laser sheet's and the particles' sizes' spread):
    the capped field stays closer to the field of the same particles equally bright than
    the field of the raw volumes does."""
    equal = _sheared_pair(lambda rng, n: np.ones(n), seed)
    spread = _sheared_pair(lambda rng, n: np.exp(rng.standard_normal(n)), seed)

    def field(pair, cap):
        grid, a, b, pos = pair
        s = PIVSettings(windows=((16, 16, 16),), passes=3, intensity_cap=cap)
        f = correlate_volumes(a, b, grid, settings=s, particles=pos)
        return np.asarray(f.u) / 1e-4

    for cap in (0.0, INTENSITY_CAP):
        assert np.all(np.isfinite(field(equal, cap)))
    raw = np.sqrt(np.mean((field(spread, 0.0) - field(equal, 0.0)) ** 2))
    cap = np.sqrt(np.mean((field(spread, INTENSITY_CAP) - field(equal, INTENSITY_CAP)) ** 2))
    assert cap < raw


def test_a_weaker_second_pulse_leaves_the_capped_field_as_it_is():
    """Volume B at 0.3 of A's energy: each volume is capped at its own particles' median,
    so the field is the one of equal pulses (to float32 rounding)."""
    grid, a, b, pos = _sheared_pair(lambda rng, n: np.exp(rng.standard_normal(n)))
    s = PIVSettings(windows=((16, 16, 16),), passes=3)
    full = correlate_volumes(a, b, grid, settings=s, particles=pos)
    weak = correlate_volumes(a, np.float32(0.3) * b, grid, settings=s, particles=pos)
    for c in ("u", "v", "w"):
        np.testing.assert_allclose(getattr(weak, c), getattr(full, c), rtol=0, atol=1e-3 * 1e-4)

