"""Calibration on realistic calibration images: black level, fixed pattern, hot pixels,
lenslet throughput, vignetting inside the micro-images, read noise; with and without a dark
frame.

The ideal focal-point render of the 50 mm preset (a 97 x 143-lenslet patch) is recorded by a
NumPy sensor model (:class:`Sensor`). Each effect alone, and all together, must leave S_i
within what the noise allows: the photon-noise bound :func:`photon_bound` propagates the
photon and read noise of every pixel of each spot's centre window to the spot centres, and
those through the focal-spot scale p = k d to S_i. Four standard deviations of it is the
limit (a false alarm once in 16,000 runs).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from plenopiv.calibration import defects
from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.spot_detection import detect_spots
from plenopiv.camera.model import load_camera
from plenopiv.camera.optics import focal_spot_exact
from plenopiv.conventions import sensor_to_pixel
from plenopiv.errors import ImageError
from plenopiv.synthetic.images import focal_point_image

SI = 0.101                  # the truth; the camera file says 100 mm
FULL, FULL_WELL = 4095, 20000.0     # a 12-bit sensor, 20,000 e- at full scale
PEAK = 0.25                  # the brightest spot pixel at a quarter of full scale


@dataclasses.dataclass(frozen=True)
class Sensor:
    """A sensor's fixed defects and its noise, counts (DN) of a 12-bit sensor.

    ``black`` holds the black level with its fixed pattern (column, row, pixel), ``hot`` the
    dark signal of the hot pixels; every recording adds photon noise (``FULL_WELL`` electrons
    at full scale) and Gaussian read noise ``read``, and is rounded and clipped.
    """

    black: np.ndarray
    hot: np.ndarray
    read: float

    @classmethod
    def make(cls, shape, rng, *, offset=300.0, column=0.0, row=0.0, pixel=0.0, hot=0.0,
             read=4.0):
        black = (offset + rng.normal(0, column, shape[1])[None, :]
                 + rng.normal(0, row, shape[0])[:, None] + rng.normal(0, pixel, shape))
        hot_map = np.zeros(shape)
        n = int(hot * hot_map.size)
        idx = rng.choice(hot_map.size, n, replace=False)
        hot_map.ravel()[idx] = rng.uniform(0.05, 1.0, n) * FULL
        return cls(black, hot_map, read)

    def record(self, counts, rng):
        e = FULL_WELL / FULL
        x = rng.poisson(np.clip(counts, 0, None) * e) / e + self.black + self.hot
        x = x + rng.normal(0.0, self.read, x.shape)
        return np.clip(np.rint(x), 0, FULL).astype(np.uint16)

    def dark(self, rng):
        return self.record(np.zeros(self.black.shape), rng)


def spots_px(camera, si):
    """The true focal spots (chief rays) and lenslet centres, ``(row, col)`` px."""
    mla, shape, pp = camera.microlens_array, camera.sensor.shape, camera.sensor.pixel_pitch
    spots = focal_spot_exact(mla.centres(), si, mla.sensor_distance)
    return sensor_to_pixel(spots, shape, pp), sensor_to_pixel(mla.centres(), shape, pp)


def lenslet_effects(irr, camera, rng, *, throughput=0.0, vignetting=0.0, si=SI):
    """Irradiance with each lenslet's throughput (uniform within ±``throughput``) and the
    micro-images falling off to ``1 - vignetting`` at half a pitch from their centres."""
    spots, _ = spots_px(camera, si)
    rr, cc = np.indices(irr.shape)
    _, owner = cKDTree(spots).query(np.column_stack([rr.ravel(), cc.ravel()]))
    owner = owner.reshape(irr.shape)
    out = irr * (1.0 + rng.uniform(-throughput, throughput, len(spots)))[owner]
    q = ((rr - spots[owner, 0]) ** 2 + (cc - spots[owner, 1]) ** 2) / (camera.pitch_px / 2) ** 2
    return out * np.clip(1.0 - vignetting * q, 0.0, None)


def photon_bound(counts, camera, si, window_px, read_px):
    """Standard deviation of S_i (m) that the photon and read noise allow.

    Each spot's centre is the first moment in a window of radius ``window_px``; its variance
    per axis is sum (x - c)^2 var(x) / F^2 over the window's pixels, var the photon noise of
    the noiseless ``counts`` plus ``read_px`` squared, F the window's signal. The spots are
    p = k d about the axis, so sigma_k = sigma_c / sqrt(sum |d|^2) and sigma_S = sigma_k /
    |dk/dS_i|.
    """
    spots, _ = spots_px(camera, si)
    h = int(np.ceil(window_px))
    dr, dc = np.mgrid[-h:h + 1, -h:h + 1]
    sample = spots[:: max(1, len(spots) // 400)]
    var_c = []
    for r, c in sample:
        r0, c0 = int(round(r)), int(round(c))
        rows, cols = r0 + dr, c0 + dc
        if rows.min() < 0 or cols.min() < 0 or rows.max() >= counts.shape[0] \
                or cols.max() >= counts.shape[1]:
            continue
        inside = np.hypot(rows - r, cols - c) <= window_px
        s = counts[rows, cols][inside]
        var = s * FULL / FULL_WELL + read_px ** 2
        x = (cols - c)[inside]
        var_c.append(np.sum(x * x * var) / np.sum(s) ** 2)
    centre_rc = (np.array(counts.shape) - 1) / 2.0
    d = spots - centre_rc
    sigma_k = np.sqrt(np.mean(var_c)) / np.sqrt(np.sum(d * d))
    mla = camera.microlens_array
    ds = 1e-4
    k = [np.hypot(*focal_spot_exact(np.array([[1e-3, 0.0]]), s, mla.sensor_distance)[0]) / 1e-3
         for s in (si - ds, si + ds)]
    return sigma_k / abs((k[1] - k[0]) / (2 * ds))


@pytest.fixture(scope="module")
def camera():
    return load_camera("auburn_50mm").patch(97, 143)


@pytest.fixture(scope="module")
def ideal(camera):
    """The noiseless focal-point image (f/16, 0.5 px point spread) in counts, and its truth."""
    irr = focal_point_image(camera.with_image_distance(SI), f_number=16, psf_px=0.5)
    return irr * (PEAK * FULL / irr.max())


CASES = {
    "photon noise only": ({}, {}),
    "black level": ({"offset": 300.0}, {}),
    "fixed pattern": ({"offset": 300.0, "column": 12.0, "row": 6.0, "pixel": 3.0}, {}),
    "hot pixels": ({"offset": 300.0, "hot": 5e-4}, {}),
    "throughput": ({"offset": 300.0}, {"throughput": 0.1}),
    "vignetting": ({"offset": 300.0}, {"vignetting": 0.4}),
    "all": ({"offset": 300.0, "column": 12.0, "row": 6.0, "pixel": 3.0, "hot": 5e-4},
            {"throughput": 0.1, "vignetting": 0.4}),
}


@pytest.mark.parametrize("case", list(CASES))
def test_si_within_the_photon_noise_bound(camera, ideal, case):
    sensor_kw, lens_kw = CASES[case]
    rng = np.random.default_rng(11)
    counts = lenslet_effects(ideal, camera, rng, **lens_kw) if lens_kw else ideal
    read = 0.0 if case == "photon noise only" else 4.0
    sensor = Sensor.make(ideal.shape, rng, read=read, **sensor_kw)
    rep = calibrate(camera, sensor.record(counts, rng))
    spots = rep.focal_spots
    pixel_noise = np.hypot(read, sensor_kw.get("pixel", 0.0))
    bound = photon_bound(counts, camera, SI, spots.moment_radius_px, pixel_noise)
    err = rep.focal_fit.image_distance - SI
    assert spots.method == "window"
    assert abs(err) <= 4 * bound, (case, err * 1e3, bound * 1e3)
    # the fit's own uncertainty tells the truth about it
    assert 0.5 * bound <= rep.focal_fit.sigma_image_distance <= 2.0 * bound
    assert rep.n_missing <= 0.005 * rep.calibration.n_lenslets


def test_with_the_dark_frame_all_effects_are_within_the_bound(camera, ideal):
    sensor_kw, lens_kw = CASES["all"]
    rng = np.random.default_rng(12)
    counts = lenslet_effects(ideal, camera, rng, **lens_kw)
    sensor = Sensor.make(ideal.shape, rng, read=4.0, **sensor_kw)
    image, dark = sensor.record(counts, rng), sensor.dark(rng)
    rep = calibrate(camera, image, dark=dark)
    # with the dark frame subtracted, its read noise adds to the image's
    bound = photon_bound(counts, camera, SI, rep.focal_spots.moment_radius_px, 4.0 * np.sqrt(2))
    assert abs(rep.focal_fit.image_distance - SI) <= 4 * bound
    assert rep.n_missing <= 0.002 * rep.calibration.n_lenslets
    with pytest.raises(ImageError, match="dark frame has shape"):
        calibrate(camera, image, dark=dark[:-1])


def test_a_hot_pixel_beside_a_spot_does_not_pull_it(rng):
    """A hot pixel 3 px from a spot of 1 px rms radius, as bright as the spot's peak: its
    pull on the window centroid would be ~3 px x 1/(2 pi) = 0.5 px."""
    rr, cc = np.mgrid[0:160, 0:160]
    img = np.zeros((160, 160))
    truth = []
    for r in range(10, 160, 20):
        for c in range(10, 160, 20):
            t = (r + rng.uniform(-0.5, 0.5), c + rng.uniform(-0.5, 0.5))
            truth.append(t)
            img += 1000 * np.exp(-((rr - t[0]) ** 2 + (cc - t[1]) ** 2) / 2.0)
    img += 100 + rng.normal(0, 2, img.shape)
    hot = img.copy()
    hot[70, 73] += 1000                           # beside the spot near (70, 70)
    hot[40, 120] += 3000                          # between spots
    got = detect_spots(hot, expected_pitch_px=20.0)
    ref = detect_spots(img, expected_pitch_px=20.0)
    assert len(got) == len(ref) == 64
    dist, _ = cKDTree(ref.centres_px).query(got.centres_px)
    assert dist.max() < 0.005
    assert {(70, 73), (40, 120)} <= {tuple(p) for p in got.rejected_px.astype(int).tolist()}


def test_fixed_pattern_is_measured_on_the_gaps(camera, ideal, rng):
    """Column and row offsets under the spots: recovered to their noise, 1/sqrt(n) of the
    read noise over the n gap pixels of a line, above smooth terms (the local background's)."""
    sensor = Sensor.make(ideal.shape, rng, offset=300.0, column=12.0, row=6.0, read=4.0)
    image = sensor.record(ideal, rng).astype(np.float32)
    got = defects.fixed_pattern(image, camera.pitch_px)
    col, row = got[0] - got[0].mean(), got[:, 0] - got[:, 0].mean()
    true_col = sensor.black[0] - sensor.black[0].mean()
    true_row = sensor.black[:, 0] - sensor.black[:, 0].mean()

    def high_pass(v):
        return v - np.convolve(v, np.ones(17) / 17, mode="same")

    n_rows, n_cols = image.shape
    for est, true, n in ((col, true_col, n_rows), (row, true_row, n_cols)):
        e = high_pass(est - true)[20:-20]
        assert np.std(e) < 2.0 * 4.0 / np.sqrt(0.5 * n)
    # no pattern: nothing subtracted
    flat = Sensor.make(ideal.shape, rng, offset=300.0, read=4.0).record(ideal, rng)
    assert not defects.fixed_pattern(flat.astype(np.float32), camera.pitch_px).any()


def test_hot_pixels_from_a_dark_frame_and_patching(rng):
    dark = 200 + rng.normal(0, 3, (300, 400))
    hot = rng.random(dark.shape) < 1e-3
    dark[hot] += rng.uniform(60, 3000, hot.sum())
    found = defects.hot_pixels_from_dark(dark)
    assert (found == hot).all()
    img = np.full(dark.shape, 50.0)
    img[hot] = 4000.0
    np.testing.assert_array_equal(defects.patch_pixels(img, found), 50.0)
    with pytest.raises(ImageError, match="mask is 3 × 3"):
        defects.patch_pixels(img, np.zeros((3, 3), bool))


def test_isolated_pixels_are_hot_and_spot_peaks_are_not(rng):
    rr, cc = np.mgrid[0:60, 0:60]
    img = 500 * np.exp(-((rr - 30.3) ** 2 + (cc - 29.8) ** 2) / (2 * 0.75 ** 2))
    img += rng.normal(0, 2, img.shape)
    img[10, 10] = 300.0
    found = defects.isolated_pixels(img, 2.0)
    assert np.argwhere(found).tolist() == [[10, 10]]


@pytest.mark.slow
@pytest.mark.parametrize("preset, si", [("auburn_135mm", 0.202), ("auburn_50mm", 0.101)])
def test_full_presets_with_every_effect(preset, si):
    """The whole 193 x 287-lenslet camera, every effect at once, with and without the dark
    frame: S_i within 4 standard deviations of the photon-noise bound (2-6 µm), far inside
    0.05 mm."""
    cam = load_camera(preset)
    irr = focal_point_image(cam.with_image_distance(si), f_number=16, psf_px=0.5)
    ideal = irr * (PEAK * FULL / irr.max())
    sensor_kw, lens_kw = CASES["all"]
    rng = np.random.default_rng(13)
    counts = lenslet_effects(ideal, cam, rng, si=si, **lens_kw)
    sensor = Sensor.make(ideal.shape, rng, read=4.0, **sensor_kw)
    image = sensor.record(counts, rng)
    for dark, noise in ((None, np.hypot(4.0, 3.0)), (sensor.dark(rng), 4.0 * np.sqrt(2))):
        rep = calibrate(cam, image, dark=dark)
        bound = photon_bound(counts, cam, si, rep.focal_spots.moment_radius_px, noise)
        err = rep.focal_fit.image_distance - si
        assert abs(err) <= min(4 * bound, 0.05e-3), (err * 1e3, bound * 1e3)
