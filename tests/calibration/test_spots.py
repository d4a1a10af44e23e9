"""Tests of lenslet spot detection and lattice fitting (plenopiv.calibration.spots).

Synthetic images are rendered here with NumPy (pixel-integrated Gaussian spots on a known
lattice), so every centre is known exactly. Third-party reference images are read from
``<repo>/../shared/data`` (tests marked ``data``): skipped, naming the folder and how to get the
data, when that folder is absent (a failure under ``CI=true``; see ``conftest.shared_data_path``).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.special import erf

from conftest import shared_data_path
from plenopiv.calibration import _spot_kernels as K
from plenopiv.calibration.lattice_fit import fit_lattice
from plenopiv.calibration.spot_detection import detect_spots, estimate_pitch
from plenopiv.calibration.spot_types import Lattice, SpotFlag, SpotSet
from plenopiv.errors import CalibrationError, ImageError

# ``rng`` (a seeded np.random.Generator) comes from tests/conftest.py.


# ----------------------------------------------------------------------------------------------
# Synthetic lattices and images
# ----------------------------------------------------------------------------------------------


def lattice_points(grid, n_rows, n_cols, pitch, rotation, origin):
    """True centres ``(row, col)`` and indices of a lattice in the module's convention.

    ``rotation`` is the angle of the +col lattice axis towards +row (rad); on a hexagonal grid
    ``pitch`` is the neighbour distance and odd rows are shifted half a pitch towards +col.
    """
    c, s = np.cos(rotation), np.sin(rotation)
    e_col = pitch * np.array([s, c])
    row_step = pitch * (np.sqrt(3.0) / 2.0 if grid == "hexagonal" else 1.0)
    e_row = row_step * np.array([c, -s])
    i, j = np.meshgrid(np.arange(n_rows), np.arange(n_cols), indexing="ij")
    i, j = i.ravel(), j.ravel()
    u = j + (0.5 * (i % 2) if grid == "hexagonal" else 0.0)
    centres = np.asarray(origin, float) + i[:, None] * e_row + u[:, None] * e_col
    return centres, np.column_stack([i, j])


def render(shape, centres, sigma, amplitude):
    """Noise-free image of pixel-integrated circular Gaussian spots (peak ``amplitude``)."""
    img = np.zeros(shape)
    rows = np.arange(shape[0])
    cols = np.arange(shape[1])
    s2 = np.sqrt(2.0) * sigma
    amps = np.broadcast_to(np.asarray(amplitude, float), (len(centres),))
    for (y, x), a in zip(centres, amps, strict=True):
        h = int(np.ceil(6 * sigma))
        r0, r1 = max(int(y) - h, 0), min(int(y) + h + 1, shape[0])
        c0, c1 = max(int(x) - h, 0), min(int(x) + h + 1, shape[1])
        if r0 >= r1 or c0 >= c1:
            continue
        pr = 0.5 * (erf((rows[r0:r1] - y + 0.5) / s2) - erf((rows[r0:r1] - y - 0.5) / s2))
        pc = 0.5 * (erf((cols[c0:c1] - x + 0.5) / s2) - erf((cols[c0:c1] - x - 0.5) / s2))
        img[r0:r1, c0:c1] += a * 2.0 * np.pi * sigma**2 * np.outer(pr, pc)
    return img


def match(found, truth, radius):
    """Index of the nearest ``found`` spot for each truth, and whether it lies within radius."""
    d, k = cKDTree(found).query(truth)
    return k, d < radius


def centroid_noise_px(image, centres, radius, threshold, noise_sigma):
    """Rms position noise (px, per axis) of the thresholded centroid, by error propagation.

    ``x = sum(w x) / sum(w)`` with ``w = I - L`` on pixels above the level ``L``; an independent
    pixel noise ``s`` moves it by ``var(x) = s^2 sum_(w > 0) (x_i - x)^2 / (sum w)^2``. The
    level is taken from the noise-free spot, as the detector takes it from the 3 x 3-mean peak.
    """
    var = []
    rr, cc = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    for y, x in centres:
        inside = (rr - y) ** 2 + (cc - x) ** 2 <= radius**2
        peak = image[inside].max()
        w = np.where(inside, image - threshold * peak, 0.0)
        w = np.where(w > 0, w, 0.0)
        sw = w.sum()
        on = w > 0
        var.append(noise_sigma**2 * np.sum((rr[on] - y) ** 2) / sw**2)
        var.append(noise_sigma**2 * np.sum((cc[on] - x) ** 2) / sw**2)
    return float(np.sqrt(np.mean(var)))


# ----------------------------------------------------------------------------------------------
# Sub-pixel centres on synthetic lattices
# ----------------------------------------------------------------------------------------------

SQUARE = dict(grid="square", n_rows=12, n_cols=14, pitch=15.0, rotation=0.03, origin=(12.3, 10.7))
HEX = dict(grid="hexagonal", n_rows=13, n_cols=12, pitch=16.0, rotation=-0.012, origin=(11.6, 12.2))


@pytest.mark.parametrize("sigma", [1.0, 1.5, 2.0])
def test_noise_free_centres_are_within_the_threshold_sampling_bias(sigma):
    centres, _ = lattice_points(**SQUARE)
    image = render((200, 230), centres, sigma, 1000.0)
    spots = detect_spots(image, expected_pitch_px=SQUARE["pitch"])
    assert len(spots) == len(centres)
    k, ok = match(spots.centres_px, centres, SQUARE["pitch"] / 4)
    assert ok.all()
    err = spots.centres_px[k] - centres
    # A thresholded centroid of a pixel-sampled spot is not exactly point-symmetric about
    # the true centre unless it sits on a pixel centre; for spots with sigma >= 1 px this
    # sampling bias stays below 0.02 px (Fourier terms of the sampled Gaussian ~ exp(-2 pi^2
    # sigma^2) are negligible; the residual comes from the pixels crossing the threshold).
    assert np.abs(err).max() < 0.02


def render_discs(shape, centres, radius, level, supersample=8):
    """Noise-free white-image-like micro-images: flat discs, pixel coverage by supersampling."""
    img = np.zeros(shape)
    off = (np.arange(supersample) + 0.5) / supersample - 0.5
    for y, x in centres:
        r0, r1 = max(int(y - radius) - 1, 0), min(int(y + radius) + 2, shape[0])
        c0, c1 = max(int(x - radius) - 1, 0), min(int(x + radius) + 2, shape[1])
        if r0 >= r1 or c0 >= c1:
            continue
        rr = (np.arange(r0, r1)[:, None] + off[None, :]).ravel()
        cc = (np.arange(c0, c1)[:, None] + off[None, :]).ravel()
        inside = (rr[:, None] - y) ** 2 + (cc[None, :] - x) ** 2 <= radius**2
        cover = inside.reshape(r1 - r0, supersample, c1 - c0, supersample).mean(axis=(1, 3))
        img[r0:r1, c0:c1] += level * cover
    return img


@pytest.mark.parametrize("grid", ["square", "hexagonal"])
def test_white_image_discs(grid):
    # full-aperture micro-images: 40 px discs on a 48 px pitch, as in a white image
    centres, index = lattice_points(grid, 8, 9, 48.0, 0.004, (30.3, 31.7))
    image = render_discs((400, 470), centres, 20.0, 200.0) + 10.0
    spots = detect_spots(image)
    lattice = fit_lattice(spots)
    assert lattice.grid == grid
    k, ok = match(spots.centres_px, centres, 12.0)
    assert ok.all() and len(spots) == len(centres)
    # the thresholded centroid of a pixel-sampled disc: the same sampling bias as for spots
    complete = (lattice.flags[k] & SpotFlag.EDGE) == 0
    assert np.abs(spots.centres_px[k[complete]] - centres[complete]).max() < 0.02
    assert lattice.rotation_rad == pytest.approx(0.004, abs=5 * lattice.rotation_std_rad + 1e-5)


def test_alignment_image_very_small_spots(rng):
    # spots of 1.4 px FWHM (sigma 0.6 px): still several pixels, not hot pixels
    centres, _ = lattice_points("square", 10, 12, 17.0, 0.01, (10.3, 11.6))
    image = render((190, 220), centres, 0.6, 1000.0) + rng.normal(0.0, 5.0, (190, 220))
    spots = detect_spots(image)
    assert len(spots) == len(centres) and len(spots.rejected_px) == 0
    k, ok = match(spots.centres_px, centres, 17.0 / 4)
    assert ok.all()
    # a spot this small is sampled coarsely: its thresholded centroid locks towards pixel
    # centres by up to a few hundredths of a pixel
    assert np.abs(spots.centres_px[k] - centres).max() < 0.05


@pytest.mark.parametrize("method", ["centroid", "gaussian"])
def test_noisy_square_lattice_error_matches_propagated_noise(rng, method):
    shape = (200, 230)
    centres, _ = lattice_points(**SQUARE)
    clean = render(shape, centres, 1.5, 1000.0)
    noise_sigma = 20.0
    noisy = clean + 100.0 + rng.normal(0.0, noise_sigma, shape)
    ref = detect_spots(clean, expected_pitch_px=15.0, method=method, threshold=0.1)
    got = detect_spots(noisy, expected_pitch_px=15.0, method=method, threshold=0.1)
    assert len(got) == len(centres)
    k_ref, ok_ref = match(ref.centres_px, centres, 3.0)
    k_got, ok_got = match(got.centres_px, centres, 3.0)
    assert ok_ref.all() and ok_got.all()
    # the noise moves each centre away from its noise-free estimate (same pixel sampling)
    delta = got.centres_px[k_got] - ref.centres_px[k_ref]
    measured = float(np.sqrt(np.mean(delta**2)))
    threshold = 0.1  # the default of detect_spots
    predicted = centroid_noise_px(clean, centres, got.window_radius_px, threshold, noise_sigma)
    # 336 samples estimate an rms to about 4 %, and the propagation leaves out the noise of
    # the threshold level and of the background (a few %): the centroid must meet it within
    # -15 % ... +20 %. On Gaussian spots in additive noise the least-squares Gaussian fit is
    # the better estimator (it weights pixels by the model's slope): below the centroid's
    # noise, though not by more than a third.
    if method == "centroid":
        assert 0.85 * predicted < measured < 1.2 * predicted
    else:
        assert 0.67 * predicted < measured < 1.0 * predicted
    bias = delta.mean(axis=0)
    assert np.all(np.abs(bias) < 4 * measured / np.sqrt(len(centres)))


def test_square_lattice_fit_recovers_pitch_rotation_and_indices(rng):
    shape = (200, 230)
    centres, index = lattice_points(**SQUARE)
    image = render(shape, centres, 1.5, 1000.0) + rng.normal(0.0, 10.0, shape)
    lattice = fit_lattice(detect_spots(image))  # pitch estimated from the image
    assert lattice.grid == "square"
    assert np.allclose(lattice.pitch_px, 15.0, atol=5 * lattice.pitch_std_px.max() + 1e-3)
    assert abs(lattice.rotation_rad - 0.03) < 5 * lattice.rotation_std_rad + 1e-4
    k, ok = match(lattice.centres_px, centres, 3.0)
    assert ok.all()
    # the same indices up to the choice of (0, 0): the first row and column holding a spot
    assert np.array_equal(lattice.grid_index[k] - lattice.grid_index[k].min(axis=0), index)
    # every spot is fitted except those whose window (half a pitch) is cut by the image edge
    assert lattice.n_missing == 0
    assert np.array_equal(lattice.inlier, (lattice.flags & SpotFlag.EDGE) == 0)
    assert np.allclose(lattice.predict(lattice.grid_index[k]), centres, atol=0.02)


def test_hexagonal_lattice_fit(rng):
    shape = (210, 220)
    centres, index = lattice_points(**HEX)
    image = render(shape, centres, 1.4, 800.0) + rng.normal(0.0, 8.0, shape)
    spots = detect_spots(image)
    lattice = fit_lattice(spots)
    assert lattice.grid == "hexagonal"
    assert abs(lattice.rotation_rad - HEX["rotation"]) < 5 * lattice.rotation_std_rad + 1e-4
    assert lattice.pitch_px[1] == pytest.approx(16.0, abs=5 * lattice.pitch_std_px[1] + 1e-3)
    assert lattice.pitch_px[0] == pytest.approx(
        16.0 * np.sqrt(3) / 2, abs=5 * lattice.pitch_std_px[0] + 1e-3
    )
    # odd rows shifted half a column step towards +col
    assert np.allclose(lattice.odd_row_shift_px, lattice.basis[1] / 2, atol=0.02)
    k, ok = match(lattice.centres_px, centres, 3.0)
    assert ok.all()
    got = lattice.grid_index[k]
    assert np.array_equal(got[:, 0] - got[:, 0].min(), index[:, 0])
    assert np.array_equal(got[:, 1] - got[:, 1].min(), index[:, 1])
    assert got[:, 0].min() == 0  # row 0 is an even row holding spots


def test_hexagonal_index_parity_when_first_row_is_shifted():
    # drop the first (unshifted) row: the top row is now shifted half a step, so it must be
    # indexed as an even row whose columns begin at 0 while the next rows move accordingly
    centres, index = lattice_points(
        grid="hexagonal", n_rows=9, n_cols=9, pitch=10.0, rotation=0.0, origin=(5, 5)
    )
    keep = index[:, 0] >= 1
    lattice = fit_lattice(centres[keep])
    assert lattice.grid == "hexagonal"
    assert lattice.grid_index[:, 0].min() == 0 and lattice.grid_index[:, 1].min() == 0
    assert np.allclose(lattice.predict(lattice.grid_index), centres[keep], atol=1e-9)
    # odd rows lie half a step to +col of the even rows
    shift = lattice.odd_row_shift_px
    assert shift[1] == pytest.approx(lattice.basis[1, 1] / 2, abs=1e-9)


def test_rotation_sign_convention():
    # the lattice +col axis points towards +row: angle atan2(d_row, d_col) > 0
    centres, _ = lattice_points(
        grid="square", n_rows=6, n_cols=6, pitch=10.0, rotation=0.02, origin=(5, 5)
    )
    lattice = fit_lattice(centres)
    assert lattice.rotation_rad == pytest.approx(0.02, abs=1e-12)
    assert lattice.basis[1, 0] > 0  # moving along +col, the row grows


@settings(max_examples=25, deadline=None)
@given(
    grid=st.sampled_from(["square", "hexagonal"]),
    rotation=st.floats(-0.3, 0.3),
    pitch=st.floats(5.0, 40.0),
    origin=st.tuples(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0)),
    seed=st.integers(0, 2**16),
)
def test_exact_lattice_points_are_fitted_exactly(grid, rotation, pitch, origin, seed):
    centres, _ = lattice_points(grid, 7, 8, pitch, rotation, origin)
    order = np.random.default_rng(seed).permutation(len(centres))
    lattice = fit_lattice(centres[order])
    assert lattice.grid == grid
    assert lattice.rotation_rad == pytest.approx(rotation, abs=1e-9)
    assert np.allclose(lattice.predict(lattice.grid_index), centres[order], atol=1e-8 * pitch)
    assert lattice.rms_residual_px < 1e-8 * pitch
    assert lattice.grid_index.min() == 0
    assert len({tuple(ij) for ij in lattice.grid_index}) == len(centres)


# ----------------------------------------------------------------------------------------------
# Robustness: hot pixels, dust, holes, partial lenslets
# ----------------------------------------------------------------------------------------------


def _square_image(rng, amplitude=1000.0, extra=None, shape=(200, 230)):
    centres, index = lattice_points(**SQUARE)
    amp = np.full(len(centres), amplitude)
    if extra is not None:
        amp = extra(amp, index)
    image = render(shape, centres, 1.5, amp) + 50.0 + rng.normal(0.0, 5.0, shape)
    return image, centres, index


def test_hot_pixels_are_not_spots(rng):
    image, centres, _ = _square_image(rng)
    # single-pixel spikes, brighter than any spot: one in the gap between four spots, one in
    # the empty margin right of the lattice (there it is a candidate, rejected by its size)
    gap = np.rint(centres[20] + 0.5 * np.array([15.0, 15.0])).astype(int)
    lone = np.array([100, 223])
    for r, c in (gap, lone):
        image[r, c] = 5000.0
    spots = detect_spots(image, expected_pitch_px=15.0)
    assert len(spots) == len(centres)
    for hot in (gap, lone):
        assert np.min(np.hypot(*(spots.centres_px - hot).T)) > 5.0
    assert np.min(np.hypot(*(spots.rejected_px - lone).T)) < 0.5
    lattice = fit_lattice(spots)
    assert lattice.n_missing == 0
    assert np.array_equal(lattice.inlier, (lattice.flags & SpotFlag.EDGE) == 0)


def test_dust_dimmed_spot_is_flagged_and_keeps_its_index(rng):
    def dim(amp, index):
        amp[(index[:, 0] == 5) & (index[:, 1] == 6)] *= 0.25
        return amp

    image, centres, index = _square_image(rng, extra=dim)
    spots = detect_spots(image, expected_pitch_px=15.0)
    lattice = fit_lattice(spots)
    k, ok = match(lattice.centres_px, centres, 3.0)
    assert ok.all()
    dusty = np.flatnonzero((index[:, 0] == 5) & (index[:, 1] == 6))[0]
    assert lattice.flags[k[dusty]] & SpotFlag.DIM
    assert not lattice.inlier[k[dusty]]
    assert np.array_equal(lattice.grid_index[k], index)
    assert np.count_nonzero(lattice.flags & SpotFlag.DIM) == 1
    assert any(spot == k[dusty] and "dim" in why for spot, _, why in lattice.flagged)


def test_missing_block_is_reported_and_other_indices_unchanged(rng):
    def holes(amp, index):
        # a third of the spots missing in one region: rows 3-9, columns 2-9 (56 of 168)
        amp[(index[:, 0] >= 3) & (index[:, 0] <= 9) & (index[:, 1] >= 2) & (index[:, 1] <= 9)] = 0.0
        return amp

    image, centres, index = _square_image(rng, extra=holes)
    gone = (index[:, 0] >= 3) & (index[:, 0] <= 9) & (index[:, 1] >= 2) & (index[:, 1] <= 9)
    spots = detect_spots(image, expected_pitch_px=15.0)
    lattice = fit_lattice(spots)
    assert len(spots) == np.count_nonzero(~gone)
    k, ok = match(lattice.centres_px, centres[~gone], 3.0)
    assert ok.all()
    assert np.array_equal(lattice.grid_index[k], index[~gone])
    assert lattice.n_missing == np.count_nonzero(gone)
    assert {tuple(ij) for ij in lattice.missing_index} == {tuple(ij) for ij in index[gone]}
    # the fraction is taken over the complete lattice positions (window inside the image)
    n_complete = np.count_nonzero((lattice.flags & SpotFlag.EDGE) == 0) + 56
    assert lattice.missing_fraction == pytest.approx(56 / n_complete)
    with pytest.raises(
        CalibrationError,
        match=rf"56 of {n_complete} lattice positions .* missing grid indices \(3, 2\)",
    ):
        fit_lattice(spots, max_missing_fraction=0.2)


def test_partial_edge_lenslets_are_flagged_and_indexed(rng):
    # the lattice overruns the image: the outer spots are cut by the edges
    centres, index = lattice_points(
        grid="square", n_rows=12, n_cols=14, pitch=15.0, rotation=0.03, origin=(3.0, 2.0)
    )
    shape = (160, 190)
    image = render(shape, centres, 1.5, 1000.0) + rng.normal(0.0, 5.0, shape)
    spots = detect_spots(image, expected_pitch_px=15.0)
    lattice = fit_lattice(spots)
    radius = spots.window_radius_px
    inside = (
        (centres[:, 0] - radius >= -0.5)
        & (centres[:, 0] + radius <= shape[0] - 0.5)
        & (centres[:, 1] - radius >= -0.5)
        & (centres[:, 1] + radius <= shape[1] - 0.5)
    )
    k, ok = match(lattice.centres_px, centres, 15.0 / 2)
    found = ok & (np.hypot(*(lattice.centres_px[k] - centres).T) < 15.0 / 2)
    # every complete lenslet is found, not flagged EDGE, and correctly indexed
    assert found[inside].all()
    assert not np.any(lattice.flags[k[inside]] & SpotFlag.EDGE)
    offset = (lattice.grid_index[k[inside]] - index[inside])[0]
    assert np.array_equal(lattice.grid_index[k[found]] - offset, index[found])
    # the partial ones that were detected carry EDGE and are not in the fit
    partial = found & ~inside
    assert partial.any()
    assert np.all(lattice.flags[k[partial]] & SpotFlag.EDGE)
    assert not lattice.inlier[k[partial]].any()
    assert lattice.n_missing == 0


# ----------------------------------------------------------------------------------------------
# Bad images and bad options
# ----------------------------------------------------------------------------------------------


def test_nan_pixels(rng):
    image, _, _ = _square_image(rng)
    image[7, 9] = np.nan
    image[50, 3] = np.nan
    with pytest.raises(ImageError, match=r"2 non-finite pixels .* \(row 7, col 9\)"):
        detect_spots(image)


@pytest.mark.parametrize(
    "image, message",
    [
        (np.zeros((64, 64), np.uint8), "all dark"),
        (np.full((64, 64), 7.0), "constant"),
        (np.ones((4, 4, 4)), "must be 2-D"),
        (np.ones((64, 64, 3)), "colour image"),
        (np.ones((64, 64), complex), "dtype complex128"),
        (np.ones((64, 64), bool), "dtype bool"),
        (np.ones((5, 64)), "too small"),
    ],
)
def test_unusable_images(image, message):
    with pytest.raises(ImageError, match=message):
        detect_spots(image)


def test_saturated_image(rng):
    image, _, _ = _square_image(rng, amplitude=200.0)
    img8 = np.clip(image, 0, 255).astype(np.uint8)
    img8[:, :30] = 255  # 13 % of the pixels at the uint8 maximum
    with pytest.raises(ImageError, match=r"13\.0 % of the pixels .* saturated at 255"):
        detect_spots(img8)


def test_saturated_spots_are_flagged(rng):
    image, centres, _ = _square_image(rng, amplitude=300.0)
    img8 = np.clip(image, 0, 255).astype(np.uint8)  # spot peaks clipped, < 2 % of pixels
    spots = detect_spots(img8, expected_pitch_px=15.0)
    assert len(spots) == len(centres)
    assert np.all(spots.flags & SpotFlag.SATURATED)


def test_too_few_spots(rng):
    centres, _ = lattice_points(
        grid="square", n_rows=3, n_cols=3, pitch=15.0, rotation=0.0, origin=(10, 10)
    )
    with pytest.raises(
        CalibrationError, match=r"found 9 spots, expected a lattice of at least 4 x 4"
    ):
        fit_lattice(centres)
    centres, _ = lattice_points(
        grid="square", n_rows=2, n_cols=12, pitch=15.0, rotation=0.0, origin=(10, 10)
    )
    with pytest.raises(CalibrationError, match=r"2 x 12 lenslets; expected at least 4 x 4"):
        fit_lattice(centres)


def test_random_points_are_not_a_lattice(rng):
    with pytest.raises(CalibrationError, match="do not form a square or hexagonal lattice"):
        fit_lattice(rng.uniform(0, 500, (200, 2)))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(method="peak"),
         r"method must be one of 'auto', 'window', 'shape', 'centroid', 'gaussian'; got 'peak'"),
        (dict(background="median"), r"background must be one of 'local', 'none'"),
        (dict(grid="triangular"), r"grid must be one of 'square', 'hexagonal'"),
        (dict(threshold=1.5), r"threshold must satisfy 0 <= threshold < 1"),
        (dict(detection_threshold=0.0), r"detection_threshold must satisfy"),
        (dict(expected_pitch_px=2.0), r"expected_pitch_px must be a finite number >= 3 px"),
        (dict(expected_pitch_px=15.0, window_radius_px=20.0), r"window_radius_px must satisfy"),
    ],
)
def test_invalid_options(rng, kwargs, message):
    image, _, _ = _square_image(rng)
    with pytest.raises(ValueError, match=message):
        detect_spots(image, **kwargs)


def test_fit_lattice_invalid_options(rng):
    centres, _ = lattice_points(**SQUARE)
    with pytest.raises(ValueError, match=r"grid must be one of 'auto', 'square', 'hexagonal'"):
        fit_lattice(centres, grid="cubic")
    with pytest.raises(ValueError, match=r"shape \(168, 3\)"):
        fit_lattice(np.zeros((168, 3)))
    with pytest.raises(
        CalibrationError, match=r"median spot spacing is 15.00 px; expected about 30.00 px"
    ):
        fit_lattice(centres, expected_pitch_px=30.0)


def test_estimate_pitch(rng):
    for spec in (SQUARE, HEX):
        centres, _ = lattice_points(**spec)
        image = render((220, 240), centres, 1.5, 1000.0) + rng.normal(0, 5.0, (220, 240))
        # the integer-lag autocorrelation peak with a parabolic refinement: within 2 %
        assert estimate_pitch(image) == pytest.approx(spec["pitch"], rel=0.02)


def test_results_are_frozen(rng):
    image, _, _ = _square_image(rng)
    spots = detect_spots(image)
    lattice = fit_lattice(spots)
    with pytest.raises(dataclasses.FrozenInstanceError):
        spots.pitch_px = 3.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        lattice.grid = "hexagonal"
    with pytest.raises(ValueError):
        spots.centres_px[0, 0] = 1.0
    with pytest.raises(ValueError):
        lattice.basis[0, 0] = 1.0
    assert isinstance(spots, SpotSet) and isinstance(lattice, Lattice)
    with pytest.raises(ValueError, match="integer array of shape"):
        lattice.predict([[0.5, 1.0]])


# ----------------------------------------------------------------------------------------------
# Numba kernels against their NumPy twins
# ----------------------------------------------------------------------------------------------

REFINERS = [K.centroid_refine_numba, K.centroid_refine_numpy]
GAUSS_FITS = [K.gaussian_fit_numba, K.gaussian_fit_numpy]


@pytest.mark.parametrize("refine", REFINERS, ids=["numba", "numpy"])
def test_centroid_engine_finds_a_symmetric_spot(refine):
    centre = np.array([[20.37, 18.81]])
    image = render((40, 40), centre, 2.0, 100.0)
    out, intensity, area, peak = refine(image, np.array([[20.0, 19.0]]), 8.0, 0.1, 20, 1e-6)
    assert np.allclose(out, centre, atol=0.01)
    assert intensity[0] > 0 and peak[0] > 0
    # effective area of a thresholded Gaussian: about 4 sigma^2 (module docstring)
    assert 0.7 * 4 * 2.0**2 < area[0] < 1.3 * 4 * 2.0**2


@pytest.mark.parametrize("fit", GAUSS_FITS, ids=["numba", "numpy"])
def test_gaussian_engine_recovers_parameters(fit):
    y, x = np.mgrid[0:30, 0:30]
    image = 80.0 * np.exp(-((y - 14.3) ** 2 + (x - 15.6) ** 2) / (2 * 1.7**2)) + 5.0
    p = fit(image, np.array([[14.0, 16.0]]), np.array([1.2]), 7.0, 50)
    assert np.allclose(p[0], [80.0, 14.3, 15.6, 1.7, 5.0], atol=1e-6)


def test_centroid_kernel_matches_numpy_twin(rng):
    image = render((120, 130), rng.uniform(5, 115, (40, 2)), 1.8, 100.0) + rng.normal(
        0, 2.0, (120, 130)
    )
    image[0:3, 0:3] = 400.0  # a bright corner, to exercise the image edge
    start = np.vstack([rng.uniform(-2, 125, (60, 2)), [[0.0, 0.0], [119.0, 129.0]]])
    for radius, thr in ((4.0, 0.1), (6.5, 0.0), (3.2, 0.3)):
        a = K.centroid_refine_numba(image.astype(np.float32), start, radius, thr, 20, 1e-4)
        b = K.centroid_refine_numpy(image.astype(np.float32), start, radius, thr, 20, 1e-4)
        for x, y in zip(a, b, strict=True):
            assert np.array_equal(np.isnan(x), np.isnan(y))
            assert np.allclose(x, y, rtol=1e-9, atol=1e-7, equal_nan=True)


def test_gaussian_kernel_matches_numpy_twin(rng):
    truth = rng.uniform(8, 92, (30, 2))
    image = render((100, 100), truth, 1.6, 200.0) + rng.normal(0, 3.0, (100, 100))
    start = truth + rng.normal(0, 0.3, truth.shape)
    sigma0 = np.full(len(start), 1.2)
    a = K.gaussian_fit_numba(image, start, sigma0, 5.0, 50)
    b = K.gaussian_fit_numpy(image, start, sigma0, 5.0, 50)
    assert np.array_equal(np.isnan(a), np.isnan(b))
    assert np.allclose(a, b, rtol=1e-7, atol=1e-7, equal_nan=True)


# ----------------------------------------------------------------------------------------------
# Third-party reference images
# ----------------------------------------------------------------------------------------------


def _data(*parts):
    return shared_data_path(*parts)


def _read_png(path):
    from skimage.io import imread

    return imread(path)


@pytest.fixture(scope="module")
def plenopticam():
    """Detection and lattice of PlenoptiCam's reference spot images, computed once."""
    cache = {}

    def get(name):
        if name not in cache:
            image = _read_png(_data("plenopticam_spots", f"{name}.png"))
            truth = np.loadtxt(_data("plenopticam_spots", f"{name}.txt"))
            spots = detect_spots(image)
            cache[name] = (image, truth, spots, fit_lattice(spots))
        return cache[name]

    return get


