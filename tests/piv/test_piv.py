"""Tests of plenopiv.piv: 3-D PIV of synthetic Gaussian-particle volumes with known motion.

Volumes are rendered here with NumPy: every particle is a 3-D Gaussian blob drawn at its
exact (sub-voxel) position, so a sub-voxel displacement is made by moving the particles,
never by interpolating a volume. Particles are seeded beyond the volume so that particles
enter and leave it as they would in an experiment.

Tolerances. With noise-free volumes of ~10 particles per 16^3 window the random error of a
converged window-deformation estimate is about 0.01 voxel (its floor is set by the spline
interpolation of the deformation and by particles crossing the window border), so a bias
bound of 0.02 voxel and an RMS bound of 0.05 voxel per axis leave a margin of 2-4x while
still catching a lost sub-voxel fit (peak locking: errors up to 0.1-0.2 voxel) or a wrong
axis order (errors of whole voxels). Vectors on the outer layer of the grid are left out:
their windows lose up to half of their particles across the volume border.
"""

from __future__ import annotations

from dataclasses import FrozenInstanceError
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.fft
import scipy.ndimage
from hypothesis import given, settings
from hypothesis import strategies as st

from plenopiv import PIVError
from plenopiv.piv import (
    PIVSettings,
    VectorField,
    correlate_volumes,
    normalized_median_test,
    replace_outliers,
)
from plenopiv.piv._kernels import ENGINES
from plenopiv.piv.correlation import _regular_spectra
from plenopiv.piv.windows import _SPLINE_PAD, _deform, _spline_coefficients, _window_layout

ENGINE_NAMES = tuple(ENGINES)


# --------------------------------------------------------------------------------------------
# synthetic particle volumes
# --------------------------------------------------------------------------------------------


@pytest.fixture
def seed():
    return 20240611


@pytest.fixture
def rng(seed):
    return np.random.default_rng(seed)


def render(shape, positions, sigma_vox, peaks):
    """Sum of Gaussian blobs; ``positions`` (N, 3) are ``(z, y, x)`` voxel indices."""
    volume = np.zeros(shape)
    sigma = np.asarray(sigma_vox, dtype=float)
    reach = np.ceil(4 * sigma).astype(int)
    for p, peak in zip(positions, peaks, strict=True):
        c = np.rint(p).astype(int)
        lo = np.maximum(c - reach, 0)
        hi = np.minimum(c + reach + 1, shape)
        if np.any(hi <= lo):
            continue
        g = [np.exp(-0.5 * ((np.arange(lo[a], hi[a]) - p[a]) / sigma[a]) ** 2) for a in range(3)]
        volume[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] += (
            peak * g[0][:, None, None] * g[1][None, :, None] * g[2][None, None, :]
        )
    return volume.astype(np.float32)


def seed_particles(rng, shape, *, density=0.01, margin=12):
    """Uniform particle positions (voxels) filling the volume and a margin around it."""
    extent = np.asarray(shape) + 2 * margin
    n = int(density * np.prod(extent))
    positions = rng.uniform(-margin, np.asarray(shape) - 1 + margin, size=(n, 3))
    peaks = rng.uniform(0.5, 1.0, n)
    return positions, peaks


def volume_pair(rng, shape, move, *, sigma_vox=(1.0, 1.0, 1.0), density=0.01):
    """Two volumes of the same particles, before and after ``move`` (positions -> positions)."""
    positions, peaks = seed_particles(rng, shape, density=density)
    a = render(shape, positions, sigma_vox, peaks)
    b = render(shape, move(positions), sigma_vox, peaks)
    return a, b


def unit_grid(shape=None):
    return SimpleNamespace(origin=(0.0, 0.0, 0.0), voxel_size=1.0, shape=shape)


def components_vox(field, voxel=(1.0, 1.0, 1.0)):
    """``(w, v, u)`` of a VectorField in voxels, stacked as (3, nz, ny, nx) in (z, y, x) order."""
    dx, dy, dz = voxel
    return np.stack([field.w / dz, field.v / dy, field.u / dx])


def interior(a):
    return a[..., 1:-1, 1:-1, 1:-1]


# --------------------------------------------------------------------------------------------
# uniform displacement
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "shift_vox",
    [(3.0, -5.0, 8.0), (2.3, -7.6, 5.45), (-8.0, 0.5, 7.8), (0.25, 0.5, -0.75)],
    ids=["integer", "subvoxel", "large", "small"],
)
def test_uniform_shift_recovered_in_metres(rng, shift_vox):
    shape = (64, 64, 64)
    shift = np.asarray(shift_vox)
    a, b = volume_pair(rng, shape, lambda p: p + shift)
    voxel = (50e-6, 60e-6, 80e-6)  # (dx, dy, dz), metres
    origin = (-1.0e-3, 2.0e-3, -3.0e-3)  # (x, y, z) of voxel [0, 0, 0], metres
    grid = SimpleNamespace(origin=origin, voxel_size=voxel, shape=shape)
    s = PIVSettings(windows=((32, 32, 32), (16, 16, 16)), passes=3)

    field = correlate_volumes(a, b, grid, settings=s)

    assert field.shape == (7, 7, 7)
    # window centres: 16-voxel windows every 8 voxels, the first centred on voxel 7.5
    centres = 7.5 + 8 * np.arange(7)
    np.testing.assert_allclose(field.x, origin[0] + centres * voxel[0])
    np.testing.assert_allclose(field.y, origin[1] + centres * voxel[1])
    np.testing.assert_allclose(field.z, origin[2] + centres * voxel[2])
    err = interior(components_vox(field, voxel)).reshape(3, -1) - shift[:, None]
    bias = err.mean(axis=1)
    rms = np.sqrt((err**2).mean(axis=1))
    assert np.all(np.abs(bias) <= 0.02), f"bias (z, y, x) = {bias} voxel"
    assert np.all(rms <= 0.05), f"RMS (z, y, x) = {rms} voxel"
    assert interior(field.valid).all()


