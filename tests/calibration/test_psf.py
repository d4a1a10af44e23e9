"""plenopiv.calibration.psf: the sensor's point spread from the focal-point image's spots, and
the blur the response renders its test images with."""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.model import Calibration
from plenopiv.calibration.psf import point_spread_sigma
from plenopiv.calibration.spot_detection import detect_spots
from plenopiv.synthetic.images import blurred, finish_image, focal_point_image

F_NUMBER = 16.0


@pytest.fixture(scope="module")
def patch(small_camera):
    return small_camera.patch(21, 21)


@pytest.fixture(scope="module")
def sharp(patch):
    return focal_point_image(patch, f_number=F_NUMBER)


def test_the_blur_adds_its_variance_at_any_width():
    """A point blurred by sigma has the variance sigma² per axis (the continuous Gaussian),
    also below a pixel, where a kernel sampled on the pixels adds less."""
    point = np.zeros((64, 64))
    point[32, 32] = 1.0
    r, c = np.mgrid[:64, :64]
    for sigma in (0.3, 0.5, 1.5):
        img = blurred(point, sigma)
        assert img.sum() == pytest.approx(1.0)
        var_c = (img * (c - 32.0) ** 2).sum()
        var_r = (img * (r - 32.0) ** 2).sum()
        assert var_c == pytest.approx(sigma**2, rel=1e-6)
        assert var_r == pytest.approx(sigma**2, rel=1e-6)
    assert np.array_equal(blurred(point, 0.0), point)


@pytest.mark.parametrize("sigma", [0.5, 0.8, 1.2])
def test_the_point_spread_is_measured_whatever_the_noise(patch, sharp, sigma):
    """Spots blurred by sigma (and Poisson noise) give sigma back: the rms radius of a spot
    of about two pixels is measured to a few hundredths of a pixel, so sigma within 0.06 px;
    a sharp image gives less than 0.1 px (the pixels sample its disc the same way)."""
    rng = np.random.default_rng(11)
    img = finish_image(blurred(sharp, sigma), noise="poisson", rng=rng)
    got = point_spread_sigma(patch, detect_spots(img), F_NUMBER)
    assert got == pytest.approx(sigma, abs=0.06)
    spots = detect_spots(finish_image(sharp, noise="poisson", rng=rng))
    assert point_spread_sigma(patch, spots, F_NUMBER) < 0.1
    # the stop of the focal-point image unknown: so is the blur
    assert point_spread_sigma(patch, spots, None) is None


def test_the_calibration_records_the_point_spread(tmp_path, small_camera):
    """Calibrating with the focal-point image's stop records the blur in the product (None
    without the stop), and it survives the file."""
    rng = np.random.default_rng(5)
    truth = small_camera.with_image_distance(0.21)
    fp = finish_image(blurred(focal_point_image(truth, f_number=F_NUMBER), 0.7),
                      noise="poisson", rng=rng)
    cal = calibrate(small_camera, fp, focal_point_f_number=F_NUMBER).calibration
    assert cal.point_spread_sigma_px == pytest.approx(0.7, abs=0.06)
    assert Calibration.load(cal.save(tmp_path / "cal.h5")).point_spread_sigma_px == \
        cal.point_spread_sigma_px
    assert calibrate(small_camera, fp).calibration.point_spread_sigma_px is None
    assert Calibration.from_camera(truth).point_spread_sigma_px is None


@pytest.mark.parametrize("layout", [dict(grid="hexagonal"), dict(rotation=0.02),
                                    dict(grid="hexagonal", rotation=-0.015)],
                         ids=["hexagonal", "rotated", "hexagonal-rotated"])
def test_the_point_spread_of_real_lenslet_arrays(small_camera, layout):
    """Hexagonal and rotated arrays give the blur back as the square one does (their model
    patch holds the shifted rows)."""
    import dataclasses

    mla = dataclasses.replace(small_camera.microlens_array, **layout)
    cam = small_camera.replace(microlens_array=mla).with_image_distance(0.21)
    img = finish_image(blurred(focal_point_image(cam, f_number=F_NUMBER), 0.6), noise="poisson",
                       rng=np.random.default_rng(3))
    spots = detect_spots(img, grid=mla.grid)
    assert point_spread_sigma(cam, spots, F_NUMBER) == pytest.approx(0.6, abs=0.06)
    # and its patch fits its sensor
    patch = cam.patch(15, 15)
    assert patch.microlens_array.extent[0] <= patch.sensor.width


def test_the_point_spread_has_unit_gain_and_ignores_a_sub_pixel_shift(small_camera):
    """Measured against true blur variance over 0.5-1.2 px the slope is 1 (within 5 %) with
    no offset beyond 0.02 px²; moving the lenslet array by a fraction of a pixel on the sensor
    (the spots sample other pixel phases) changes the estimate by under 0.03 px."""
    import dataclasses

    truth = small_camera.with_image_distance(0.21)
    pp = truth.sensor.pixel_pitch
    shifted = truth.replace(microlens_array=dataclasses.replace(
        truth.microlens_array, offset=(0.37 * pp, -0.21 * pp)))
    true, measured = [], []
    for cam in (truth, shifted):
        sharp = focal_point_image(cam, f_number=F_NUMBER)
        for sigma in (0.5, 0.8, 1.2):
            spots = detect_spots(blurred(sharp, sigma))
            measured.append(point_spread_sigma(cam, spots, F_NUMBER))
            true.append(sigma)
    slope, offset = np.polyfit(np.square(true[:3]), np.square(measured[:3]), 1)
    assert slope == pytest.approx(1.0, abs=0.05) and abs(offset) < 0.02
    np.testing.assert_allclose(measured[3:], measured[:3], atol=0.03)
