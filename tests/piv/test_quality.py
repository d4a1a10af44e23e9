"""Per-vector quality of plenopiv.piv: correlation statistics (uncertainty), rejection flags,
replacement options and the volume mask, on synthetic Gaussian-particle volumes."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import scipy.fft

from piv.test_piv import render, seed_particles, volume_pair
from plenopiv import PIVError
from plenopiv.piv import (
    FLAG_EMPTY,
    FLAG_MASKED,
    FLAG_OUTLIER,
    PIVSettings,
    VectorField,
    correlate_volumes,
    particle_image_size,
)
from plenopiv.piv._kernels import ENGINES
from plenopiv.piv.statistics import NUMPY_STATISTICS_MAX_VOXELS, _statistics_kernel

ENGINE_NAMES = tuple(ENGINES)
GRID = SimpleNamespace(origin=(0.0, 0.0, 0.0), voxel_size=1.0)


@pytest.fixture
def rng():
    return np.random.default_rng(20260515)


def _windows_and_peaks(rng, n=6, window=(8, 6, 10)):
    shape = (20, 18, 24)
    a = rng.random(shape).astype(np.float32)
    b = np.roll(a, (1, -1, 2), axis=(0, 1, 2)) + 0.1 * rng.random(shape).astype(np.float32)
    starts = rng.integers(-2, 12, size=(n, 3)).astype(np.int64)
    starts_b = starts + rng.integers(-1, 2, size=(n, 3))
    peak = rng.integers(-2, 3, size=(n, 3)).astype(np.int64)
    return a, b.astype(np.float32), starts, starts_b, window, peak


@pytest.mark.parametrize("block", [(1, 1, 1), (3, 3, 5), (5, 1, 3)])
def test_kernel_peak_statistics_engines_agree(rng, block):
    a, b, sa, sb, window, peak = _windows_and_peaks(rng)
    out = [ENGINES[e].peak_statistics(a, b, sa, sb, *window, peak, np.array(block))
           for e in ENGINE_NAMES]
    np.testing.assert_allclose(out[0], out[1], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_small_fields_take_the_numpy_statistics_with_either_engine(engine):
    # the numba kernel's compilation costs more than it saves on a small field; the engines
    # agree (test above), so the choice changes the time only
    kernels = ENGINES[engine]
    window = (12, 12, 12)
    n_small = NUMPY_STATISTICS_MAX_VOXELS // 1728
    assert _statistics_kernel(kernels, n_small, window) is ENGINES["numpy"].peak_statistics
    assert _statistics_kernel(kernels, n_small + 1, window) is kernels.peak_statistics


def test_peak_statistics_equal_the_circular_correlation(rng):
    """C0 and C+- are the FFT correlation's values at the peak and beside it; their
    asymmetry's voxel contributions vanish for identical windows."""
    a, b, sa, sb, window, peak = _windows_and_peaks(rng, n=4)
    stats = ENGINES["numba"].peak_statistics(a, b, sa, sb, *window, peak, np.array((3, 3, 3)))
    wa = ENGINES["numpy"].extract_windows(a, sa, *window).astype(float)
    wb = ENGINES["numpy"].extract_windows(b, sb, *window).astype(float)
    wa -= wa.mean(axis=(1, 2, 3), keepdims=True)
    wb -= wb.mean(axis=(1, 2, 3), keepdims=True)
    corr = np.real(scipy.fft.ifftn(np.conj(scipy.fft.fftn(wa, axes=(1, 2, 3)))
                                   * scipy.fft.fftn(wb, axes=(1, 2, 3)), axes=(1, 2, 3)))
    for k in range(4):
        s = peak[k] % np.array(window)
        assert stats[k, 0] == pytest.approx(corr[k][tuple(s)], rel=1e-9)
        for axis in range(3):
            e = np.zeros(3, int)
            e[axis] = 1
            plus = corr[k][tuple((peak[k] + e) % np.array(window))]
            minus = corr[k][tuple((peak[k] - e) % np.array(window))]
            assert stats[k, 1 + 2 * axis] == pytest.approx(plus, rel=1e-9)
            assert stats[k, 2 + 2 * axis] == pytest.approx(minus, rel=1e-9)
    same = ENGINES["numba"].peak_statistics(a, a, sa, sa, *window, np.zeros_like(peak),
                                            np.array((3, 3, 3)))
    np.testing.assert_allclose(same[:, 7:], 0.0, atol=1e-12)


def test_particle_image_size_of_gaussian_blobs(rng):
    shape = (40, 40, 40)
    pos, peaks = seed_particles(rng, shape, density=0.003)
    vol = render(shape, pos, (2.0, 1.0, 0.7), peaks)
    size = particle_image_size(vol)
    np.testing.assert_allclose(size, (2.0, 1.0, 0.7), rtol=0.15)
    assert np.all(particle_image_size(np.zeros(shape)) == 0)


