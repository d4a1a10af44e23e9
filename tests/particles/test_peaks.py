"""Particle extraction: kernels against NumPy twins, sub-voxel accuracy against derived bounds."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from plenopiv import ReconstructionError
from plenopiv.conventions import voxel_to_world
from plenopiv.particles import _kernels as pk
from plenopiv.particles.peaks import CENTROID_METHODS, Particles, find_particles

U32 = 2.0**-24



#: The options these tests were written for: the 3-point Gaussian fit and 2-voxel boxes
#: (the pipeline's own come from ``[particles]``,
#: :func:`plenopiv.workflow.volume.particle_options`).
GAUSSIAN_3POINT = dict(method="gaussian", min_separation_vox=2.0, box_vox=(2, 2, 2),
                       fit_spacing_vox=(1, 1, 1))


def find(volume, **options):
    """:func:`find_particles` with :data:`GAUSSIAN_3POINT` where ``options`` leave a gap."""
    return find_particles(volume, **{**GAUSSIAN_3POINT, **options})


def blob(shape, centre, sigma, amplitude=1.0):
    """Point-sampled Gaussian ``A exp(-sum_a (k_a - c_a)^2 / (2 s_a^2))`` on the voxel grid."""
    grid = np.indices(shape, dtype=np.float64)
    sigma = np.broadcast_to(np.asarray(sigma, float), (3,))
    return amplitude * np.exp(-sum((grid[a] - centre[a]) ** 2 / (2 * sigma[a] ** 2)
                                   for a in range(3)))


@pytest.mark.parametrize("gaussian", [True, False])
@pytest.mark.parametrize("spacing", [(1, 1, 1), (2, 1, 3)])
def test_refine_kernel_matches_numpy_twin(rng, gaussian, spacing):
    volume = rng.uniform(0.0, 1.0, (9, 8, 10)).astype(np.float32)
    volume[rng.uniform(size=volume.shape) < 0.1] = 0.0  # zero samples take the fallback
    peaks = np.stack([rng.integers(0, s, 40) for s in volume.shape], axis=1).astype(np.int64)
    half_box = np.array([2, 1, 3], np.int64)
    spacing = np.array(spacing, np.int64)
    position, size, intensity = (np.empty((40, 3)), np.empty((40, 3)), np.empty(40))
    pk.refine_peaks(volume, peaks, half_box, spacing, gaussian, position, size, intensity)
    ref = (np.empty((40, 3)), np.empty((40, 3)), np.empty(40))
    pk.refine_peaks_numpy(volume, peaks, half_box, spacing, gaussian, *ref)
    np.testing.assert_allclose(position, ref[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(size, ref[1], rtol=1e-12, atol=1e-12, equal_nan=True)
    np.testing.assert_allclose(intensity, ref[2], rtol=1e-12)


@pytest.mark.parametrize("separation", [(1.0, 1.0, 1.0), (2.0, 2.0, 2.0), (3.5, 1.5, 2.0)])
def test_suppress_kernel_matches_numpy_twin(rng, separation):
    shape = (10, 12, 9)
    flat = rng.choice(np.prod(shape), 60, replace=False)
    peaks = np.stack(np.unravel_index(flat, shape), axis=1).astype(np.int64)
    sep = np.array(separation)
    keep = pk.suppress_close(peaks, np.array(shape, np.int64), sep)
    want = pk.suppress_close_numpy(peaks, np.array(shape, np.int64), sep)
    np.testing.assert_array_equal(keep, want)


# -- sub-voxel accuracy on Gaussian blobs ----------------------------------------------------


def gaussian_fit_bound(sigma, m):
    """Error of the 3-point Gaussian on float32 samples of an exact Gaussian, voxels.

    delta = m N / (2 D) with N = ln I- - ln I+ and D = ln I- - 2 ln I0 + ln I+ = -m^2/s^2.
    Rounding the samples to float32 moves each log by <= U32, so |dN| <= 2 U32,
    |dD| <= 4 U32 and |d delta| <= U32 s^2 / m + 2 |delta| U32 s^2 / m^2 * 2, |delta| <= 1/2.
    Doubled for the float64 logs and second-order terms.
    """
    return 2 * U32 * sigma**2 * (1 / m + 2 / m**2)


def truncated_centroid_bound(sigma, delta, h):
    """|c - delta| for the centroid of samples g(k - delta), |k| <= h, of a Gaussian of width s.

    With S, M the sums of g and k g over all k (M = delta S up to aliasing) and S_w, M_w the
    window's: delta S_w - M_w = sum_{|k|>h} (k - delta) g - (delta S - M), so
    |c - delta| <= (sum_{|k|>h} |k - delta| g + |delta S - M|) / S_w.
    """
    k = np.arange(-80, 81)
    g = np.exp(-((k - delta) ** 2) / (2 * sigma**2))
    tail = np.abs(k) > h
    aliasing = abs(delta * g.sum() - (k * g).sum())
    return (np.sum(np.abs(k[tail] - delta) * g[tail]) + aliasing) / g[~tail].sum()


@pytest.mark.parametrize("sigma", [(1.0, 1.0, 1.0), (3.0, 1.0, 1.0), (2.0, 1.3, 0.8)])
def test_gaussian_fit_is_exact_for_sampled_gaussians(rng, sigma):
    """Noise-free, the 3-point Gaussian returns the centre and sigma to float32 precision,
    however elongated the blob (and for any sample spacing)."""
    shape = (33, 15, 15)
    for spacing in [(1, 1, 1), (3, 1, 1)]:
        for _ in range(5):
            centre = np.array([16, 7, 7]) + rng.uniform(-0.5, 0.5, 3)
            volume = blob(shape, centre, sigma).astype(np.float32)
            found = find(volume, threshold=0.5, min_separation_vox=(8, 3, 3),
                                   fit_spacing_vox=spacing)
            assert len(found) == 1 and found.method == "gaussian"
            for a in range(3):
                bound = gaussian_fit_bound(sigma[a], spacing[a])
                assert abs(found.position_vox[0, a] - centre[a]) <= bound
                assert abs(found.size_vox[0, a] - sigma[a]) <= bound * sigma[a]


@pytest.mark.parametrize("sigma", [(1.0, 1.0, 1.0), (3.0, 1.0, 1.0)])
@pytest.mark.parametrize("box", [(1, 1, 1), (2, 2, 2), (6, 2, 2)])
def test_centroid_error_is_the_window_truncation_bias(rng, sigma, box):
    """The windowed centroid is biased towards the peak voxel by at most the truncation
    bound; for an elongated blob and a short box the bias in z is large (a sizeable
    fraction of a voxel), which is why the Gaussian fit is the default."""
    shape = (33, 15, 15)
    worst = np.zeros(3)
    for _ in range(8):
        centre = np.array([16, 7, 7]) + rng.uniform(-0.5, 0.5, 3)
        volume = blob(shape, centre, sigma)
        found = find(volume, threshold=0.5, method="centroid", box_vox=box,
                               min_separation_vox=(8, 3, 3))
        assert len(found) == 1
        peak = np.round(centre)
        for a in range(3):
            err = abs(found.position_vox[0, a] - centre[a])
            bound = truncated_centroid_bound(sigma[a], centre[a] - peak[a], box[a])
            assert err <= bound + 1e-12
            worst[a] = max(worst[a], err)
    if sigma[0] == 3.0 and box[0] <= 2:
        assert worst[0] > 0.1  # the truncation bias is real, not a loose bound


def test_gaussian_fit_beats_centroid_on_elongated_blobs(rng):
    """Same blobs, both methods: noise-free the fit is exact while the default box (2, 2, 2)
    centroid is biased by up to the truncation bound in z."""
    shape = (33, 15, 15)
    errors = {method: [] for method in CENTROID_METHODS}
    for _ in range(10):
        centre = np.array([16, 7, 7]) + rng.uniform(-0.5, 0.5, 3)
        volume = blob(shape, centre, (3.0, 1.0, 1.0)).astype(np.float32)
        for method in CENTROID_METHODS:
            found = find(volume, threshold=0.5, method=method,
                                   min_separation_vox=(8, 3, 3))
            errors[method].append(np.abs(found.position_vox[0] - centre))
    gaussian, centroid = (np.max(errors[m], axis=0) for m in CENTROID_METHODS)
    assert np.all(gaussian <= gaussian_fit_bound(3.0, 1))
    assert centroid[0] > 100 * gaussian[0] + 0.05


def test_sizes_measure_depth_elongation():
    volume = blob((33, 15, 15), (16.2, 7.1, 6.8), (3.0, 1.0, 1.0)).astype(np.float32)
    found = find(volume, threshold=0.5, min_separation_vox=(8, 3, 3))
    np.testing.assert_allclose(found.size_vox[0], [3.0, 1.0, 1.0], rtol=1e-5)
    assert found.elongation[0] == pytest.approx(3.0, rel=1e-5)
    # the centroid's second moment is cut by the box: biased low, most in z
    moments = find(volume, threshold=0.5, method="centroid", box_vox=(2, 2, 2),
                             min_separation_vox=(8, 3, 3)).size_vox[0]
    assert np.all(moments < [3.0, 1.0, 1.0]) and moments[0] < 2.0


def test_integrated_intensity_of_a_blob():
    """The sum of samples of a Gaussian equals its integral A (2 pi)^(3/2) s_z s_y s_x up to
    aliasing O(exp(-2 pi^2 s^2)); a box of +-4.5 s misses a fraction
    erfc(4.5/sqrt 2) < 1e-5 per axis."""
    sigma = np.array([2.0, 1.0, 1.0])
    volume = blob((41, 21, 21), (20.3, 10.4, 9.8), sigma, amplitude=5.0)
    found = find(volume, threshold=1.0, box_vox=(9, 5, 5),
                           min_separation_vox=(8, 3, 3))
    expected = 5.0 * (2 * np.pi) ** 1.5 * np.prod(sigma)
    assert found.intensity[0] == pytest.approx(expected, rel=4e-5)
    assert found.peak[0] == pytest.approx(volume.max())


def close_pair_bound(sigma, d, delta):
    """First-order error of the 3-point Gaussian when a twin blob sits d voxels away (x).

    The twin adds g(k - d) to the sample at offset k, i.e. ln I_k grows by
    e_k = ln(1 + g(k - d - delta) / g(k - delta)). Through delta = N/(2D):
    |d delta| <= s^2 (|e_-| + |e_+|) / 2 + |delta| s^2 (|e_-| + 2|e_0| + |e_+|).
    """
    def g(x):
        return np.exp(-x**2 / (2 * sigma**2))
    e = [math.log1p(g(k - d - delta) / g(k - delta)) for k in (-1, 0, 1)]
    return (sigma**2 * (abs(e[0]) + abs(e[2])) / 2
            + abs(delta) * sigma**2 * (abs(e[0]) + 2 * abs(e[1]) + abs(e[2])))


def test_two_close_particles_are_both_found():
    shape = (15, 15, 24)
    a = np.array([7.0, 7.2, 8.3])
    b = a + [0.0, 0.0, 4.3]
    volume = (blob(shape, a, 1.0) + blob(shape, b, 1.0)).astype(np.float32)
    found = find(volume, threshold=0.5)
    assert len(found) == 2
    order = np.argsort(found.position_vox[:, 2])
    for truth, got in zip((a, b), found.position_vox[order], strict=True):
        peak = np.round(truth)
        # the twin lies +-4.3 voxels along x; bound the error along x from its tail
        delta = truth[2] - peak[2]
        sign = 1 if truth is a else -1
        bound = close_pair_bound(1.0, sign * 4.3, delta)
        assert abs(got[2] - truth[2]) <= bound
        assert bound < 0.05
        np.testing.assert_allclose(got[:2], truth[:2], atol=1e-5)
    # a separation larger than their distance merges them into the brighter one
    merged = find(volume, threshold=0.5, min_separation_vox=6.0)
    assert len(merged) == 1


def test_threshold_excludes_noise(rng):
    """Uniform noise below 0.1 makes many local maxima; a threshold above the noise floor
    keeps exactly the particles."""
    shape = (20, 20, 20)
    centres = [np.array(c) + rng.uniform(-0.4, 0.4, 3)
               for c in ([5, 5, 5], [14, 6, 12], [8, 15, 9], [15, 14, 4])]
    clean = sum(blob(shape, c, 1.0) for c in centres)
    volume = (clean + rng.uniform(0.0, 0.1, shape)).astype(np.float32)
    assert len(find(volume, threshold=0.0)) > 50
    found = find(volume, threshold=0.3)
    assert len(found) == 4
    for c in centres:
        nearest = np.min(np.linalg.norm(found.position_vox - c, axis=1))
        assert nearest < 0.2  # noise of 0.1 on a unit peak moves the fit by a fraction


def test_plateaus_and_borders():
    volume = np.zeros((7, 7, 7), np.float32)
    volume[3, 3, 3:5] = 1.0  # a two-voxel plateau is one particle
    assert len(find(volume, threshold=0.5)) == 1
    volume[:] = 0.0
    volume[0, 3, 3] = 1.0  # on the z = 0 face
    assert len(find(volume, threshold=0.5)) == 0
    edge = find(volume, threshold=0.5, exclude_border=False)
    assert len(edge) == 1
    assert edge.position_vox[0, 0] == 0.0 and np.isnan(edge.size_vox[0, 0])
    empty = find(volume, threshold=2.0)
    assert len(empty) == 0 and empty.position_vox.shape == (0, 3)


def test_world_coordinates_go_through_the_conventions():
    particles = Particles(position_vox=np.array([[2.0, 1.0, 0.5]]), intensity=np.ones(1),
                          size_vox=np.array([[3.0, 1.0, 2.0]]), peak=np.ones(1),
                          method="gaussian")
    origin, voxel = np.array([-1e-3, 2e-3, 5e-3]), np.array([1e-4, 2e-4, 4e-4])
    np.testing.assert_allclose(particles.position_world(origin, voxel),
                               voxel_to_world(particles.position_vox, origin, voxel))
    np.testing.assert_allclose(particles.position_world(origin, voxel),
                               [[-1e-3 + 0.5e-4, 2e-3 + 2e-4, 5e-3 + 8e-4]])
    np.testing.assert_allclose(particles.size_world(voxel), [[2e-4, 2e-4, 12e-4]])


@pytest.mark.parametrize(
    "volume,kwargs,error,match",
    [
        (np.ones((4, 4)), {}, ReconstructionError, "3-D numeric array"),
        (np.full((4, 4, 4), np.nan), {}, ReconstructionError, "64 NaN or infinite"),
        (np.ones((4, 4, 4)), dict(method="max"), ValueError,
         r"method must be one of \('gaussian', 'centroid'\)"),
        (np.ones((4, 4, 4)), dict(threshold=-1.0), ValueError, "threshold must be finite"),
        (np.ones((4, 4, 4)), dict(min_separation_vox=0), ValueError, "must be > 0"),
        (np.ones((4, 4, 4)), dict(min_separation_vox=(1, 2)), ValueError, "3 numbers"),
        (np.ones((4, 4, 4)), dict(box_vox=(0, 1, 1)), ValueError, "integers >= 1"),
        (np.ones((4, 4, 4)), dict(box_vox=1.5), ValueError, "must be integers"),
        (np.ones((4, 4, 4)), dict(fit_spacing_vox=0), ValueError, "integers >= 1"),
    ],
)
def test_bad_inputs_are_refused(volume, kwargs, error, match):
    kwargs = {"threshold": 0.5, **kwargs}
    with pytest.raises(error, match=match):
        find(volume, **kwargs)


def test_defaults_are_those_of_the_particles_settings():
    """One set of defaults: find_particles' keyword defaults are ParticleSettings' own, and
    the two that ParticleSettings leaves to the camera (None) have none in find_particles."""
    import inspect

    from plenopiv.particles.settings import ParticleSettings

    settings = ParticleSettings()
    params = inspect.signature(find_particles).parameters
    # threshold is a fraction of the reference intensity in the settings and an intensity
    # here (pipeline.particle_options converts); it has no default here
    assert params["threshold"].default is inspect.Parameter.empty
    shared = [name for name in params
              if name in {f.name for f in dataclasses.fields(ParticleSettings)}
              and name != "threshold"]
    assert sorted(shared) == ["box_vox", "fit_spacing_vox", "method", "min_separation_vox"]
    for name in shared:
        default = params[name].default
        if getattr(settings, name) is None:
            assert default is inspect.Parameter.empty, name
        else:
            assert default == getattr(settings, name), name
    volume = blob((15, 15, 15), (7.2, 6.9, 7.1), (2.0, 1.0, 1.0)).astype(np.float32)
    assert find_particles(volume, threshold=0.5, min_separation_vox=3.0,
                          box_vox=2).method == settings.method
