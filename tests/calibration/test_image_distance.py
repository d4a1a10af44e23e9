"""Image distance: focal-point fit (with MLA misplacement and substrate), magnification method,
lens corrections. Synthetic images come from the project's ray tracer."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plenopiv.calibration.image_distance import (
    SpotModel,
    find_ruler_ticks,
    fit_focal_points,
    fit_linear_correction,
    fit_pupil_correction,
    index_ticks,
    lenslet_integral_image,
    magnification_from_ticks,
)
from plenopiv.camera import optics
from plenopiv.camera.model import Substrate
from plenopiv.conventions import pixel_to_sensor
from plenopiv.errors import CalibrationError
from plenopiv.synthetic.images import Ruler, focal_point_image, ruler_image
from synthetic.test_images import predicted_spots, spot_centroids

OFFSET, ROTATION = (3e-6, -2e-6), 2e-4


def misplaced(camera, si, plate=None, back_side="physical"):
    mla = dataclasses.replace(camera.microlens_array, substrate=plate, back_side=back_side,
                              offset=OFFSET, rotation=ROTATION)
    return camera.replace(microlens_array=mla).with_image_distance(si)


def measured_spots(cam, rng=None, noise_px=0.0):
    img = focal_point_image(cam, f_number=16, pupil_across=7, cell_across=1)
    got = spot_centroids(img, predicted_spots(cam))
    if noise_px:
        got = got + rng.uniform(-noise_px, noise_px, got.shape)
    return pixel_to_sensor(got, cam.sensor.shape, cam.sensor.pixel_pitch)


@pytest.mark.parametrize("si", [0.136, 0.2025, 0.27, 0.3375, 0.405])
def test_focal_point_fit_recovers_si_offset_rotation(auburn_camera, si):
    """Thesis Fig. 3.8: S_i from 135 to 405 mm (no noise): |error| ≤ 0.01 mm."""
    cam = misplaced(auburn_camera, si)
    fit = fit_focal_points(cam.microlens_array.nominal_centres(), measured_spots(cam),
                           SpotModel.from_camera(cam))
    assert abs(fit.image_distance - si) <= 1e-5
    assert np.abs(fit.offset - OFFSET).max() <= 0.1e-6
    assert abs(fit.rotation - ROTATION) <= 10e-6
    assert fit.rms_residual < 1e-3 * cam.sensor.pixel_pitch


@pytest.mark.parametrize("si", [0.136, 0.27, 0.405])
def test_focal_point_fit_with_one_pixel_noise(auburn_camera, rng, si):
    """Thesis Fig. 3.9 / Table 5.3: uniform ±1 px noise on every spot.

    Least squares cannot beat σ_S = S_i²/f̄ · σ_p/√(Σ|d|²) (σ_p = 1/√3 px): 0.05 mm at
    136 mm, 0.21 mm at 270 mm, 0.47 mm at 405 mm for the Auburn camera. The fit must reach
    that bound, report it as its own σ, and stay within 3σ.
    """
    cam = misplaced(auburn_camera, si)
    nominal = cam.microlens_array.nominal_centres()
    fit = fit_focal_points(nominal, measured_spots(cam, rng, noise_px=1.0),
                           SpotModel.from_camera(cam))
    sigma_p = cam.sensor.pixel_pitch / np.sqrt(3)
    bound = si ** 2 / 500e-6 * sigma_p / np.sqrt((nominal ** 2).sum())
    assert fit.sigma_image_distance == pytest.approx(bound, rel=0.1)
    assert abs(fit.image_distance - si) <= 3 * bound
    if si < 0.2:
        assert abs(fit.image_distance - si) <= 0.3e-3
    # uniform ±1 px noise has σ = 1/√3 px per axis; the rms residual must say so
    assert fit.rms_residual / cam.sensor.pixel_pitch == pytest.approx(1 / np.sqrt(3), rel=0.03)


@pytest.mark.parametrize("plate", [Substrate(6.3e-3, 1.46), Substrate(10.4e-3, 1.517)])
def test_thesis_back_side_needs_the_plate_model(auburn_camera, plate):
    """Thesis Fig. 5.5: with the in-glass back side, the model without the plate overestimates
    S_i (by about n), the plate model (Eq. 4.8) is right."""
    si = 0.2
    cam = misplaced(auburn_camera, si, plate=plate, back_side="thesis")
    spots = measured_spots(cam)
    nominal = cam.microlens_array.nominal_centres()
    right = fit_focal_points(nominal, spots, SpotModel.from_camera(cam))
    naive = fit_focal_points(nominal, spots, SpotModel.from_camera(cam, ignore_substrate=True))
    # the in-glass slope is not linear across the f/16 stop, so a spot's centroid sits up to
    # 3e-4 px from its chief ray at the field edge: a 0.02 mm bias, within the thesis's 0.05 mm
    assert abs(right.image_distance - si) <= 0.05e-3
    n, t = plate.refractive_index, plate.thickness
    assert naive.image_distance == pytest.approx(n * (si - t / n) + t, rel=5e-3)
    assert naive.image_distance > 1.3 * si


def test_physical_back_side_is_insensitive_to_the_plate(auburn_camera):
    """With the lenslets on the sensor side, the spots depend on S_i,eff only (Eq. 3.11)."""
    cam = misplaced(auburn_camera, 0.2, plate=Substrate(10.4e-3, 1.517))
    spots = measured_spots(cam)
    nominal = cam.microlens_array.nominal_centres()
    fit = fit_focal_points(nominal, spots, SpotModel.from_camera(cam))
    naive = fit_focal_points(nominal, spots, SpotModel.from_camera(cam, ignore_substrate=True))
    assert abs(fit.image_distance - 0.2) <= 1e-5
    assert abs(naive.image_distance - 0.2) <= 0.1e-3       # only non-paraxial terms differ


def test_focal_point_fit_rejects_unusable_input():
    d = np.array([[0, 0], [1e-3, 0]], float)
    with pytest.raises(CalibrationError, match="at least"):
        fit_focal_points(d, d, SpotModel(500e-6))
    d = np.random.default_rng(0).uniform(-1e-2, 1e-2, (50, 2))
    with pytest.raises(CalibrationError, match="not spread out"):
        fit_focal_points(d, d * 0.9, SpotModel(500e-6))


def test_magnification_method_within_its_uncertainty(small_camera):
    for si in (0.2, 0.3):
        cam = small_camera.with_image_distance(si)
        img = ruler_image(cam, Ruler(spacing=1e-3, tick_width=0.15e-3), rays_per_lenslet=1000)
        mla = cam.microlens_array
        integ = lenslet_integral_image(img, predicted_spots(cam), mla.grid_index(), cam.pitch_px)
        profile = integ[mla.rows // 2 - 3: mla.rows // 2 + 4].mean(axis=0)
        ticks = index_ticks(find_ruler_ticks(profile)) * mla.pitch
        res = magnification_from_ticks(ticks, 1e-3, cam.main_lens.focal_length,
                                       cam.main_lens.f_number, mla.pitch)
        assert abs(res.image_distance - si) <= res.sigma_image_distance
        assert res.magnification == pytest.approx(cam.magnification, rel=0.01)
        assert res.object_distance == pytest.approx(
            optics.conjugate_distance(cam.main_lens.focal_length, res.image_distance))


def test_ruler_without_ticks_is_an_error():
    with pytest.raises(CalibrationError, match="ruler ticks"):
        find_ruler_ticks(np.ones(40))


def test_linear_correction_reproduces_thesis_constants():
    """Table 5.4 trends (known - computed = s·known + c) give Eqs. 5.3 and 5.4."""
    for slope, icpt, a, b in ((0.5149, -39.734e-3, 2.0614, -81.9089e-3),
                              (0.5309, -22.236e-3, 2.1317, -47.4014e-3)):
        known = np.linspace(0.06, 0.25, 9)
        computed = known - (slope * known + icpt)
        corr = fit_linear_correction(computed, known)
        assert corr.a == pytest.approx(a, abs=2e-4)
        assert corr.b == pytest.approx(b, abs=0.02e-3)
        assert np.allclose(corr.apply(computed), known)


def test_pupil_model_recovers_exit_pupil_and_camera_constant(small_camera):
    """Simulated extension-tube series with an exit pupil 25 mm behind the principal plane
    and f̄ = 520 µm: the uncorrected method is biased, the pupil model is right."""
    e, fbar, si0 = 25e-3, 520e-6, 0.145
    tubes = np.array([0.0, 12e-3, 24e-3, 48e-3, 76e-3, 100e-3])
    lens = dataclasses.replace(small_camera.main_lens, exit_pupil_offset=e)
    mla = dataclasses.replace(small_camera.microlens_array, sensor_distance=fbar)
    base = small_camera.replace(main_lens=lens, microlens_array=mla)
    scales, naive = [], []
    for dl in tubes:
        cam = base.with_image_distance(si0 + dl)
        spots = measured_spots(cam)
        centres = cam.microlens_array.nominal_centres()
        # what a user without the pupil model does: thin lens at z = 0, nominal f̄ = 500 µm
        fit = fit_focal_points(centres, spots, SpotModel(500e-6), fit_misplacement=False,
                               model="paraxial")
        naive.append(fit.image_distance)
        scales.append(optics.focal_spot_scale(fit.image_distance, 500e-6))
    naive = np.array(naive)
    assert np.abs(naive - (si0 + tubes)).max() > 5e-3        # biased by millimetres
    model = fit_pupil_correction(scales, tubes, base_image_distance=si0)
    assert model.sensor_distance == pytest.approx(fbar, rel=1e-4)
    assert model.pupil_distance == pytest.approx(si0 - e, rel=1e-4)
    assert model.pupil_offset == pytest.approx(e, abs=0.02e-3)
    assert np.allclose(model.image_distance(scales), si0 + tubes, atol=0.02e-3)