def _field_errors(rng, noise, shift=(0.4, -1.3, 2.2)):
    shape = (40, 40, 40)
    a, b = volume_pair(rng, shape, lambda p: p + np.asarray(shift))
    a = a + noise * rng.standard_normal(shape).astype(np.float32)
    b = b + noise * rng.standard_normal(shape).astype(np.float32)
    s = PIVSettings(windows=((16, 16, 16), (12, 12, 12)), passes=3)
    f = correlate_volumes(a, b, GRID, settings=s)
    meas = np.stack([f.w, f.v, f.u])[:, 1:-1, 1:-1, 1:-1]
    sig = np.stack([f.w_uncertainty, f.v_uncertainty, f.u_uncertainty])[:, 1:-1, 1:-1, 1:-1]
    err = meas - np.asarray(shift)[:, None, None, None]
    return np.sqrt((err**2).mean()), np.sqrt((sig**2).mean())


def test_uncertainty_covers_the_errors_on_noisy_particle_volumes(rng):
    """Correlation statistics plus the last correction cover the true errors of noisy
    synthetic particle volumes: at least 85 % within +-2 sigma per component, and not every
    error (pooled over the components at most 99 %: a sigma inflated twice would cover all).

    The vectors of one pair share its shift, so the coverage of a few pairs scatters by
    several per cent (measured 93-99 % per component over seeds with 16 pairs); 16 pairs
    keep that scatter inside the bounds."""
    errors, sigmas = [], []
    for noise in (0.02, 0.1):
        for _ in range(8):
            shape = (40, 40, 40)
            shift = rng.uniform(-2, 2, 3)
            a, b = volume_pair(rng, shape, lambda p, s=shift: p + s)
            a = a + noise * rng.standard_normal(shape).astype(np.float32)
            b = b + noise * rng.standard_normal(shape).astype(np.float32)
            f = correlate_volumes(a, b, GRID, settings=PIVSettings(
                windows=((16, 16, 16), (12, 12, 12)), passes=3))
            meas = np.stack([f.w, f.v, f.u])[:, 1:-1, 1:-1, 1:-1].reshape(3, -1)
            errors.append(meas - shift[:, None])
            sigmas.append(np.stack([f.w_uncertainty, f.v_uncertainty,
                                    f.u_uncertainty])[:, 1:-1, 1:-1, 1:-1].reshape(3, -1))
    e, s = np.concatenate(errors, axis=1), np.concatenate(sigmas, axis=1)
    within = np.abs(e) <= 2 * s
    assert np.all(within.mean(axis=1) >= 0.85), within.mean(axis=1)
    assert within.mean() <= 0.99, within.mean()


def test_uncertainty_follows_the_image_noise(rng):
    """Correlation statistics on noisy particle volumes: the estimated uncertainty grows
    with the noise as the true error does, and stays of its size (within a factor of 2;
    the 0.01-voxel floor of the deformation's interpolation is not in the statistics)."""
    quiet_err, quiet_sig = _field_errors(rng, 0.02)
    noisy_err, noisy_sig = _field_errors(rng, 0.15)
    assert noisy_sig > 2 * quiet_sig
    assert noisy_err > 1.5 * quiet_err
    assert 0.5 < noisy_err / noisy_sig < 2.0


SHIFT = np.array([1.2, -0.7, 2.1])   # (z, y, x) voxels


def _corrupted_pair(rng):
    """One 16-voxel window of volume B holds unrelated particles."""
    shape = (48, 48, 48)
    a, b = volume_pair(rng, shape, lambda p: p + SHIFT)
    positions, peaks = seed_particles(np.random.default_rng(5), (16, 16, 16), margin=0)
    b[16:32, 16:32, 16:32] = render((16, 16, 16), positions, (1.0, 1.0, 1.0), peaks)
    return a, b


@pytest.mark.parametrize("method", ["median", "mean", "none"])
def test_rejected_vectors_replaced_or_left_nan(rng, method):
    a, b = _corrupted_pair(rng)
    s = PIVSettings(windows=16, overlap=0.0, passes=2, replacement=method)
    f = correlate_volumes(a, b, GRID, settings=s)
    rejected = ~f.valid
    assert rejected[1, 1, 1] and f.valid.mean() > 0.7
    assert np.all(f.flag[f.valid] == 0) and np.all(f.flag[rejected] & FLAG_OUTLIER)
    assert np.all(np.isfinite(f.u_uncertainty[f.valid]))
    if method == "none":
        assert not f.replaced.any() and f.n_replaced == 0
        assert np.all(np.isnan(f.u[rejected])) and np.all(np.isnan(f.u_uncertainty[rejected]))
    else:
        assert np.array_equal(f.replaced, rejected) and f.n_replaced == rejected.sum()
        assert np.all(np.isfinite(f.u[rejected]))
        assert np.all(np.abs(f.u[rejected] - SHIFT[2]) < 0.3)   # filled from good neighbours
        assert np.all(np.isfinite(f.u_uncertainty[rejected]))


