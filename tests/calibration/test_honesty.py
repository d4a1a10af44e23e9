"""Every bad calibration input is a clear error or a flagged result (issue #10, items 4-5).

A forced wrong grid type, a scene image, a lattice with too many missing lenslets, an
f-number that contradicts the white image, a refocus α the light field cannot support; and
the dim lenslets of a vignetted corner, which must be found rather than counted missing.
"""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest

from conftest import shared_data_path
from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.lattice_fit import fit_lattice
from plenopiv.calibration.lattice_quality import check_lattice
from plenopiv.calibration.spot_detection import detect_spots
from plenopiv.cli import main
from plenopiv.errors import CalibrationError
from plenopiv.lightfield import LightFieldWarning, light_field, refocus
from plenopiv.products.images import write_image
from plenopiv.synthetic.images import (
    Ruler,
    finish_image,
    focal_point_image,
    particle_image,
    ruler_image,
)
from plenopiv.synthetic.seeding import SeedingBox, random_particles


@pytest.fixture(scope="module")
def patch(small_camera):
    """A 21 x 31-lenslet patch of the Auburn optics at S_i = 200 mm."""
    return small_camera.patch(21, 31, margin_px=12)


@pytest.fixture(scope="module")
def focal(patch):
    """Its f/16 focal-point image with a 0.5 px PSF and photon noise (0.9 x 4095 counts)."""
    irr = focal_point_image(patch, f_number=16, psf_px=0.5)
    return finish_image(irr, noise="poisson", bit_depth=16, full_well=65535.0,
                        peak_fraction=0.9 * 4095 / 65535, rng=np.random.default_rng(2))


def _as_hexagonal(camera):
    mla = dataclasses.replace(camera.microlens_array, grid="hexagonal")
    return camera.replace(microlens_array=mla)


def test_a_good_calibration_reports_its_lattice_quality(patch, focal):
    rep = calibrate(patch, focal)
    q = rep.summary()["lattice"]["focal_point"]
    assert q["grid"] == "square" and q["spot_method"] == "window"
    assert q["n_missing"] == 0 and q["missing_fraction"] == 0.0
    assert q["rms_residual_px"] < 0.02 and q["rms_residual_pitch"] < 0.002
    assert q["n_fitted"] == q["n_spots"] - q["n_edge"]
    assert abs(q["shear_deg"]) < 0.01
    json.dumps(rep.summary())                     # JSON-ready


def test_forced_wrong_grid_type_is_refused(patch, focal):
    with pytest.raises(CalibrationError, match=r"do not form a hexagonal lattice.*"
                                               r"at most .*max_shape_error = 0.05.*square array"):
        calibrate(_as_hexagonal(patch), focal)
    spots = detect_spots(focal)
    with pytest.raises(CalibrationError, match="do not form a hexagonal lattice"):
        fit_lattice(spots, grid="hexagonal")
    assert fit_lattice(spots, grid="square").grid == "square"


def test_hexagonal_image_forced_square_is_refused(patch):
    hexcam = _as_hexagonal(patch)
    img = focal_point_image(hexcam, f_number=16, psf_px=0.5)
    assert fit_lattice(detect_spots(img)).grid == "hexagonal"
    with pytest.raises(CalibrationError, match="do not form a square lattice"):
        calibrate(patch, img)


def test_scene_images_are_refused(patch):
    ruler = ruler_image(patch, Ruler(1e-3), rays_per_lenslet=300)
    with pytest.raises(CalibrationError,
                       match=r"(max_rms_residual_pitch|max_missing_fraction).*a ruler image "
                             r"given as"):
        calibrate(patch, ruler)
    box = SeedingBox.field_of_view(patch, (-5e-3, 5e-3))
    parts = particle_image(patch, random_particles(box, 400, np.random.default_rng(1)),
                           rays_per_particle=256)
    with pytest.raises(CalibrationError):
        calibrate(patch, parts)


