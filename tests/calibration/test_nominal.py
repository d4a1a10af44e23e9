"""A calibration far from its camera's nominal values is refused or warned about, with figures.

Every nominal quantity a calibration rests on is given wrong by the factors 0.5, 0.9, 1.1, 2
and 10 in the camera file (or on the command line, the ruler's spacing), and the calibration
of one set of true images must do what the physics says: S_i from the focal-point fit scales
with f̄ (S_i = f̄/(p/d - 1)) and not with the pitch when an alignment image measures it; the
magnification method's S_i = f_m (1 - M) scales with f_m, and with the ruler's spacing through
M. The expected S_i is compared with the camera file's by the documented thresholds
(calibration.nominal): beyond 10 % refused, beyond 7 % warned, S_i <= f_m refused; within two
standard uncertainties of a threshold either outcome is right. A camera file that cannot
describe a camera (an array wider than its sensor, S_i short of f_m) is refused at once,
naming the key the user wrote.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.model import Calibration
from plenopiv.calibration.nominal import (
    IMAGE_DISTANCE_REFUSE,
    IMAGE_DISTANCE_WARN,
    PITCH_REFUSE,
    PITCH_WARN,
)
from plenopiv.errors import CalibrationError, ConfigError, PlenopivWarning
from plenopiv.synthetic.images import (
    Ruler,
    alignment_image,
    finish_image,
    focal_point_image,
    ruler_image,
)

SI = 0.2
#: The camera file's S_i, 4 % short of the truth: a user's nominal value
NOMINAL = 0.96 * SI
FACTORS = (0.5, 0.9, 1.1, 2.0, 10.0)
QUANTITIES = ("image_distance", "pitch", "sensor_distance", "focal_length", "ruler_spacing")


@pytest.fixture(scope="module")
def truth(small_camera):
    return small_camera.patch(21, 31, margin_px=12).with_image_distance(SI)


@pytest.fixture(scope="module")
def images(truth):
    rng = np.random.default_rng(3)
    return {"focal": finish_image(focal_point_image(truth, f_number=16), noise="poisson",
                                  rng=rng),
            "alignment": finish_image(alignment_image(truth), noise="poisson", rng=rng),
            "ruler": finish_image(ruler_image(truth, Ruler(1e-3), rays_per_lenslet=1000),
                                  noise="poisson", rng=rng)}


def wrong_camera(truth, quantity, k):
    """The camera file with ``quantity`` times ``k`` (and the nominal S_i), or ConfigError."""
    mla, lens = truth.microlens_array, truth.main_lens
    cam = truth.with_image_distance(NOMINAL * (k if quantity == "image_distance" else 1.0))
    if quantity == "pitch":
        return cam.replace(microlens_array=dataclasses.replace(mla, pitch=mla.pitch * k))
    if quantity == "sensor_distance":
        return cam.replace(microlens_array=dataclasses.replace(
            mla, sensor_distance=mla.sensor_distance * k))
    if quantity == "focal_length":
        return cam.replace(main_lens=dataclasses.replace(
            cam.main_lens, focal_length=lens.focal_length * k))
    return cam


def expected_image_distance(truth, quantity, k):
    """S_i the calibration must find, m, and the method that finds it."""
    f, m = truth.main_lens.focal_length, SI / truth.object_distance       # |M|
    if quantity == "sensor_distance":
        return k * SI, "focal-point"
    if quantity == "focal_length":
        return k * f * (1 + m), "magnification"
    if quantity == "ruler_spacing":
        return f * (1 + m / k), "magnification"
    return SI, "focal-point"


def outcome(share, sigma_share, warn, refuse):
    """The outcomes the thresholds allow for a deviation ``share`` known to ``sigma_share``."""
    near = 2 * sigma_share + 1e-3
    allowed = set()
    for value in (share - near, share, share + near):
        allowed.add("refused" if value > refuse else "warned" if value > warn else "ok")
    return allowed


@pytest.mark.parametrize("k", FACTORS)
@pytest.mark.parametrize("quantity", QUANTITIES)
def test_each_nominal_quantity_off_is_refused_or_warned_with_its_figure(truth, images,
                                                                        quantity, k):
    try:
        camera = wrong_camera(truth, quantity, k)
    except ConfigError as exc:       # the file describes no camera: the user's own key
        key = {"image_distance": "image_distance_mm", "pitch": "pitch_um",
               "focal_length": "focal_length_mm"}[quantity]
        assert key in str(exc)
        return
    si, method = expected_image_distance(truth, quantity, k)
    ruler = dict(ruler_image=images["ruler"], method=method,
                 ruler_spacing=1e-3 * (k if quantity == "ruler_spacing" else 1.0))
    if method == "focal-point":
        ruler = {}
    alignment = images["alignment"] if quantity == "pitch" else None
    sigma = 0.01 * si if method == "magnification" else 1e-4 * si
    if quantity == "pitch":
        allowed = outcome(abs(1 / k - 1), 0.0, PITCH_WARN, PITCH_REFUSE)
    elif si <= camera.main_lens.focal_length:
        allowed = {"refused"}
    else:
        nominal = camera.main_lens.image_distance
        allowed = outcome(abs(si / nominal - 1), sigma / nominal, IMAGE_DISTANCE_WARN,
                          IMAGE_DISTANCE_REFUSE)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            rep = calibrate(camera, images["focal"], alignment_image=alignment,
                            focal_point_f_number=16, **ruler)
            said = [str(w.message) for w in caught if issubclass(w.category, PlenopivWarning)]
            got = "warned" if said else "ok"
            text = " ".join(said)
        except CalibrationError as exc:
            got, text, rep = "refused", str(exc), None
    assert got in allowed, (quantity, k, got, text)
    if got == "ok":
        assert rep.calibration.image_distance == pytest.approx(si, rel=0.03)
        return
    # the figure, named as calibrated (or as the pitch measured), never as a key unwritten
    if quantity == "pitch":
        assert "the alignment image's lenslets are" in text and "pitch_um =" in text
    else:
        assert "the calibrated image distance S_i = " in text
        assert f"(measured by the {method} method" in text
    assert "image_distance_mm = " not in text.replace(
        "the camera file's [main_lens] image_distance_mm = ", "")


def test_the_issues_ruler_ten_times_wrong_is_refused(truth, images):
    """A ruler spacing 10 times wrong: the magnification S_i is 26 % short of the file's."""
    with pytest.raises(CalibrationError, match=r"differs from the camera file's \[main_lens\] "
                                               r"image_distance_mm = 192 by .* mm, 2\d\.\d % of"):
        calibrate(truth.with_image_distance(NOMINAL), images["focal"],
                  ruler_image=images["ruler"], ruler_spacing=10e-3, method="magnification")