@pytest.mark.parametrize(
    ("options", "bias_max", "rms_max"),
    [
        # trilinear deformation smooths the particle images unevenly: ~0.03 voxel bias
        ({"deformation_order": 1}, 0.05, 0.06),
        # whole-voxel window offset: the sub-voxel remainder keeps the one-pass bias
        ({"deformation": False}, 0.15, 0.2),
    ],
    ids=["trilinear", "window-offset"],
)
def test_other_modes_are_less_accurate_but_bounded(rng, options, bias_max, rms_max):
    shape = (48, 48, 48)
    shift = np.array([2.3, -1.55, 3.45])
    a, b = volume_pair(rng, shape, lambda p: p + shift)
    s = PIVSettings(windows=((32, 32, 32), (16, 16, 16)), passes=3, **options)
    field = correlate_volumes(a, b, unit_grid(), settings=s)
    err = interior(components_vox(field)).reshape(3, -1) - shift[:, None]
    bias = err.mean(axis=1)
    rms = np.sqrt((err**2).mean(axis=1))
    message = f"bias (z, y, x) = {bias}, RMS = {rms} voxel"
    assert np.all(np.abs(bias) <= bias_max) and np.all(rms <= rms_max), message


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_engines_agree_end_to_end(rng, engine):
    shape = (40, 48, 56)
    shift = np.array([1.3, -2.6, 3.7])
    a, b = volume_pair(rng, shape, lambda p: p + shift)
    s = PIVSettings(windows=((24, 24, 24), (16, 16, 16)), passes=2)
    reference = correlate_volumes(a, b, unit_grid(), settings=s, engine="numba")
    field = correlate_volumes(a, b, unit_grid(), settings=s, engine=engine)
    np.testing.assert_allclose(components_vox(field), components_vox(reference), atol=1e-4)
    np.testing.assert_allclose(field.correlation, reference.correlation, atol=1e-5)
    np.testing.assert_array_equal(field.valid, reference.valid)


@settings(max_examples=12, deadline=None)
@given(
    shape=st.tuples(*(st.sampled_from([8, 12, 16]) for _ in range(3))),
    fractions=st.tuples(*(st.floats(-0.45, 0.45) for _ in range(3))),
    seed=st.integers(0, 2**32 - 1),
)
def test_correlating_with_np_roll_returns_the_roll(shape, fractions, seed):
    # one window covering the whole volume: the circular correlation sees the roll exactly
    rng = np.random.default_rng(seed)
    volume = rng.random(shape, dtype=np.float32)
    # |roll| < n/2: a roll of exactly n/2 is the same as -n/2 for a circular correlation
    roll = tuple(int(np.trunc(f * n)) for f, n in zip(fractions, shape, strict=True))
    rolled = np.roll(volume, roll, axis=(0, 1, 2))
    # a rolled volume is periodic: no pair is lost across the window border, so the overlap
    # correction (made for real, non-periodic particle volumes) does not apply; nor does
    # intensity capping (made for particles: noise has no particle peaks to cap at)
    s = PIVSettings(windows=shape, passes=1, overlap=0.0, overlap_correction=False,
                    intensity_cap=0.0)

    field = correlate_volumes(volume, rolled, unit_grid(), settings=s)

    got = components_vox(field)[:, 0, 0, 0]
    np.testing.assert_allclose(got, roll, atol=1e-3)
    assert field.correlation[0, 0, 0] == pytest.approx(1.0, abs=1e-5)


# --------------------------------------------------------------------------------------------
# non-uniform flow: window deformation
# --------------------------------------------------------------------------------------------


def test_solid_body_rotation_better_with_deformation(rng):
    # rotation by theta about the z axis through the volume centre. The displacement measured
    # at a point m by the symmetric (central-difference) scheme is the chord of the particle
    # path whose midpoint is m: d(m) = 2 tan(theta/2) e_z x (m - c).
    shape = (48, 64, 64)
    centre = (np.asarray(shape) - 1) / 2
    theta = 0.1  # rad: up to 2.4 voxels at the outer window centres, 1.6 voxel across a window
    cos, sin = np.cos(theta), np.sin(theta)

    def rotate(p):
        rel = p - centre
        q = p.copy()
        q[:, 2] = centre[2] + cos * rel[:, 2] - sin * rel[:, 1]
        q[:, 1] = centre[1] + sin * rel[:, 2] + cos * rel[:, 1]
        return q

    a, b = volume_pair(rng, shape, rotate)
    errors = {}
    for deformation in (True, False):
        s = PIVSettings(windows=((32, 32, 32), (16, 16, 16)), passes=4, deformation=deformation)
        field = correlate_volumes(a, b, unit_grid(), settings=s)
        z, y, x = np.meshgrid(field.z, field.y, field.x, indexing="ij")
        k = 2 * np.tan(theta / 2)
        truth = np.stack([0 * z, k * (x - centre[2]), -k * (y - centre[1])])
        err = components_vox(field) - truth
        errors[deformation] = np.sqrt(np.mean(err[:, :, 1:-1, 1:-1] ** 2))
    message = (
        f"RMS error with deformation {errors[True]:.4f} voxel, without {errors[False]:.4f} voxel"
    )
    assert errors[True] < 0.7 * errors[False], message
    assert errors[True] < 0.03, message


