"""Evidence per vector: the particles each window holds, and the minimum a valid vector needs.

Volumes are sums of Gaussian blobs (standard deviation 1 voxel) placed at least 4 voxels
inside their windows, so that each window's count is known exactly and no particle image
reaches a neighbouring window: a window of n particles then correlates n pairs and nothing
else, and the valid fraction must follow ``min_particles_per_window`` exactly.
"""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import numpy as np
import pytest

from plenopiv import PIVError
from plenopiv.piv import (
    FLAG_EMPTY,
    FLAG_FEW_PARTICLES,
    PIVSettings,
    VectorField,
    correlate_volumes,
)
from plenopiv.piv.evidence import particle_table, window_counts
from plenopiv.piv.windows import _window_layout

WINDOW = 16
VOXEL = 1e-4          # metres
SHIFT_VOX = np.array([0.6, -0.4, 0.8])     # (z, y, x)


def render(shape, positions_vox, sigma=1.0):
    """Gaussian blobs of unit peak at ``positions_vox`` (N, 3) ``(z, y, x)``, cut at 3.5 sigma."""
    axes = [np.arange(n, dtype=float) for n in shape]
    volume = np.zeros(shape)
    for p in positions_vox:
        g = [np.where(np.abs(a - c) <= 3.5 * sigma, np.exp(-0.5 * ((a - c) / sigma) ** 2), 0.0)
             for a, c in zip(axes, p, strict=True)]
        volume += g[0][:, None, None] * g[1][None, :, None] * g[2][None, None, :]
    return volume.astype(np.float32)


def grid_of(shape):
    return SimpleNamespace(origin=(0.0, 0.0, 0.0), voxel_size=VOXEL, shape=shape)


def to_metres(positions_vox):
    """``(z, y, x)`` voxels to ``(x, y, z)`` metres on :func:`grid_of`."""
    return np.asarray(positions_vox, float)[:, ::-1] * VOXEL


def counted_windows(counts, rng):
    """Volume A, B, the particles (voxels) of each, for windows holding ``counts`` particles.

    ``counts`` has one entry per window of a (2, 2, len/4) layout of 16-voxel windows
    without overlap; particles lie 4 voxels or more inside their window, 3 voxels or more
    apart, and move by :data:`SHIFT_VOX`.
    """
    nx = len(counts) // 4
    shape = (2 * WINDOW, 2 * WINDOW, nx * WINDOW)
    positions = []
    for n, (iz, iy, ix) in zip(counts, itertools.product(range(2), range(2), range(nx)),
                               strict=True):
        lo = np.array([iz, iy, ix]) * WINDOW + 4
        inside = np.zeros((0, 3))
        while len(inside) < n:       # 3 voxels apart at least: one peak per particle
            p = rng.uniform(lo, lo + WINDOW - 9)
            if not len(inside) or np.min(np.linalg.norm(inside - p, axis=1)) >= 3.0:
                inside = np.vstack([inside, p])
        positions.append(inside)
    pa = np.concatenate(positions)
    pb = pa + SHIFT_VOX
    return render(shape, pa), render(shape, pb), pa, pb, shape


@pytest.mark.parametrize("minimum", [0, 1, 2, 3, 5])
@pytest.mark.parametrize("tables", [True, False], ids=["particle-tables", "volume-peaks"])
def test_valid_fraction_follows_the_minimum(rng, minimum, tables):
    """Windows of 0..7 particles: a vector is valid exactly where its window holds enough."""
    counts = [3, 0, 1, 2, 4, 5, 6, 7, 3, 1, 2, 5]           # 12 windows, (2, 2, 3)
    a, b, pa, pb, shape = counted_windows(counts, rng)
    s = PIVSettings(windows=WINDOW, overlap=0.0, passes=1, min_particles_per_window=minimum,
                    replacement="none")
    particles = (to_metres(pa), to_metres(pb)) if tables else None
    field = correlate_volumes(a, b, grid_of(shape), settings=s, particles=particles)
    n = np.array(counts).reshape(field.shape)
    np.testing.assert_array_equal(field.particles_per_window, n)
    few = (n < minimum) & (n > 0)
    np.testing.assert_array_equal((field.flag & FLAG_FEW_PARTICLES) != 0, few)
    np.testing.assert_array_equal((field.flag & FLAG_EMPTY) != 0, n == 0)
    np.testing.assert_array_equal(field.valid, n >= max(minimum, 1))
    # a valid vector measures the shift: one pass over a few particles, no gross error
    measured = np.stack([field.w, field.v, field.u])[:, field.valid] / VOXEL
    assert np.abs(measured - SHIFT_VOX[:, None]).max() < 0.5