def test_mean_and_median_replacement_differ_only_where_replaced(rng):
    a, b = _corrupted_pair(rng)
    s = PIVSettings(windows=16, overlap=0.0, passes=2)
    med = correlate_volumes(a, b, GRID, settings=s)
    mean = correlate_volumes(a, b, GRID, settings=PIVSettings(windows=16, overlap=0.0, passes=2,
                                                               replacement="mean"))
    np.testing.assert_array_equal(med.u[med.valid], mean.u[mean.valid])
    assert not np.array_equal(med.u[~med.valid], mean.u[~mean.valid])


def test_empty_windows_are_flagged_empty(rng):
    shape = (32, 32, 48)
    a, b = volume_pair(rng, shape, lambda p: p + 1.0)
    a[:, :, 32:] = 0
    b[:, :, 32:] = 0
    f = correlate_volumes(a, b, GRID, settings=PIVSettings(windows=16, passes=1))
    empty = (f.flag & FLAG_EMPTY) != 0
    assert empty[..., -1].all() and not empty[..., 0].any()


def test_volume_mask_gives_nan_flagged_vectors(rng):
    shape = (32, 40, 48)
    shift = np.array([0.6, -0.8, 1.4])
    a, b = volume_pair(rng, shape, lambda p: p + shift)
    mask = np.zeros(shape, bool)
    mask[:, :, 28:] = True                       # the right part is a "model"
    s = PIVSettings(windows=((16, 16, 16), (12, 12, 12)), passes=3)
    f = correlate_volumes(a, b, GRID, settings=s, mask=mask)
    cx = f.x                                      # window centres, voxels here
    inside = cx >= 28 - 0.5
    assert f.masked[..., inside].all() and not f.masked[..., ~inside].any()
    assert np.all(np.isnan(f.u[..., inside])) and np.all(np.isnan(f.w_uncertainty[..., inside]))
    assert not f.valid[..., inside].any() and not f.replaced[..., inside].any()
    assert np.all(f.flag[..., inside] == FLAG_MASKED)
    # the vectors outside the mask are measured as without it
    free = f.valid[1:-1, 1:-1][..., ~inside]
    u = f.u[1:-1, 1:-1][..., ~inside]
    assert free.mean() > 0.9
    assert np.abs(np.median(u[free]) - shift[2]) < 0.05
    with pytest.raises(PIVError, match="mask has shape"):
        correlate_volumes(a, b, GRID, settings=s, mask=mask[1:])


def test_vector_field_defaults_for_the_old_constructor():
    shape = (1, 2, 2)
    z = np.zeros(shape)
    valid = np.array([[[True, False], [True, True]]])
    f = VectorField(x=np.arange(2.0), y=np.arange(2.0), z=np.zeros(1), u=z, v=z, w=z,
                    valid=valid, snr=z + 2, correlation=z + 0.5)
    assert f.flag.dtype == np.uint8 and f.flag[0, 0, 1] == FLAG_OUTLIER
    assert f.replaced[0, 0, 1] and f.replaced.sum() == 1
    assert np.all(np.isnan(f.u_uncertainty)) and f.peak_ratio is f.snr


def test_rejected_vectors_record_how_far_their_measurement_lay(rng):
    """A rejected vector keeps, per component, the distance of its own measurement from its
    neighbours' median; valid vectors record 0; the record does not depend on what replaces
    the rejected vector."""
    a, b = _corrupted_pair(rng)
    fields = {m: correlate_volumes(a, b, GRID, settings=PIVSettings(
        windows=16, overlap=0.0, passes=2, replacement=m)) for m in ("median", "none")}
    f = fields["median"]
    d = f.uncertainty_parts["rejected_disagreement"]
    assert d.shape == (3,) + f.u.shape
    rejected = ~f.valid
    assert np.all(d[:, f.valid] == 0.0)
    # the unrelated particles of the corrupted window: rejected, and its measurement lay more
    # than the threshold's worth of noise (2 x 0.1 voxel) from the median of its neighbours
    assert rejected[1, 1, 1] and np.max(d[:, 1, 1, 1] / GRID.voxel_size) > 0.2
    # its replaced value is that median: the record is the distance from it
    np.testing.assert_array_equal(d, fields["none"].uncertainty_parts["rejected_disagreement"])