PLENOPTICAM = [("b", "hexagonal"), ("c", "hexagonal"), ("d", "square")]


@pytest.mark.data
@pytest.mark.parametrize("name, grid", PLENOPTICAM)
def test_plenopticam_every_complete_spot_found(plenopticam, name, grid):
    image, truth, spots, lattice = plenopticam(name)
    n_rows, n_cols = image.shape
    radius, pitch = spots.window_radius_px, spots.pitch_px
    # "complete": the spot's window (radius window_radius_px) lies inside the image. A truth
    # spot closer than 0.5 px to that limit may go either way, so it is left out here.
    margin = 0.5
    complete = (
        (truth[:, 0] - radius - margin >= -0.5)
        & (truth[:, 0] + radius + margin <= n_rows - 0.5)
        & (truth[:, 1] - radius - margin >= -0.5)
        & (truth[:, 1] + radius + margin <= n_cols - 0.5)
    )
    k, ok = match(spots.centres_px, truth[complete], pitch / 4)
    assert ok.all(), f"{np.count_nonzero(~ok)} complete spots of {name} not found"
    assert not np.any(lattice.flags[k] & SpotFlag.EDGE)
    # and nothing complete was found where there is no spot
    found_complete = (lattice.flags & SpotFlag.EDGE) == 0
    _, real = match(truth, spots.centres_px[found_complete], pitch / 4)
    assert real.all()
    assert lattice.grid == grid
    assert lattice.n_missing == 0
    # every spot, the partial ones included, carries the index of a real lenslet: the lattice
    # position of its index is a listed centre (to the lattice's own accuracy), never twice
    dist, _ = cKDTree(truth).query(lattice.predict(lattice.grid_index))
    assert dist.max() < 0.05
    assert len({tuple(ij) for ij in lattice.grid_index}) == len(spots)