def test_elongated_particles_with_taller_windows(rng):
    # plenoptic particles are ~2.5x longer in Z. Each deformation pass removes only part of
    # the remaining z error (the corrector sees about half of it for these particles and
    # windows), so the test runs six passes; the z error is larger because the correlation
    # peak is wider in z (its random error grows with the peak width).
    shape = (64, 48, 48)
    shift = np.array([1.6, -2.3, 3.4])
    a, b = volume_pair(rng, shape, lambda p: p + shift, sigma_vox=(2.5, 1.0, 1.0), density=0.008)
    s = PIVSettings(windows=((32, 24, 24), (24, 16, 16)), passes=6)

    field = correlate_volumes(a, b, unit_grid(), settings=s)

    assert field.shape == (4, 5, 5)
    err = interior(components_vox(field)).reshape(3, -1) - shift[:, None]
    bias = err.mean(axis=1)
    rms = np.sqrt((err**2).mean(axis=1))
    message = f"bias (z, y, x) = {bias}, RMS = {rms} voxel"
    assert np.all(np.abs(bias[1:]) <= 0.02) and np.all(rms[1:] <= 0.05), message
    assert abs(bias[0]) <= 0.04 and rms[0] <= 0.06, message


# --------------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------------


def smooth_field(shape):
    z, y, x = np.meshgrid(*(np.arange(n, dtype=float) for n in shape), indexing="ij")
    return np.stack([0.3 * x - 0.2 * y + 1.0, 0.5 * z + 0.1 * x, -0.4 * y + 0.05 * z * x])


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_median_test_finds_and_replaces_injected_outliers(rng, engine):
    shape = (8, 9, 10)
    truth = smooth_field(shape)
    field = truth.copy()
    # outliers inside, on faces and on a corner, none adjacent to another
    spots = [(0, 0, 0), (4, 4, 5), (2, 6, 2), (6, 2, 8), (7, 8, 4), (3, 0, 6), (5, 7, 9)]
    for i, spot in enumerate(spots):
        field[(i % 3,) + spot] += rng.choice([-1, 1]) * rng.uniform(3.0, 6.0)
    injected = np.zeros(shape, dtype=bool)
    injected[tuple(np.array(spots).T)] = True

    outlier, residual = normalized_median_test(*field, threshold=2.0, epsilon=0.1, engine=engine)

    np.testing.assert_array_equal(outlier, injected)
    assert np.all(residual[injected] > 2.0)
    u, v, w, n_replaced = replace_outliers(*field, outlier, engine=engine)
    assert n_replaced == len(spots)
    replaced = np.stack([u, v, w])
    # the field is linear except for the small z*x term: the neighbour median is exact to it
    np.testing.assert_allclose(replaced[:, injected], truth[:, injected], atol=0.3)
    np.testing.assert_array_equal(replaced[:, ~injected], field[:, ~injected])


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_median_test_keeps_a_steep_linear_field_including_its_border(engine):
    # one-sided border neighbourhoods would flag every border vector of a steep linear flow
    shape = (4, 6, 7)
    z, y, x = np.meshgrid(*(np.arange(n, dtype=float) for n in shape), indexing="ij")
    outlier, _ = normalized_median_test(2.0 * x, -1.6 * y, 0.9 * z + 0.5 * x, engine=engine)
    assert not outlier.any()


def test_replace_fills_a_cluster_from_its_edges():
    shape = (6, 6, 6)
    truth = smooth_field(shape)
    outlier = np.zeros(shape, dtype=bool)
    outlier[2:5, 2:5, 2:5] = True  # 27 neighbours in a block: the centre has no usable one
    field = np.where(outlier, 99.0, truth)
    u, v, w, n = replace_outliers(*field, outlier)
    assert n == 27
    assert np.all(np.isfinite([u, v, w]))
    np.testing.assert_allclose(np.stack([u, v, w])[:, outlier], truth[:, outlier], atol=0.6)


def test_corrupted_region_is_flagged_and_replaced(rng, seed):
    shape = (48, 48, 48)
    shift = np.array([1.2, -0.7, 2.1])
    a, b = volume_pair(rng, shape, lambda p: p + shift)
    # replace one window's worth of volume B by unrelated particles
    other = np.random.default_rng(seed + 1)
    positions, peaks = seed_particles(other, (16, 16, 16), margin=0)
    noise = render((16, 16, 16), positions, (1.0, 1.0, 1.0), peaks)
    b[16:32, 16:32, 16:32] = noise
    s = PIVSettings(windows=16, overlap=0.0, passes=2)

    field = correlate_volumes(a, b, unit_grid(), settings=s)

    assert field.shape == (3, 3, 3)
    assert not field.valid[1, 1, 1]
    assert field.n_replaced == int((~field.valid).sum()) >= 1
    np.testing.assert_allclose(components_vox(field)[:, 1, 1, 1], shift, atol=0.3)


