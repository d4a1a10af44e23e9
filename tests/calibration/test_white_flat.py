"""The white's flat field on the calibration images: what the micro-images' fall-off and the
lenslets' throughput do to S_i, with and without the white.

The small camera (41 x 61 lenslets, S_i 100 mm) records its focal-point image (f/16) and its
alignment image through one of the recording effects of :mod:`plenopiv.synthetic.sensor`,
with photon noise, and a white at its working aperture (four frames averaged). The fall-off
inside a micro-image pulls every spot towards the brighter side by its gradient times the
spot's variance: the alignment spots, off their micro-images' centres by up to 2.6 px, move
towards them and the focal-point fit reads a longer S_i. Divided by the white, S_i must lie
within four of the fit's own standard deviations of the truth (a false alarm once in 16,000
runs), whatever the effect and wherever the fall-off is centred.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.defects import DarkFrame, WhiteFlat
from plenopiv.camera.model import load_camera
from plenopiv.errors import ImageError
from plenopiv.synthetic.sensor import REALISTIC, RecordingSettings
from sensor_recording import FOCAL_POINT_F_NUMBER, record

#: 20 % of the light lost at a micro-image's rim (REALISTIC's), centred on the micro-image or
#: on the lenslet's axis; a +-10 % throughput spread between lenslets.
EFFECTS = {
    "vignetting about the micro-image": RecordingSettings(vignetting=0.2),
    "vignetting about the lenslet axis": RecordingSettings(vignetting=0.2,
                                                           vignetting_centre="lenslet"),
    "throughput spread": RecordingSettings(throughput_spread=0.1),
}


@pytest.fixture(scope="module")
def camera():
    return load_camera("small_m1")


def _image_distance(camera, fp, al, white=None, dark=None):
    user = camera.replace(main_lens=replace(camera.main_lens, image_distance=None))
    rep = calibrate(user, fp, alignment_image=al, white_image=white, dark=dark,
                    focal_point_f_number=FOCAL_POINT_F_NUMBER)
    assert rep.calibration.n_lenslets == camera.microlens_array.centres().shape[0] - 1 or \
        rep.n_missing <= 0.005 * rep.calibration.n_lenslets
    return rep.calibration.image_distance, rep.focal_fit.sigma_image_distance


@pytest.mark.parametrize("effect", list(EFFECTS))
def test_the_white_takes_the_effect_out_of_si(camera, effect):
    fp, al, white, _ = record(camera, EFFECTS[effect], seed=3)
    si, sigma = _image_distance(camera, fp, al, white)
    err = si - camera.image_distance
    assert abs(err) <= 4 * sigma, (effect, err * 1e3, sigma * 1e3)


@pytest.mark.parametrize("centre", ["micro-image", "lenslet"])
def test_without_the_white_vignetting_lengthens_si(camera, centre):
    """The effect is real: 20 % fall-off at the rims moves S_i by more than 0.1 mm (30 of the
    fit's standard deviations) the way the spots' pull predicts, longer."""
    fp, al, _, _ = record(camera, RecordingSettings(vignetting=0.2, vignetting_centre=centre),
                           seed=3)
    si, sigma = _image_distance(camera, fp, al)
    assert si - camera.image_distance > max(0.1e-3, 10 * sigma)


@pytest.mark.parametrize(("effect", "with_dark"), [
    ("black level", True), ("black level", False), ("all", True), ("all", False)])
def test_the_white_with_a_black_level_with_or_without_its_dark(camera, effect, with_dark):
    """A sensor's black level (100 counts of a 12-bit ADC with its column and pixel pattern)
    in the white and the calibration images: with the dark it is subtracted from all three;
    without it, each image's own (the smooth level of its gaps and its fixed pattern) is,
    before the flat multiplies it (times the flat it would print the micro-images into the
    gaps), and the hot pixels the focal-point image shows by their shape are repaired in the
    alignment image. Either way S_i within four of the fit's standard deviations, every
    lenslet found; "all" is every effect of REALISTIC (without the dark +0.022 mm, sigma
    0.0075 mm; -0.135 mm before the hot pixels were repaired)."""
    settings = REALISTIC if effect == "all" else RecordingSettings(**{
        f: getattr(REALISTIC, f) for f in ("black_level_counts", "column_offset_counts",
                                           "pixel_offset_counts", "adc_bits")})
    fp, al, white, dark = record(camera, settings, seed=5)
    si, sigma = _image_distance(camera, fp, al, white, dark if with_dark else None)
    err = si - camera.image_distance
    assert abs(err) <= 4 * sigma, (effect, with_dark, err * 1e3, sigma * 1e3)


def test_the_flat_is_continuous_and_bounded(rng):
    """Gain = level / max(white, level / 2): 1 on the plateau, at most 2 anywhere, and the
    white's dark taken off first."""
    white = np.full((40, 40), 1000.0)
    white[:, :10] = np.linspace(0.0, 1000.0, 10)
    dark = rng.normal(50.0, 1.0, (40, 40))
    flat = WhiteFlat.of(white + dark, DarkFrame.of(dark, (40, 40)), (40, 40), 10.0)
    assert flat.level == pytest.approx(1000.0, rel=1e-6)
    assert np.allclose(flat.gain[:, 10:], 1.0, atol=1e-4)
    assert flat.gain.max() == pytest.approx(2.0, rel=1e-5)
    assert np.all(np.abs(np.diff(flat.gain, axis=1)) <= 1.0)
    image = np.ones((40, 40))
    assert np.allclose(flat.apply(image), flat.gain)
    assert WhiteFlat.of(None, DarkFrame(), (40, 40), 10.0).apply(image) is image


def test_a_white_without_light_is_refused(rng):
    """All dark, or no light above its dark frame (a dark given as the white)."""
    with pytest.raises(ImageError, match="white image is all dark"):
        WhiteFlat.of(np.zeros((40, 40)), DarkFrame(), (40, 40), 10.0)
    dark = rng.normal(50.0, 1.0, (40, 40))
    with pytest.raises(ImageError, match="white image holds no light above its dark"):
        WhiteFlat.of(dark, DarkFrame.of(dark, (40, 40)), (40, 40), 10.0)