@pytest.mark.data
@pytest.mark.parametrize("name, grid", PLENOPTICAM)
def test_plenopticam_rotation_and_pitch_match_the_truth_lattice(plenopticam, name, grid):
    _, truth, _, lattice = plenopticam(name)
    true_lattice = fit_lattice(truth)
    assert true_lattice.grid == grid and true_lattice.rms_residual_px < 1e-9
    # the fitted parameters scatter with the per-spot noise: 5 standard errors
    assert abs(lattice.rotation_rad - true_lattice.rotation_rad) < 5 * lattice.rotation_std_rad
    assert np.all(np.abs(lattice.pitch_px - true_lattice.pitch_px) < 5 * lattice.pitch_std_px)
    expected_deg = {"b": 0.0, "c": 1.0, "d": -2.0}[name]  # the README's "about 1 deg / 2 deg"
    assert np.degrees(lattice.rotation_rad) == pytest.approx(expected_deg, abs=0.05)


@pytest.mark.data
@pytest.mark.parametrize("name", ["b", "c", "d"])
def test_plenopticam_centre_accuracy(plenopticam, name):
    image, truth, spots, lattice = plenopticam(name)
    pitch = spots.pitch_px
    # PlenoptiCam renders the first complete row and column of c and d about 1.2 px away
    # from their listed centres (its micro-image boxes are clipped at the border; the
    # lattice flags them as outliers, see the next test): accuracy is measured on spots at
    # least one pitch inside the border.
    n_rows, n_cols = image.shape
    interior = np.all((truth >= pitch) & (truth <= np.array([n_rows, n_cols]) - 1 - pitch), axis=1)
    k, ok = match(spots.centres_px, truth[interior], pitch / 4)
    assert ok.all()
    err = spots.centres_px[k] - truth[interior]
    rms = np.sqrt(np.mean(err**2, axis=0))
    bias = err.mean(axis=0)
    # mean bias: 0.02 px per axis (the brief), and within 5 standard errors of the mean
    assert np.all(np.abs(bias) < 0.02)
    assert np.all(np.abs(bias) < 5 * rms / np.sqrt(len(err)) + 0.005)
    # per-spot rms: the truth is an exact lattice, so the lattice residual measures the same
    # random scatter as the error against the truth; they must agree (20 %) ...
    inl = lattice.inlier[k]
    res_rms = np.sqrt(np.mean(lattice.residual_px[k][inl] ** 2, axis=0))
    assert np.allclose(rms, res_rms, rtol=0.2)
    # ... and beat the plain thresholded centroid (0.11-0.17 px rms, data README) clearly
    assert np.all(rms < 0.1)
    # no worse than documented in detect_spots (issue #10 keeps these): "auto" takes the
    # thresholded centroid for micro-images that fill their cell
    assert spots.method == "centroid"
    assert np.all(rms <= {"b": (0.041, 0.042), "c": (0.068, 0.059), "d": (0.049, 0.049)}[name])
    if name == "b":  # large, bright micro-images: the 0.05 px rms target per spot holds
        assert np.all(rms < 0.05)
    # the calibration product, the fitted lattice, averages the noise of thousands of spots
    pred = lattice.predict(lattice.grid_index[k]) - truth[interior]
    assert np.all(np.sqrt(np.mean(pred**2, axis=0)) < 0.05)
    assert np.all(np.abs(pred.mean(axis=0)) < 0.02)