def test_empty_windows_are_invalid_and_replaced(rng):
    shape = (32, 32, 48)
    shift = np.array([0.4, 0.8, -1.1])
    a, b = volume_pair(rng, shape, lambda p: p + shift)
    a[:, :, 32:] = 0.0  # no particles in the last third along x
    b[:, :, 32:] = 0.0
    s = PIVSettings(windows=16, overlap=0.0, passes=1)
    field = correlate_volumes(a, b, unit_grid(), settings=s)
    assert field.shape == (2, 2, 3)
    assert not field.valid[:, :, 2].any()
    assert field.valid[:, :, :2].all()
    assert np.all(field.correlation[:, :, 2] == 0.0)
    assert np.all(np.isfinite([field.u, field.v, field.w]))


def test_no_particles_at_all_is_an_error():
    zeros = np.zeros((16, 16, 16), dtype=np.float32)
    with pytest.raises(PIVError, match="outliers or empty"):
        correlate_volumes(zeros, zeros, unit_grid(), settings=PIVSettings(windows=8, passes=1))


# --------------------------------------------------------------------------------------------
# API: settings, result object, progress, errors
# --------------------------------------------------------------------------------------------


def test_settings_normalise_windows_and_passes():
    assert PIVSettings(windows=16, passes=None).windows == ((16, 16, 16),)
    assert PIVSettings(windows=(32, 24, 16), passes=None).windows == ((32, 24, 16),)
    s = PIVSettings(windows=((32, 32, 32), (24, 16, 16)), passes=4)
    assert [s.window_vox(k) for k in range(4)] == [
        (32,) * 3,
        (24, 16, 16),
        (24, 16, 16),
        (24, 16, 16),
    ]
    with pytest.raises(FrozenInstanceError):
        s.overlap = 0.75


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"windows": 3}, r"windows = \(3, 3, 3\).*at least 4"),
        ({"windows": (16, 16)}, r"windows = \(16, 16\).*expected an int or a \(wz, wy, wx\)"),
        ({"windows": "big"}, r"windows = 'big'"),
        ({"windows": ((16, 16, 16), (8, 8, 8)), "passes": 1}, r"passes = 1.*>= len\(windows\) = 2"),
        ({"overlap": 1.0}, r"overlap = 1.0.*0 <= overlap < 1"),
        ({"deformation_order": 7}, r"deformation_order = 7.*\(1, 2, 3, 4, 5\)"),
        ({"median_threshold": 0.0}, r"median_threshold = 0.0.*> 0"),
        ({"median_epsilon_vox": -0.1}, r"median_epsilon_vox = -0.1"),
        ({"median_iterations": 0}, r"median_iterations = 0"),
        ({"subpixel": "centroid"}, r"subpixel = 'centroid'.*\('gaussian', 'parabolic'\)"),
        ({"deformation": "yes"}, r"deformation = 'yes'"),
    ],
)
def test_bad_settings_name_parameter_value_and_expectation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PIVSettings(**kwargs)


def test_every_setting_is_a_piv_key_with_the_one_default():
    """The ``[piv]`` table is PIVSettings: no key of its own, the same defaults."""
    from plenopiv.config.experiment import experiment_from_dict
    from plenopiv.piv.settings import PIVSettings

    volume = {"x_mm": [-1, 1], "y_mm": [-1, 1], "z_mm": [-1, 1], "voxel_mm": 0.25}
    exp = experiment_from_dict({"camera": "small_test", "volume": volume})
    assert exp.piv == PIVSettings()
    exp = experiment_from_dict({"camera": "small_test", "volume": volume, "piv": {}})
    assert exp.piv == PIVSettings()


def test_piv_keys_reach_the_settings():
    from plenopiv.config.experiment import experiment_from_dict
    from plenopiv.piv.settings import PIVSettings

    given = {"windows": [(16, 12, 12)], "passes": 2, "overlap": 0.25, "deformation": False,
             "deformation_order": 1, "median_threshold": 3.0, "median_epsilon_vox": 0.2,
             "median_iterations": 3, "smooth_predictor": False, "subpixel": "parabolic",
             "replacement": "mean", "overlap_correction": False, "broad_peaks": False}
    volume = {"x_mm": [-1, 1], "y_mm": [-1, 1], "z_mm": [-1, 1], "voxel_mm": 0.25}
    toml = {**given, "windows": [[16, 12, 12]], "uncertainty": "correlation",
            "response_displacements": 1}
    s = experiment_from_dict({"camera": "small_test", "volume": volume, "piv": toml}).piv
    assert s == PIVSettings(**{**toml, "windows": ((16, 12, 12),)})


@pytest.mark.parametrize(
    ("key", "value"),
    [("deformation_order", 6), ("deformation_order", True), ("median_epsilon_vox", -0.1),
     ("median_epsilon_vox", float("inf")), ("median_iterations", 0), ("subpixel", "centroid")],
)
def test_bad_piv_keys_are_refused_by_name(key, value):
    from plenopiv.piv.settings import PIVSettings

    with pytest.raises(ValueError, match=key):
        PIVSettings(**{key: value})


@pytest.fixture
def small_pair(rng):
    return volume_pair(rng, (24, 24, 24), lambda p: p + 1.0)


