"""The focal-point calibration on images the project's defaults do not make (issue #10).

Metamorphic tests, independent of any one renderer's exactness: S_i must come out right
whatever the splat, PSF, lenslet count, plate and back side, must not move when the whole
image moves by a sub-pixel amount, and must hold on a renderer written apart from the
project's (``independent_render.py``). One S_i error of 0.01 mm at 405 mm is a spot-lattice
scale error of 3e-8: the spot centres may carry no bias that depends on their sub-pixel phase.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import independent_render
from plenopiv.calibration import _spot_kernels as K
from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.lattice_fit import fit_lattice
from plenopiv.calibration.spot_detection import detect_spots
from plenopiv.camera.model import Substrate
from plenopiv.synthetic.images import finish_image, focal_point_image

IMAGE_DISTANCES = (0.136, 0.2, 0.27, 0.405)
PLATES = {"6.3mm n1.46": Substrate(6.3e-3, 1.46), "10.4mm n1.517": Substrate(10.4e-3, 1.517)}
FAST = dict(splat="bilinear", psf_px=0.5)
# every rendering choice of the simulator for which the spots are not sharper than the pixel
# grid can sample: on a pixel-integrating sensor ("pixel") a spot of 1-2 px needs an optics
# blur of about half a pixel or more (0.5 px on the 40 x 60 camera, 0.7 px on these 20 x 30
# patches, whose fewer phases pin the phase-bias fit less well; docs/validation/
# calibration_study.md gives the limit)
CHOICES = [dict(splat="bilinear", psf_px=0.0), dict(splat="bilinear", psf_px=0.5),
           dict(splat="pixel", psf_px=0.7), dict(splat="pixel", psf_px=1.0)]


def camera(small_camera, si, rows=20, cols=30, *, plate=None, back_side="physical"):
    """A rows x cols patch of the Auburn optics at S_i,eff = si (no plate by default)."""
    mla = dataclasses.replace(small_camera.microlens_array, substrate=plate,
                              back_side=back_side)
    cam = small_camera.replace(microlens_array=mla).with_image_distance(si)
    return cam.patch(rows, cols, margin_px=12)


def si_error_mm(cam, image, **kw):
    """S_i error (mm) of calibrating ``cam`` from its f/16 focal-point image."""
    fit = calibrate(cam, image, focal_point_f_number=16, **kw).focal_fit
    return (fit.image_distance - cam.image_distance) * 1e3, fit


def _id(choice):
    return f"{choice['splat']}-psf{choice['psf_px']}"


# ---- every rendering choice, even and odd lenslet counts ---------------------------------------

CASES = [pytest.param(c, n, marks=() if c == FAST else pytest.mark.slow,
                      id=f"{_id(c)}-{n[0]}x{n[1]}")
         for c in CHOICES for n in ((20, 30), (21, 31))]


@pytest.mark.parametrize("choice, lenslets", CASES)
def test_si_within_0p01_mm_for_every_rendering_choice(small_camera, choice, lenslets):
    for si in IMAGE_DISTANCES:
        cam = camera(small_camera, si, *lenslets)
        img = focal_point_image(cam, f_number=16, **choice)
        err, fit = si_error_mm(cam, img)
        assert abs(err) <= 0.01, f"S_i = {si * 1e3:.0f} mm: error {err:+.4f} mm"
        # the spots fit the chief-ray model to far better than the issue's 0.002 px
        assert fit.rms_residual / cam.sensor.pixel_pitch <= 0.002


@pytest.mark.slow
@pytest.mark.parametrize("lenslets", [(40, 60), (41, 61)])
def test_pixel_sensor_with_half_a_pixel_of_blur_on_the_issues_camera(small_camera, lenslets):
    for si in IMAGE_DISTANCES:
        cam = camera(small_camera, si, *lenslets)
        err, _ = si_error_mm(cam, focal_point_image(cam, f_number=16, splat="pixel",
                                                    psf_px=0.5))
        assert abs(err) <= 0.01, f"S_i = {si * 1e3:.0f} mm: error {err:+.4f} mm"


@pytest.mark.parametrize("choice, lenslets", [
    (FAST, (21, 31)), pytest.param(CHOICES[0], (20, 30), marks=pytest.mark.slow),
    pytest.param(CHOICES[2], (21, 31), marks=pytest.mark.slow),
    pytest.param(dict(splat="pixel", psf_px=0.5), (41, 61), marks=pytest.mark.slow)],
    ids=lambda v: _id(v) if isinstance(v, dict) else f"{v[0]}x{v[1]}")
def test_si_does_not_move_with_a_subpixel_shift_of_the_image(small_camera, rng, choice,
                                                              lenslets):
    for si in (0.27, 0.405):
        cam = camera(small_camera, si, *lenslets)
        ref, _ = si_error_mm(cam, focal_point_image(cam, f_number=16, **choice))
        for shift in rng.uniform(-0.5, 0.5, (2, 2)):
            img = focal_point_image(cam, f_number=16, sensor_shift_px=tuple(shift), **choice)
            moved, _ = si_error_mm(cam, img)
            assert abs(moved - ref) <= 0.005, f"shift {shift}: S_i moved {moved - ref:+.4f} mm"


PLATE_CASES = [pytest.param(p, b, marks=() if (p, b) == ("10.4mm n1.517", "thesis") else
                            pytest.mark.slow, id=f"{p}-{b}")
               for p in PLATES for b in ("physical", "thesis")]


@pytest.mark.parametrize("plate, back_side", PLATE_CASES)
def test_both_plates_and_back_sides_within_0p02_mm(small_camera, plate, back_side):
    for si in (0.145, 0.27, 0.405):
        cam = camera(small_camera, si, 21, 31, plate=PLATES[plate], back_side=back_side)
        err, _ = si_error_mm(cam, focal_point_image(cam, f_number=16, **FAST))
        assert abs(err) <= 0.02, f"S_i = {si * 1e3:.0f} mm: error {err:+.4f} mm"


# ---- a renderer written apart from the project's -----------------------------------------------


@pytest.mark.parametrize("plate, back_side, si", [
    (None, "physical", 0.405),
    pytest.param((10.4e-3, 1.517), "physical", 0.2, marks=pytest.mark.slow),
    pytest.param((10.4e-3, 1.517), "thesis", 0.405, marks=pytest.mark.slow),
])
def test_independent_renders(small_camera, plate, back_side, si):
    """The issue's camera (40 x 60 lenslets, f/16, PSF 0.5 px), noiseless, on a renderer that
    samples rays differently (random-turned spiral pupil, random cell points): the error is
    within the renderer's own floor (its ray means against the chief ray), which a thresholded
    centroid missed by up to 1.8 mm."""
    mla = dataclasses.replace(small_camera.microlens_array, rows=40, cols=60, back_side=back_side,
                              substrate=None if plate is None else Substrate(*plate))
    cam = small_camera.replace(microlens_array=mla).with_image_distance(si)
    img, _ = independent_render.render(si_eff=si, plate=plate, back_side=back_side, seed=3)
    err, fit = si_error_mm(cam, img)
    assert abs(err) <= (0.01 if plate is None else 0.02)
    assert fit.rms_residual / cam.sensor.pixel_pitch <= 0.002


@pytest.mark.slow
def test_poisson_noise_error_is_the_fits_own_sigma(small_camera):
    """Photon noise at 0.9 x 4095 counts on the issue's 40 x 60 camera: the error scatters as
    the fit's own sigma says, with an rms within 0.05 mm up to 200 mm. That is the photon
    limit, not the estimator's: the window centroid's variance is within 7 % of the
    Cramer-Rao bound of these spots, and at 270 mm the fit's sigma is itself 0.053 mm
    (docs/validation/calibration_study.md)."""
    for si in (0.145, 0.2, 0.27, 0.405):
        cam = small_camera.with_image_distance(si).patch(40, 60, margin_px=12)
        irr = focal_point_image(cam, f_number=16, psf_px=0.5)
        errs, sig = [], []
        for seed in range(4):
            img = finish_image(irr, noise="poisson", bit_depth=16, full_well=65535.0,
                               peak_fraction=0.9 * 4095 / 65535, rng=np.random.default_rng(seed))
            err, fit = si_error_mm(cam, img)
            errs.append(err)
            sig.append(fit.sigma_image_distance * 1e3)
        errs, sigma = np.array(errs), float(np.mean(sig))
        assert np.sqrt(np.mean(errs ** 2)) <= 2.0 * sigma
        assert abs(errs.mean()) <= 3.0 * sigma / 2.0
        if si <= 0.2:
            assert np.sqrt(np.mean(errs ** 2)) <= 0.05


# ---- the estimator itself: no bias against the sub-pixel phase ---------------------------------


@pytest.mark.parametrize("splat, blurs, limit", [("bilinear", (0.0, 0.5, 1.0), 3e-4),
                                                 ("pixel", (0.5, 1.0), 6e-4)])
@pytest.mark.parametrize("diameter", [1.0, 2.5, 4.0])
def test_window_centroid_has_no_phase_bias(splat, blurs, limit, diameter):
    worst_window, worst_threshold = 0.0, 0.0
    for blur in blurs:
        radius = 1.75 * (diameter / 2 + 2.5 * blur + 0.5) + 0.5
        for phase in np.linspace(0.0, 1.0, 9)[:-1]:
            true = np.array([12.0 + phase, 12.0 + 0.37 * phase])
            img = independent_render.disc_spot(true, diameter, blur, splat)
            got, *_ = K.window_centroid_numba(img, true[None] + 0.2, radius, radius + 0.5,
                                              radius + 2.5, 50, 1e-9)
            worst_window = max(worst_window, float(np.abs(got[0] - true).max()))
            old, *_ = K.centroid_refine_numba(img, true[None] + 0.2, 8.0, 0.1, 20, 1e-4)
            worst_threshold = max(worst_threshold, float(np.abs(old[0] - true).max()))
    assert worst_window <= limit
    # the thresholded centroid (the estimator before) is pulled by 0.004-0.03 px
    assert worst_threshold > 10 * worst_window


def test_window_centroid_ignores_a_background_plane(rng):
    true = np.array([12.31, 11.77])
    spot = independent_render.disc_spot(true, 3.0, 0.5, "bilinear") * 1000.0
    rr, cc = np.indices(spot.shape)
    img = spot + 50.0 + 3.0 * (rr - 12) - 2.0 * (cc - 12)
    got, flux, bg = K.window_centroid_numba(img, true[None] + 0.3, 4.5, 5.0, 7.0, 50, 1e-10)
    assert np.allclose(got[0], true, atol=1e-6)
    # (the spot's faint tail in the annulus lifts it by 1e-4)
    assert bg[0] == pytest.approx(50.0 + 3.0 * 0.31 - 2.0 * -0.23, abs=1e-3)


@pytest.mark.parametrize("kernel", [K.window_centroid_numba, K.window_centroid_numpy],
                         ids=["numba", "numpy"])
def test_window_kernel_matches_numpy_twin(rng, kernel):
    rr, cc = np.indices((80, 90))
    truth = rng.uniform(8, 72, (25, 2))
    img = rng.normal(0.0, 0.02, (80, 90)) + 0.1 + 0.001 * cc
    for y, x in truth:
        img += np.exp(-((rr - y) ** 2 + (cc - x) ** 2) / (2 * 0.9 ** 2))
    start = truth + rng.normal(0, 0.3, truth.shape)
    start[0] = [1.0, 1.0]          # a window cut by the image edge
    a = K.window_centroid_numba(img, start, 3.0, 3.5, 5.5, 50, 1e-9)
    b = kernel(img, start, 3.0, 3.5, 5.5, 50, 1e-9)
    for x, y in zip(a, b, strict=True):
        assert np.allclose(x, y, rtol=1e-10, atol=1e-10, equal_nan=True)
    ea = K.radial_energy_numba(img, truth, 8.0, 0.25)
    eb = K.radial_energy_numpy(img, truth, 8.0, 0.25)
    assert np.allclose(ea[0], eb[0]) and np.array_equal(ea[1], eb[1])


def test_auto_takes_the_window_for_small_spots_and_the_shape_for_discs(small_camera):
    cam = camera(small_camera, 0.2, 21, 31)
    small = detect_spots(focal_point_image(cam, f_number=16, psf_px=0.5))
    assert small.method == "window"
    assert small.moment_radius_px > small.spot_radius_px and np.isfinite(small.annulus_px[0])
    white = detect_spots(focal_point_image(cam, f_number=2.8, psf_px=0.5))
    assert white.method == "shape"          # micro-images that fill their cells
    assert white.spot_radius_px > 0.35 * white.pitch_px


# ---- sub-pixel phase bias removed with the lattice ----------------------------------------------


def test_lattice_fit_removes_an_injected_phase_bias(rng):
    i, j = np.meshgrid(np.arange(30), np.arange(40), indexing="ij")
    true = np.column_stack([10.3 + 16.9 * i.ravel(), 12.6 + 16.9 * j.ravel()])
    bias = 0.02 * np.sin(2 * np.pi * true) + 0.005 * np.sin(4 * np.pi * true)
    lat = fit_lattice(true + bias, phase_harmonics=2)
    # the bias is a function of the true phase, the fit sees the measured one: 40 times less
    # pitch error than without the terms (2.7e-4 px), a lattice within 1e-4 px of the truth
    assert np.abs(lat.corrected_centres_px - lat.predict(lat.grid_index)).max() < 1e-3
    assert lat.pitch_px == pytest.approx([16.9, 16.9], abs=1e-5)
    assert np.abs(lat.predict(lat.grid_index) - true).max() < 1e-4
    assert np.abs(fit_lattice(true + bias).pitch_px - 16.9).max() > 1e-4
    # an irregularly placed array (0.1 px scatter): no correction is made up from the scatter
    jittered = true + rng.normal(0, 0.1, true.shape)
    assert np.all(fit_lattice(jittered, phase_harmonics=2).phase_bias_px == 0.0)