@pytest.mark.data
def test_a_real_scene_image_is_refused():
    """The plenoptomos letters: a plenoptic image of a scene, not a calibration image. Its
    micro-images make a lattice, but an eighth of its positions are dark."""
    from skimage.io import imread

    raw = imread(shared_data_path("plenoptomos_letters_ULF", "letters_ULF_M1.png"))
    lat = fit_lattice(detect_spots(raw), image_shape=raw.shape)
    with pytest.raises(CalibrationError, match=r"hold no spot.*at most 5 %.*max_missing_frac"):
        check_lattice(lat, what="letters_ULF_M1.png")
    white = imread(shared_data_path("plenoptomos_letters_ULF", "letters_ULF_M1_white.png"))
    q = check_lattice(fit_lattice(detect_spots(white), image_shape=white.shape))
    assert q["n_missing"] == 0


def test_more_than_five_percent_missing_lenslets_is_refused(patch, focal):
    img = focal.copy()
    p = patch.pitch_px
    # a dark block of 5 x 3 lenslets inside the array (2.3 % of them): reported, filled
    r0, c0 = int(6 * p), int(10 * p)
    small = img.copy()
    small[r0:r0 + int(5 * p), c0:c0 + int(3 * p)] = 0
    rep = calibrate(patch, small)
    assert 0 < rep.summary()["lattice"]["focal_point"]["missing_fraction"] <= 0.05
    assert any("missing" in n for n in rep.notes)
    # 7 x 6 of them (6.5 %): refused, naming the fraction and the threshold
    img[r0:r0 + int(7 * p), c0:c0 + int(6 * p)] = 0
    with pytest.raises(CalibrationError, match=r"hold no spot, [67]\.\d % .*at most 5 %"):
        calibrate(patch, img)
    assert calibrate(patch, img, max_missing_fraction=0.1).n_missing > 0


def test_dim_lenslets_of_a_vignetted_corner_are_found(small_camera):
    """Each spot dimmed as a whole (a vignetted lens passes less light to the outer
    lenslets), down to 4 % in the corners, with photon and read noise."""
    from scipy.spatial import cKDTree

    from plenopiv.camera.optics import focal_spot_exact
    from plenopiv.conventions import sensor_to_pixel

    irr = focal_point_image(small_camera, f_number=16, psf_px=0.5)
    mla = small_camera.microlens_array
    spots = sensor_to_pixel(focal_spot_exact(mla.centres(), 0.2, mla.sensor_distance),
                            irr.shape, small_camera.sensor.pixel_pitch)
    r = np.hypot(spots[:, 0] / irr.shape[0] - 0.5, spots[:, 1] / irr.shape[1] - 0.5)
    level = 0.04 + 0.96 * np.clip(1 - r / np.sqrt(0.5), 0, 1) ** 3     # corners at 4 %
    rr, cc = np.indices(irr.shape)
    _, owner = cKDTree(spots).query(np.column_stack([rr.ravel(), cc.ravel()]))
    vignetting = level[owner].reshape(irr.shape)
    img = finish_image(irr * vignetting, noise="poisson", bit_depth=16, full_well=65535.0,
                       peak_fraction=0.9 * 4095 / 65535, read_noise=2.0,
                       rng=np.random.default_rng(4)) + np.uint16(40)
    spots = detect_spots(img)
    assert len(spots) == small_camera.microlens_array.count
    lat = fit_lattice(spots, image_shape=img.shape)
    assert lat.n_missing == 0
    rep = calibrate(small_camera, img)
    assert rep.n_missing == 0
    assert abs(rep.focal_fit.image_distance - 0.2) <= 3 * rep.focal_fit.sigma_image_distance


@pytest.fixture(scope="module")
def whites(patch):
    """White images of the patch at its working aperture f/2.8 and at f/4."""
    return {n: focal_point_image(patch, f_number=n, psf_px=0.5) for n in (2.8, 4.0)}


def test_white_image_confirms_the_f_number(patch, focal, whites):
    rep = calibrate(patch, focal, white_image=whites[2.8])
    w = rep.summary()["white_image"]
    assert w["model_over_measured"] == pytest.approx(1.0, abs=0.03)
    assert w["implied_f_number"] == pytest.approx(2.8, rel=0.03)
    assert not rep.notes
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lf = light_field(rep.calibration)
    assert lf.n_rays > 100 * rep.calibration.n_lenslets