def test_bad_volumes_raise_piv_errors(small_pair):
    a, b = small_pair
    s = PIVSettings(windows=16, passes=1)
    with pytest.raises(
        PIVError, match=r"volume_a has shape \(24, 24, 24\) and volume_b \(24, 24, 20\)"
    ):
        correlate_volumes(a, b[:, :, :20], unit_grid(), settings=s)
    bad = b.copy()
    bad[3, 4, 5] = np.nan
    with pytest.raises(
        PIVError, match=r"volume_b holds 1 non-finite voxels \(first at \[z, y, x\] = \(3, 4, 5\)\)"
    ):
        correlate_volumes(a, bad, unit_grid(), settings=s)
    with pytest.raises(PIVError, match="volume_a has 2 dimensions"):
        correlate_volumes(a[0], b[0], unit_grid(), settings=s)
    big = PIVSettings(windows=((16, 16, 16), (32, 16, 16)), passes=2)
    with pytest.raises(
        PIVError, match=r"windows\[1\] = \(32, 16, 16\).*larger than the volume.*z: 32 > 24"
    ):
        correlate_volumes(a, b, unit_grid(), settings=big)


def test_accepts_the_project_volume_grid(small_pair):
    from plenopiv.camera.grid import VolumeGrid

    a, b = small_pair
    grid = VolumeGrid(origin=(1e-3, 2e-3, 3e-3), voxel=(1e-4, 2e-4, 3e-4), shape=a.shape)
    s = PIVSettings(windows=16, passes=2)
    field = correlate_volumes(a, b, grid, settings=s)
    in_voxels = correlate_volumes(a, b, unit_grid(), settings=s)
    np.testing.assert_allclose(field.x, 1e-3 + 7.5 * 1e-4 + 8 * 1e-4 * np.arange(2))
    np.testing.assert_allclose(field.z, 3e-3 + 7.5 * 3e-4 + 8 * 3e-4 * np.arange(2))
    np.testing.assert_allclose(field.u, in_voxels.u * 1e-4)
    np.testing.assert_allclose(field.w, in_voxels.w * 3e-4)


def test_bad_grid_and_options_raise(small_pair):
    a, b = small_pair
    s = PIVSettings(windows=16, passes=1)
    with pytest.raises(PIVError, match="expected a VolumeGrid, or an object with attributes"):
        correlate_volumes(a, b, object(), settings=s)
    with pytest.raises(PIVError, match=r"grid.voxel_size = .*> 0 metres"):
        correlate_volumes(
            a, b, SimpleNamespace(origin=(0, 0, 0), voxel_size=(1e-4, 0.0, 1e-4)), settings=s
        )
    with pytest.raises(
        PIVError, match=r"grid.shape = \(24, 24, 25\) but the volumes have shape \(24, 24, 24\)"
    ):
        correlate_volumes(a, b, unit_grid((24, 24, 25)), settings=s)
    with pytest.raises(ValueError, match=r"engine = 'cuda': expected one of \('numba', 'numpy'\)"):
        correlate_volumes(a, b, unit_grid(), settings=s, engine="cuda")
    with pytest.raises(ValueError, match=r"workers = 0"):
        correlate_volumes(a, b, unit_grid(), settings=s, workers=0)
    with pytest.raises(ValueError, match="settings = "):
        correlate_volumes(a, b, unit_grid(), settings={"windows": 16})


def test_vector_field_is_read_only_and_gives_velocity(small_pair):
    a, b = small_pair
    calls = []
    field = correlate_volumes(
        a,
        b,
        unit_grid(),
        settings=PIVSettings(windows=(16, 16, 8), passes=2),
        progress=calls.append,
    )
    assert [c["pass"] for c in calls] == [1, 2]
    assert calls[-1]["window_vox"] == (16, 16, 8) and calls[-1]["n_vectors"] == field.u.size
    assert field.shape == (2, 2, 5)
    with pytest.raises(ValueError):
        field.u[0, 0, 0] = 1.0
    with pytest.raises(FrozenInstanceError):
        field.u = field.v
    vx, vy, vz = field.velocity(0.5e-3)
    np.testing.assert_allclose(vx, field.u / 0.5e-3)
    np.testing.assert_allclose(vz, field.w / 0.5e-3)
    with pytest.raises(ValueError, match=r"dt = 0.0.*> 0 s"):
        field.velocity(0.0)
    with pytest.raises(ValueError, match=r"valid has shape \(2,\)"):
        VectorField(
            x=[0.0],
            y=[0.0],
            z=[0.0],
            u=np.zeros((1, 1, 1)),
            v=np.zeros((1, 1, 1)),
            w=np.zeros((1, 1, 1)),
            valid=[True, True],
            snr=np.ones((1, 1, 1)),
            correlation=np.ones((1, 1, 1)),
        )


def test_inputs_are_not_changed(small_pair):
    a, b = small_pair
    a0, b0 = a.copy(), b.copy()
    correlate_volumes(a, b, unit_grid(), settings=PIVSettings(windows=16, passes=2))
    np.testing.assert_array_equal(a, a0)
    np.testing.assert_array_equal(b, b0)


# --------------------------------------------------------------------------------------------
# kernels: numba against the NumPy twins (and against scipy where it applies)
# --------------------------------------------------------------------------------------------


def test_kernel_extract_windows(rng):
    volume = rng.random((9, 10, 11), dtype=np.float32)
    starts = np.array([[0, 0, 0], [-3, 2, 5], [6, 7, 8], [-9, 0, 0], [2, -2, 9]], dtype=np.int64)
    got = ENGINES["numba"].extract_windows(volume, starts, 5, 4, 6)
    want = ENGINES["numpy"].extract_windows(volume, starts, 5, 4, 6)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(got[0], volume[:5, :4, :6])
    assert not got[3].any()  # entirely outside