def test_a_volume_of_one_particle_gives_no_vector(rng):
    """One particle in the whole volume: no window holds two, and the error says so."""
    a, b, pa, pb, shape = counted_windows([1] + [0] * 11, rng)
    with pytest.raises(PIVError, match=r"holds 2 particles.*volume A holds 1 particle\b"):
        correlate_volumes(a, b, grid_of(shape), particles=(to_metres(pa), to_metres(pb)),
                          settings=PIVSettings(windows=WINDOW, overlap=0.0, passes=1))
    field = correlate_volumes(a, b, grid_of(shape), particles=(to_metres(pa), to_metres(pb)),
                              settings=PIVSettings(windows=WINDOW, overlap=0.0, passes=1,
                                                   min_particles_per_window=0))
    assert field.valid.sum() == 1


def test_window_counts_equal_a_direct_count(rng):
    """The summed-area count of every window, moved or not, is the direct count."""
    shape = (20, 27, 33)
    positions = rng.uniform(-3, np.array(shape) + 2, size=(400, 3))
    table = particle_table(shape, positions=to_metres(positions), origin=(0.0, 0.0, 0.0),
                           voxel=(VOXEL,) * 3)
    index = np.floor(positions + 0.5).astype(int)
    inside = np.all((index >= 0) & (index < shape), axis=1)
    for window, overlap in (((8, 8, 8), 0.5), ((6, 12, 9), 0.25), ((20, 4, 5), 0.0)):
        layout = _window_layout(shape, window, overlap)
        starts = layout.all_starts()
        offset = rng.normal(0.0, 3.0, size=starts.shape)
        for off in (None, offset):
            got = window_counts(table, layout, off)
            moved = starts + (0 if off is None else np.rint(off).astype(int))
            want = [np.sum(inside & np.all((index >= s) & (index < s + np.array(window)), 1))
                    for s in moved]
            np.testing.assert_array_equal(got, want)


def test_masked_particles_and_those_outside_count_nowhere():
    shape = (8, 8, 8)
    positions = np.array([[1.0, 1.0, 1.0], [6.0, 6.0, 6.0], [-2.0, 3.0, 3.0], [3.0, 3.0, 8.6]])
    mask = np.zeros(shape, bool)
    mask[5:, 5:, 5:] = True
    table = particle_table(shape, positions=to_metres(positions), origin=(0.0, 0.0, 0.0),
                           voxel=VOXEL, mask=mask)
    assert table[-1, -1, -1] == 1


def test_bare_volumes_count_their_peaks(rng):
    """Without a table the particles are the local maxima above 0.1 of the bright level."""
    a, _, pa, _, shape = counted_windows([2, 0, 3, 1, 4, 0, 1, 2], rng)
    faint = render(shape, [[8.0, 8.0, 40.0]]) * 0.05     # below the threshold
    table = particle_table(shape, volume=a + faint)
    assert table[-1, -1, -1] == len(pa)


@pytest.mark.parametrize("value", [-1, 1.5, True, "2", None])
def test_min_particles_per_window_is_a_count(value):
    with pytest.raises(ValueError, match="min_particles_per_window"):
        PIVSettings(min_particles_per_window=value)


def test_particle_tables_are_checked(rng):
    a, b, pa, pb, shape = counted_windows([2] * 4, rng)
    s = PIVSettings(windows=WINDOW, overlap=0.0, passes=1)
    bad = to_metres(pa).copy()
    bad[0, 1] = np.nan
    with pytest.raises(PIVError, match="NaN or infinite"):
        correlate_volumes(a, b, grid_of(shape), settings=s, particles=(bad, to_metres(pb)))
    with pytest.raises(PIVError, match=r"shape \(8, 2\)"):
        correlate_volumes(a, b, grid_of(shape), settings=s,
                          particles=(to_metres(pa)[:, :2], to_metres(pb)))
    with pytest.raises(ValueError, match="positions_a, positions_b"):
        correlate_volumes(a, b, grid_of(shape), settings=s, particles=to_metres(pa))


def test_a_field_made_without_counts_says_so():
    z = np.zeros((1, 1, 1))
    field = VectorField(x=[0.0], y=[0.0], z=[0.0], u=z, v=z, w=z, valid=z == 0, snr=z + 2,
                        correlation=z + 1)
    assert field.particles_per_window.tolist() == [[[-1]]]
