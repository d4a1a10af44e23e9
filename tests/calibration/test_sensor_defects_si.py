"""S_i from calibration images through a real sensor, with and without its dark frame.

Every sensor effect of :data:`~plenopiv.synthetic.sensor.REALISTIC` (on its 12-bit ADC) alone
and all of them together, on the demo camera's focal-point and alignment images with their
white (``sensor_recording.record``): S_i within the held-out bar, 0.05 mm at S_i = 100 mm, or
a warning that names what it carries into S_i and the dark frame. Never a silent error beyond
the bar. Without the dark the alignment spots' window grew to the whole cell (a hot pixel
beside a spot, which their one-pixel shape cannot tell, and the black level left in the gaps
carry the 99 % radius of their stacked light outwards) and took the gaps' pattern into every
centre: 0.26-0.28 px of noise in each instead of 0.01, which the lattice pitch, multiplied by
S_i/f = 200 into S_i, carried as -0.07 to -0.22 mm (seeds 1, 2, 5).
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.defects import hot_pixel_mask
from plenopiv.calibration.spot_detection import window_radius_from_rms
from plenopiv.camera.model import load_camera
from plenopiv.errors import PlenopivWarning
from plenopiv.synthetic.sensor import REALISTIC, RecordingSettings
from sensor_recording import FOCAL_POINT_F_NUMBER, record

#: The held-out bar on S_i (issue's bars/realcam), m
SI_BAR = 0.05e-3
_ADC = {"adc_bits": REALISTIC.adc_bits}
#: Each sensor effect of REALISTIC alone (on its ADC), and all of REALISTIC's effects
SENSOR_EFFECTS = {
    "black level + fixed pattern": RecordingSettings(
        black_level_counts=REALISTIC.black_level_counts,
        column_offset_counts=REALISTIC.column_offset_counts,
        pixel_offset_counts=REALISTIC.pixel_offset_counts, **_ADC),
    "read noise": RecordingSettings(read_noise_counts=REALISTIC.read_noise_counts, **_ADC),
    "hot and dead pixels": RecordingSettings(
        hot_pixel_fraction=REALISTIC.hot_pixel_fraction,
        hot_pixel_counts=REALISTIC.hot_pixel_counts,
        dead_pixel_fraction=REALISTIC.dead_pixel_fraction, **_ADC),
    # the pair that went wrong without the dark: hot pixels on a patterned black level
    "black level + hot pixels": RecordingSettings(
        black_level_counts=REALISTIC.black_level_counts,
        column_offset_counts=REALISTIC.column_offset_counts,
        pixel_offset_counts=REALISTIC.pixel_offset_counts,
        hot_pixel_fraction=REALISTIC.hot_pixel_fraction,
        hot_pixel_counts=REALISTIC.hot_pixel_counts, **_ADC),
    "all (REALISTIC)": REALISTIC,
}
SEEDS = (1, 2, 5)
FAST = {("black level + hot pixels", 5), ("all (REALISTIC)", 1)}
CASES = [pytest.param(effect, seed, marks=() if (effect, seed) in FAST else pytest.mark.slow,
                      id=f"{effect}-seed{seed}")
         for effect in SENSOR_EFFECTS for seed in SEEDS]


@pytest.fixture(scope="module")
def camera():
    return load_camera("small_m1")


def _si_error(camera, fp, al, white, dark):
    """S_i error (m), its warnings' texts and the report."""
    user = camera.replace(main_lens=replace(camera.main_lens, image_distance=None))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PlenopivWarning)
        rep = calibrate(user, fp, alignment_image=al, white_image=white, dark=dark,
                        focal_point_f_number=FOCAL_POINT_F_NUMBER)
    texts = [str(w.message) for w in caught if issubclass(w.category, PlenopivWarning)]
    return rep.calibration.image_distance - camera.image_distance, texts, rep


@pytest.mark.parametrize(("effect", "seed"), CASES)
def test_si_within_the_bar_or_warned_with_and_without_the_dark(camera, effect, seed):
    """With the dark S_i within the bar, unwarned; without it within the bar or warned with
    the figure and ``--dark``."""
    fp, al, white, dark = record(camera, SENSOR_EFFECTS[effect], seed)
    err, texts, _ = _si_error(camera, fp, al, white, dark)
    assert abs(err) <= SI_BAR and not texts, (effect, seed, "dark", err * 1e3, texts)
    err, texts, rep = _si_error(camera, fp, al, white, None)
    warned = any("mm into S_i" in t and "--dark" in t for t in texts)
    assert abs(err) <= SI_BAR or warned, (effect, seed, "no dark", err * 1e3, texts)
    if SENSOR_EFFECTS[effect].black_level_counts > 0:
        assert any("no dark frame: a black level of 100 counts" in n for n in rep.notes)


def test_hot_pixels_the_focal_point_image_does_not_show_are_warned_about(camera):
    """The focal-point image of the camera without its hot pixels (as from a short exposure,
    whose dark current is nothing), the alignment image and white with them, on the
    patterned black level: without the dark nothing tells the alignment image's hot pixels,
    and the warning names what the lattice carries into S_i and --dark; with it S_i is right
    and unwarned."""
    hot = SENSOR_EFFECTS["black level + hot pixels"]
    fp, _, _, _ = record(camera, SENSOR_EFFECTS["black level + fixed pattern"], 5)
    _, al, white, dark = record(camera, hot, 5)
    err, texts, _ = _si_error(camera, fp, al, white, None)
    assert any("mm into S_i" in t and "--dark" in t for t in texts), (err * 1e3, texts)
    err, texts, _ = _si_error(camera, fp, al, white, dark)
    assert not texts and abs(err) <= SI_BAR, (err * 1e3, texts)


def test_hot_pixel_mask_marks_the_rounded_positions_inside_the_image():
    mask = hot_pixel_mask(np.array([[1.2, 2.7], [-1.0, 3.0], [4.4, 9.6], [0.0, 0.0]]), (5, 10))
    assert mask.sum() == 2 and mask[1, 3] and mask[0, 0]
    assert not hot_pixel_mask(np.zeros((0, 2)), (5, 10)).any()


def test_the_window_from_the_rms_radius_is_the_gaussian_spots():
    """A Gaussian of rms radius r holds 99 % within 2.15 r; the window is 1.75 times that
    plus 0.5 px, at least that radius plus 1 px and 1.5 px."""
    for rms in (0.5, 0.83, 1.0, 2.0):
        r99 = np.sqrt(np.log(100.0)) * rms
        assert window_radius_from_rms(rms) == pytest.approx(
            max(1.75 * r99 + 0.5, r99 + 1.0, 1.5))
    assert window_radius_from_rms(0.83) == pytest.approx(3.62, abs=0.01)