def staged_layout_spectra(rng, window, n):
    """Real-FFT spectra of ``n`` random windows in the (kz, 1, ky, n, kx) layout."""
    windows = rng.normal(2.0, 1.0, size=(n,) + window).astype(np.float32)
    spectra = scipy.fft.rfftn(windows, axes=(1, 2, 3))
    return windows, spectra[None].transpose(2, 0, 3, 1, 4)


@pytest.mark.parametrize("window", [(8, 6, 10), (5, 7, 9)])
def test_kernel_cross_spectrum(rng, window):
    wa, fa = staged_layout_spectra(rng, window, 4)
    wb, fb = staged_layout_spectra(rng, window, 4)
    outs, energies = [], []
    for name in ENGINE_NAMES:
        kz, p, ky, q, kx = fa.shape
        out = np.empty((p, q, kz, ky, kx), dtype=np.complex64)
        energies.append(ENGINES[name].cross_spectrum(fa, fb, window[2], out))
        outs.append(out)
    np.testing.assert_allclose(outs[0], outs[1], rtol=1e-5, atol=1e-3)
    np.testing.assert_allclose(energies[0], energies[1], rtol=1e-5)
    # Parseval: energies about the mean and totals of the windows themselves
    a64, b64 = wa.astype(np.float64), wb.astype(np.float64)
    centred = lambda w: ((w - w.mean(axis=(1, 2, 3), keepdims=True)) ** 2).sum(axis=(1, 2, 3))  # noqa: E731
    want = np.stack(
        [centred(a64), centred(b64), (a64**2).sum(axis=(1, 2, 3)), (b64**2).sum(axis=(1, 2, 3))],
        axis=1,
    )
    np.testing.assert_allclose(energies[0], want, rtol=1e-4)
    # the inverse of the cross spectrum is the circular correlation of the centred windows
    corr = scipy.fft.irfftn(outs[0].reshape((4,) + outs[0].shape[2:]), s=window, axes=(1, 2, 3))
    a0 = a64[1] - a64[1].mean()
    b0 = b64[1] - b64[1].mean()
    s = (2, 1, 3)
    direct = np.sum(a0 * np.roll(b0, [-k for k in s], axis=(0, 1, 2)))
    assert corr[1][s] == pytest.approx(direct, rel=1e-4)


@pytest.mark.parametrize("gaussian", [True, False])
def test_kernel_find_peaks(rng, gaussian):
    n, shape = 6, (8, 10, 12)
    corr = rng.normal(0.0, 0.05, size=(n,) + shape).astype(np.float32)
    grid = np.indices(shape).astype(float)
    for k in range(n):
        centre = rng.uniform(-3, 3, size=3)
        d = [((g - c) + n_ / 2) % n_ - n_ / 2 for g, c, n_ in zip(grid, centre, shape, strict=True)]
        corr[k] += np.exp(-0.5 * sum(x**2 for x in d) / 1.2**2).astype(np.float32)
    corr[2] -= 0.6  # a peak with negative neighbours: the Gaussian fit falls back
    got = ENGINES["numba"].find_peaks(corr, gaussian)
    want = ENGINES["numpy"].find_peaks(corr, gaussian)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6)
    assert np.all(got[2] >= 1.0)


def test_kernel_find_peaks_recovers_a_sampled_gaussian():
    shape = (16, 16, 16)
    true = np.array([1.3, -2.45, 0.2])
    grid = np.indices(shape).astype(float)
    d = [((g - c) + 8) % 16 - 8 for g, c in zip(grid, true, strict=True)]
    corr = np.exp(-0.5 * sum(x**2 for x in d) / 1.5**2).astype(np.float32)[None]
    for name in ENGINE_NAMES:
        disp, peak, snr = ENGINES[name].find_peaks(corr, True)
        np.testing.assert_allclose(disp[0], true, atol=1e-4)
        assert snr[0] == np.inf  # a single peak: no secondary local maximum above zero