@pytest.mark.data
@pytest.mark.parametrize("name", ["b", "c", "d"])
def test_plenopticam_outliers_are_the_border_artefacts(plenopticam, name):
    image, _, spots, lattice = plenopticam(name)
    out = (lattice.flags & SpotFlag.OUTLIER) != 0
    c = lattice.centres_px[out]
    dist = np.min(np.column_stack([c, np.array(image.shape) - 1 - c]), axis=1)
    assert np.all(dist < 1.5 * spots.pitch_px)
    assert np.count_nonzero(out) < 0.01 * len(spots)


def _profile_pitch(profile, pitch, first):
    """Pitch (px) and its standard error from a 1-D profile: sub-pixel peak centroids, line fit."""
    h = int(pitch // 2)
    peaks = []
    k = 0
    while True:
        guess = first + k * pitch
        lo, hi = int(round(guess)) - h, int(round(guess)) + h + 1
        if hi > len(profile):
            break
        if lo >= 0:
            seg = profile[lo:hi] - profile[lo:hi].min()
            x = np.arange(lo, hi)
            peaks.append((k, np.sum(seg * x) / np.sum(seg)))
        k += 1
    k, p = np.array(peaks).T
    coef, cov = np.polyfit(k, p, 1, cov=True)
    return coef[0], np.sqrt(cov[0, 0])


@pytest.fixture(scope="module")
def white():
    image = _read_png(_data("plenoptomos_letters_ULF", "letters_ULF_M1_white.png"))
    spots = detect_spots(image)
    return image, spots, fit_lattice(spots)


def _documented_offsets(lattice, axis, a, p):
    """Fitted minus documented position of each lattice row (axis 0) or column (axis 1), px.

    The documented grid ``a + p (k + 1/2)`` is unrotated, so each fitted row (column) is
    represented by the mean position of its complete spots.
    """
    complete = (lattice.flags & SpotFlag.EDGE) == 0
    fitted = lattice.predict(lattice.grid_index)
    out = []
    for k in np.unique(lattice.grid_index[complete, axis]):
        mean = fitted[complete & (lattice.grid_index[:, axis] == k), axis].mean()
        kd = np.rint((mean - a) / p - 0.5)
        out.append(mean - (a + p * (kd + 0.5)))
    return np.array(out)


@pytest.mark.data
def test_plenoptomos_white_image(white):
    image, spots, lattice = white
    assert image.shape == (960, 1280)
    assert lattice.grid == "square"
    assert lattice.n_missing == 0
    assert lattice.rms_residual_px < 0.2
    # an independent sub-pixel estimate from the row and column sums of the image must give
    # the same pitch within 4 combined standard errors
    pitch = lattice.pitch_px
    for axis in (0, 1):
        first = lattice.predict(np.array([[1, 1]]))[0, axis]
        prof_pitch, prof_std = _profile_pitch(
            image.sum(axis=1 - axis).astype(float), pitch[axis], first
        )
        assert abs(prof_pitch - pitch[axis]) < 4 * np.hypot(prof_std, lattice.pitch_std_px[axis])
    # documented column pitch 48.2273 px and column centres col_k = 30.0504 + 48.2273 (k + 1/2)
    assert pitch[1] == pytest.approx(48.2273, abs=0.02)
    assert np.all(np.abs(_documented_offsets(lattice, 1, 30.0504, 48.2273)) < 0.5)
    # rotation "about -2 mrad" in the source's y-up view; here (CCW in x = col, y = row) the
    # rows of lenslets descend to the right, a positive angle of a few mrad
    assert 1e-3 < lattice.rotation_rad < 4e-3


@pytest.mark.data
@pytest.mark.xfail(
    reason="the documented row pitch 48.20 px is 0.034 px per lenslet shorter than both the "
    "lattice fit (48.2346 +- 0.0005) and a sub-pixel projection estimate (48.2335); the source "
    "took it from integer peak positions. The documented rows then drift from -0.81 to -0.22 px "
    "off the fit.",
    strict=True,
)
def test_plenoptomos_white_image_documented_rows(white):
    _, _, lattice = white
    assert lattice.pitch_px[0] == pytest.approx(48.20, abs=0.02)
    assert np.all(np.abs(_documented_offsets(lattice, 0, 46.0125, 48.2)) < 0.5)