def test_a_calibrated_image_distance_is_never_named_as_a_key(tmp_path, truth):
    """Every check that can refuse an S_i names a calibrated one as calibrated.

    The checks on S_i: a real image (S_i > f_m), the exit pupil before the lenslets, the
    window of an external interface in front of the lens (S_o from S_i). Each is made to
    fail by a calibrated S_i, from a product or an option, and its message must say where
    the value came from, not ``[main_lens] image_distance_mm``, which the user never wrote.
    """
    from plenopiv.camera.model import ExternalInterface

    bare = truth.with_image_distance(None)
    short = 0.8 * truth.main_lens.focal_length                # no real image
    pupil = dataclasses.replace(bare.main_lens, exit_pupil_offset=0.5)    # past the lenslets
    far = bare.replace(external_interface=ExternalInterface(1.33, 1.0, 5.0))  # past the lens
    cases = [(bare, short), (bare.replace(main_lens=pupil), SI), (far, SI)]
    for origin, says in ((f"from {str(tmp_path / 'cal.h5')!r}", "the calibrated image "
                          "distance S_i = "), ("--image-distance-mm", "--image-distance-mm ")):
        for camera, si in cases:
            with pytest.raises(ConfigError) as err:
                camera.with_image_distance(si, origin=origin)
            assert says in str(err.value) and origin in str(err.value)
            assert "image_distance_mm =" not in str(err.value)
    # and a product holding such an S_i, read back
    path = Calibration.from_camera(truth).save(tmp_path / "cal.h5")
    import h5py

    with h5py.File(path, "r+") as fh:
        fh.attrs["image_distance_m"] = short
    with pytest.raises(CalibrationError, match=r"the calibrated image distance S_i = 108 mm \(from "
                                               r"'.*cal\.h5'\): expected > "
                                               r"\[main_lens\] focal_length_mm = 135"):
        Calibration.load(path)


def test_one_image_given_as_two_calibration_images_is_warned_about(truth, images):
    """The focal-point image again as the alignment image: warned, then refused by its scale."""
    with pytest.warns(PlenopivWarning, match="the focal-point image and the alignment image "
                                             "are identical"):
        with pytest.raises(CalibrationError, match=r"\(measured on the alignment image\): "
                                                   r"expected a ratio 1 \+ f̄/S_i slightly "
                                                   r"above 1"):
            calibrate(truth, images["focal"], alignment_image=images["focal"])