def _triangle_weighted_peak(shape, true, sigma):
    """A circular Gaussian peak at ``true`` times the windows' overlap triangle."""
    grid = np.indices(shape).astype(float)
    lags = [((g + n // 2) % n) - n // 2 for g, n in zip(grid, shape, strict=True)]
    peak = np.exp(-0.5 * sum(((lg - t) / s) ** 2 for lg, t, s in zip(lags, true, sigma,
                                                                        strict=True)))
    overlap = np.prod([1 - np.abs(lg) / n for lg, n in zip(lags, shape, strict=True)], axis=0)
    return (peak * overlap).astype(np.float32)


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_refine_peaks_removes_the_overlap_bias_of_a_broad_peak(engine):
    # a depth-elongated particle (sigma 1.9 voxel) correlated in 12-voxel windows: the plain
    # 3-point fit of the overlap-weighted peak loses ~0.4 voxel of a 1-voxel displacement
    shape = (12, 12, 12)
    true = np.array([1.0, -0.3, 0.2])
    sigma = np.array([1.9 * 2**0.5, 0.6, 0.6])         # correlation peak: sqrt(2) x particle
    corr = _triangle_weighted_peak(shape, true, sigma)[None]
    plain, _, _ = ENGINES[engine].find_peaks(corr, True)
    assert plain[0, 0] < true[0] - 0.2
    refined = ENGINES[engine].refine_peaks(corr, True, True, True)
    np.testing.assert_allclose(refined[0], true, atol=0.01)
    # without the overlap correction the bias stays
    assert ENGINES[engine].refine_peaks(corr, True, False, True)[0, 0] < true[0] - 0.2


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_refine_peaks_fits_seven_samples_of_a_wide_depth_peak(engine):
    # near focus a share of the particles keeps its reconstructed depth while the others
    # move further than the flow (a particle's light stays in one lenslet until its blur
    # crosses the lenslet's edge): the depth peak is a main lobe at the frozen particles'
    # lag with a shoulder at the movers'. Five samples (lags -2..2) see the top of a peak
    # 2.7 voxels wide (sigma of the correlation of 1.9-voxel particles) and stay on the main
    # lobe; seven samples take in more of the shoulder. Mixture: 70 % of the weight at lag 0,
    # 30 % at lag 4; its mean displacement is 1.2 voxel.
    shape = (12, 12, 12)
    sigma = np.array([1.9 * 2**0.5, 0.6, 0.6])
    frozen = _triangle_weighted_peak(shape, np.array([0.0, 0.0, 0.0]), sigma)
    moved = _triangle_weighted_peak(shape, np.array([4.0, 0.0, 0.0]), sigma)
    corr = (0.7 * frozen + 0.3 * moved)[None]
    seven = ENGINES[engine].refine_peaks(corr, True, True, True)[0, 0]
    five = _five_point_vertex(corr[0, :, 0, 0], shape[0])
    # the wider fit moves towards the mean displacement, never past it
    assert five < seven < 1.2
    # a single wide Gaussian peak stays exact with seven samples
    true = np.array([0.6, -0.3, 0.2])
    single = _triangle_weighted_peak(shape, true, sigma)[None]
    np.testing.assert_allclose(ENGINES[engine].refine_peaks(single, True, True, True)[0], true,
                               atol=0.01)


def _depth_sweep(engine, true):
    """Depth peaks of a wide particle image (sigma 1.9 voxel, 12-voxel windows) at the lags
    ``true``, their laterals fixed off the grid: the refined depth of each."""
    shape = (12, 12, 12)
    sigma = np.array([1.9 * 2**0.5, 0.6, 0.6])
    return np.array([ENGINES[engine].refine_peaks(
        _triangle_weighted_peak(shape, np.array([dz, 0.2, -0.1]), sigma)[None],
        True, True, True)[0, 0] for dz in true])


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_seven_sample_fit_has_unit_gain_and_no_peak_locking_in_depth(engine):
    """A wide depth peak moved through sub-voxel steps across a voxel either side of zero, at
    positions not symmetric about a voxel centre: the measured depth follows the true one with
    gain 1 and no bias (a peak-locked estimator shows a gain below 1 and a staircase)."""
    true = np.linspace(-0.9, 0.9, 19) + 0.037
    measured = _depth_sweep(engine, true)
    gain, bias = np.polyfit(true, measured, 1)
    assert gain == pytest.approx(1.0, abs=0.01)
    assert abs(bias) < 0.01
    np.testing.assert_allclose(measured, true, atol=0.015)


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_wide_depth_peaks_beyond_one_voxel_are_not_clipped(engine):
    """The overlap correction moves a wide depth peak up to 2 sigma^2 / w (about 1.2 voxel
    here) from the raw correlation's highest sample: a true lag beyond one voxel is followed,
    not clipped at the integer peak's neighbour."""
    true = np.linspace(-1.5, 1.5, 13) + 0.037
    np.testing.assert_allclose(_depth_sweep(engine, true), true, atol=0.015)


def _five_point_vertex(line, w):
    """Vertex of the weighted least-squares Gaussian through lags -2..2 of the overlap-corrected
    correlation ``line`` (its integer peak at lag 0 or the highest sample)."""
    b = int(np.argmax(line))
    lag0 = b - w if 2 * b >= w else b
    lags = lag0 + np.arange(-2, 3)
    u = line[(b + np.arange(-2, 3)) % w] / (1 - np.abs(lags) / w)
    coef = np.polyfit(lags - lag0, np.log(u), 2, w=u)  # polyfit weights multiply residuals
    return lag0 - coef[1] / (2 * coef[0])


def _refinement_bound(window, broad):
    """Largest offset (voxels) the refinement may add to the integer peak along an axis."""
    if not broad or window < 8:
        return 1.0
    return 1.5 if window < 12 else 2.5


def test_refine_peaks_engines_agree(rng):
    n, shape = 8, (8, 12, 16)
    corr = rng.normal(0.0, 0.03, size=(n,) + shape).astype(np.float32)
    for k in range(n):
        true = rng.uniform(-2.5, 2.5, size=3)
        sigma = rng.uniform(0.5, 3.0, size=3)
        corr[k] += _triangle_weighted_peak(shape, true, sigma)
    corr[2] -= 0.5                                      # negative samples: 3-point fall-back
    for gaussian in (True, False):
        for overlap in (True, False):
            for broad in (True, False):
                got = ENGINES["numba"].refine_peaks(corr, gaussian, overlap, broad)
                want = ENGINES["numpy"].refine_peaks(corr, gaussian, overlap, broad)
                np.testing.assert_allclose(got, want, atol=1e-6)
                # the integer peak is the one find_peaks takes; the refinement moves it by at
                # most half a voxel inside the lags its fit read: 1 voxel for the 3-point
                # fit, 1.5 for five samples (windows of 8 or more), 2.5 for seven (12 or more)
                plain, _, _ = ENGINES["numpy"].find_peaks(corr, gaussian)
                bound = np.array([_refinement_bound(w, gaussian and broad) for w in shape])
                assert np.all(np.abs(got - np.rint(plain)) <= bound + 1e-9)


def test_refine_peaks_without_options_is_the_three_point_fit(rng):
    corr = rng.random((5, 8, 8, 8)).astype(np.float32)
    for gaussian in (True, False):
        plain, _, _ = ENGINES["numba"].find_peaks(corr, gaussian)
        np.testing.assert_allclose(ENGINES["numba"].refine_peaks(corr, gaussian, False, False),
                                   plain, atol=1e-9)


def test_one_pass_measures_elongated_particles_at_their_true_size(rng):
    # particles of the 50 mm plenoptic geometry (sigma 1.9 voxel in z, 0.5 laterally), one
    # 12-voxel pass: the overlap correction removes the ~50 % under-measurement along z
    shape = (36, 36, 36)
    shift = np.array([1.0, 0.4, -0.6])
    a, b = volume_pair(rng, shape, lambda p: p + shift, sigma_vox=(1.9, 0.6, 0.6), density=0.02)
    z = {}
    for corrected in (False, True):
        s = PIVSettings(windows=(12, 12, 12), passes=1, overlap_correction=corrected,
                        broad_peaks=corrected)
        field = correlate_volumes(a, b, unit_grid(), settings=s)
        z[corrected] = interior(components_vox(field))[0].mean()
    assert z[False] < 0.7 * shift[0]
    assert abs(z[True] - shift[0]) < 0.1, z


@pytest.mark.parametrize("factor", [0.5, -0.5])
def test_kernel_deform_trilinear(rng, factor):
    volume = rng.random((7, 8, 9), dtype=np.float32)
    field = rng.normal(0.0, 2.0, size=(3, 7, 8, 9)).astype(np.float32)
    got = ENGINES["numba"].deform_trilinear(volume, field, factor)
    want = ENGINES["numpy"].deform_trilinear(volume, field, factor)
    np.testing.assert_allclose(got, want, atol=1e-5)
    coords = np.indices(volume.shape) + factor * field.astype(np.float64)
    ref = scipy.ndimage.map_coordinates(volume, coords, order=1, mode="grid-constant")
    np.testing.assert_allclose(got, ref, atol=1e-5)


@pytest.mark.parametrize("factor", [0.5, -0.5])
def test_kernel_deform_cubic(rng, factor):
    volume = rng.random((7, 8, 9), dtype=np.float32)
    field = rng.normal(0.0, 2.0, size=(3, 7, 8, 9)).astype(np.float32)
    coeffs = _spline_coefficients(volume, 3)
    got = ENGINES["numba"].deform_cubic(coeffs, field, factor, _SPLINE_PAD)
    want = ENGINES["numpy"].deform_cubic(coeffs, field, factor, _SPLINE_PAD)
    np.testing.assert_allclose(got, want, atol=1e-5)
    coords = np.indices(volume.shape) + factor * field.astype(np.float64)
    ref = scipy.ndimage.map_coordinates(volume, coords, order=3, mode="grid-constant")
    np.testing.assert_allclose(got, ref, atol=1e-4)
    still = ENGINES["numba"].deform_cubic(coeffs, np.zeros_like(field), factor, _SPLINE_PAD)
    np.testing.assert_allclose(still, volume, atol=1e-5)  # the spline interpolates


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5])
def test_deformation_equals_scipy_spline_interpolation(rng, order):
    # every deformation order samples the volume as scipy.ndimage does with zero outside
    volume = rng.random((7, 8, 9), dtype=np.float32)
    field = rng.normal(0.0, 2.0, size=(3, 7, 8, 9)).astype(np.float32)
    coeffs = None if order == 1 else _spline_coefficients(volume, order)
    got = _deform(volume, field, 0.5, order, ENGINES["numba"], coeffs)
    coords = np.indices(volume.shape) + 0.5 * field.astype(np.float64)
    ref = scipy.ndimage.map_coordinates(volume, coords, order=order, mode="grid-constant")
    np.testing.assert_allclose(got, ref, atol=1e-5)


def test_kernel_neighbour_median(rng):
    field = rng.normal(size=(3, 5, 6, 7))
    usable = rng.random((5, 6, 7)) > 0.3
    usable[2:5, 2:5, 2:5] = False  # a vector with no usable neighbour: NaN
    got = ENGINES["numba"].neighbour_median(field, usable)
    want = ENGINES["numpy"].neighbour_median(field, usable)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, equal_nan=True)
    assert np.isnan(got[0][:, 3, 3, 3]).all()


def test_staged_window_spectra_equal_direct_ffts(rng):
    volume = rng.random((40, 36, 44), dtype=np.float32)
    layout = _window_layout(volume.shape, (16, 12, 20), 0.5)
    n_z, n_y, n_x = layout.shape
    seen = 0
    for iz, y0, y1, spectra in _regular_spectra(volume, layout, 1):
        for iy in range(y0, y1):
            for ix in range(n_x):
                z, y, x = (int(s[i]) for s, i in zip(layout.starts, (iz, iy, ix), strict=True))
                window = volume[z : z + 16, y : y + 12, x : x + 20]
                np.testing.assert_allclose(
                    spectra[:, iy - y0, :, ix, :], scipy.fft.rfftn(window), rtol=1e-4, atol=1e-3
                )
                seen += 1
    assert seen == n_z * n_y * n_x