def test_f_number_that_contradicts_the_white_image_is_flagged(patch, focal, whites):
    rep = calibrate(patch, focal, white_image=whites[4.0])     # the camera file says f/2.8
    w = rep.summary()["white_image"]
    assert w["implied_f_number"] == pytest.approx(4.0, rel=0.05)
    assert any("f_number = 2.8" in n and "white image" in n for n in rep.notes)
    with pytest.warns(LightFieldWarning, match=r"f_number = 2\.8 makes the micro-images .* "
                                               r"white image .* f_number = 4"):
        light_field(rep.calibration)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        light_field(rep.calibration, f_number=4.0)        # the recording's aperture: fine


def test_light_field_warns_when_nearly_empty_or_overlapping(patch, focal):
    cal = calibrate(patch, focal).calibration
    with pytest.warns(LightFieldWarning, match=r"rays for .* lenslets .* f_number = 40"):
        light_field(cal, f_number=40.0)
    # micro-images larger than their pitch overlap: the warning names f_number, and the
    # pixels claimed by two lenslets are an error
    with pytest.warns(LightFieldWarning, match=r"f_number = 2 makes .* more than their pitch"), \
            pytest.raises(CalibrationError, match="two lenslets claim the same pixel"):
        light_field(cal, f_number=2.0)


def test_refocus_outside_the_supported_alpha_is_an_error(patch, focal):
    cal = calibrate(patch, focal).calibration
    lf = light_field(cal)
    lo, hi = lf.alpha_range
    assert 0.8 < lo < 1.0 < hi < 1.25
    img = np.asarray(focal, float)
    out = refocus(img, lf, 0.5 * (1 + hi), method="fourier", grid_index=cal.grid_index)
    assert np.isfinite(out).any()
    for alpha in (0.9 * lo, 1.1 * hi):
        with pytest.raises(ValueError, match=rf"alpha = .* outside the range .* "
                                             rf"{lo:.4g} <= alpha <= {hi:.4g}"):
            refocus(img, lf, alpha, method="fourier", grid_index=cal.grid_index)


def test_cli_calibrate_reports_quality_and_refuses_a_ruler(tmp_path, capsys, small_camera):
    good = focal_point_image(small_camera, f_number=16, psf_px=0.5)
    write_image(tmp_path / "fp.tif", finish_image(good))
    write_image(tmp_path / "ruler.tif",
                finish_image(ruler_image(small_camera, Ruler(1e-3), rays_per_lenslet=300)))
    code = main(["calibrate", "small_test", "--focal-point", str(tmp_path / "fp.tif"),
                 "--focal-point-f-number", "16", "--out", str(tmp_path / "cal.h5"), "--json",
                 "--no-report"])
    s = json.loads(capsys.readouterr().out)
    assert code == 0
    q = s["lattice"]["focal_point"]
    assert q["spot_method"] == "window" and q["n_missing"] == 0 and q["rms_residual_px"] < 0.01
    assert s["image_distance_mm"] == pytest.approx(200.0, abs=0.01)
    code = main(["calibrate", "small_test", "--focal-point", str(tmp_path / "ruler.tif"),
                 "--out", str(tmp_path / "bad.h5")])
    err = capsys.readouterr().err
    assert code == 2
    assert "max_missing_fraction" in err and "a ruler image given as the focal-point image?" in err
    assert not (tmp_path / "bad.h5").exists()


@pytest.mark.parametrize("kind", ["focal-point", "alignment"])
def test_cli_simulate_rendering_choices(tmp_path, capsys, kind):
    out = tmp_path / "img.tif"
    code = main(["simulate", kind, "small_test", "--out", str(out), "--f-number", "16",
                 "--splat", "pixel", "--psf-px", "0.6", "--sensor-shift-px", "0.25", "-0.4",
                 "--json", "--quiet"])
    s = json.loads(capsys.readouterr().out)
    assert code == 0
    assert s["splat"] == "pixel" and s["psf_px"] == 0.6 and s["sensor_shift_px"] == [0.25, -0.4]
    code = main(["simulate", kind, "small_test", "--out", str(out), "--lenslets", "20", "30",
                 "--json", "--quiet"])
    s = json.loads(capsys.readouterr().out)
    assert code == 0 and "20 x 30-lenslet patch" in s["camera"] and s["shape"][0] < 700
    code = main(["simulate", kind, "small_test", "--out", str(out), "--psf-px", "-1"])
    assert code == 2 and "--psf-px -1.0: expected a finite number >= 0" in capsys.readouterr().err
