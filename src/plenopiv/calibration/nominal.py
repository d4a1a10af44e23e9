"""A calibration against its camera's nominal values: what it ran to but cannot be right.

:func:`check_against_camera` compares what a calibration measured with what the camera file
says: the image distance must make a real image (S_i > f_m) and lie near the file's
``image_distance_mm`` when it gives one; the lenslet pitch of an alignment image must be the
file's ``pitch_um``. Beyond a build's tolerance it warns, beyond what a build can explain it
refuses, each time with the figures. See docs/methods.md#against-the-nominal-camera.
"""

from __future__ import annotations

import warnings

from plenopiv.camera.model import CameraModel
from plenopiv.errors import CalibrationError, PlenopivWarning

F_BAR_TOLERANCE = 0.05
"""The lenslet array's distance from the sensor, f̄, is built to ±25 µm of 500 µm (±5 %);
the focal-point S_i is f̄/(p/d - 1), so f̄'s tolerance alone moves it by 5 %."""

IMAGE_DISTANCE_WARN = 0.07
"""Fraction of the camera file's S_i by which the calibrated S_i may differ from it before a
warning: f̄'s tolerance and an equal one of the file's nominal S_i (a focus scale, the
pupil's place), independent: sqrt(2) x 5 %."""

IMAGE_DISTANCE_REFUSE = 0.10
"""Fraction of the camera file's S_i beyond which a calibration is refused: twice f̄'s
tolerance, and the fraction beyond which a calibration is refused for another camera or focus
(:func:`plenopiv.workflow.experiment.experiment_calibration`), which this one would be with
its own camera file."""

PITCH_WARN = 0.01
"""Fraction by which an alignment image's lenslet pitch may differ from ``pitch_um`` before
a warning: twice what the Auburn camera shows (4904 px over 289 lenslets, 16.97 px, against
125 µm / 7.4 µm = 16.89 px, 0.5 %); the lattice's own standard error is ~1e-4 px."""

PITCH_REFUSE = 0.03
"""Fraction beyond which the pitch is refused: a lenslet array's lenslets scatter by up to
±3 % of the pitch, not cumulative, so their mean spacing cannot differ by more."""


def _causes(method: str, camera: CameraModel, image_distance: float) -> str:
    """What the method's S_i rests on, named as the user gives it, with its sensitivity."""
    if method == "magnification":
        return ("the magnification method rests on the ruler's tick spacing "
                "(--ruler-spacing-mm) and the lens's [main_lens] focal_length_mm: S_i = "
                "f_m (1 - M), M from the ticks")
    # p/d - 1 = f̄/S_i: a relative pitch error e moves S_i by e S_i/f̄
    per_mille = 0.001 * image_distance / camera.microlens_array.sensor_distance
    return ("the focal-point fit rests on the lenslets' pitch ([microlens_array] pitch_um over "
            "[sensor] pixel_pitch_um, unless an alignment image measures it) and on f̄ "
            "([microlens_array] sensor_distance_um): S_i = f̄/(p/d - 1), so a pitch 0.1 % off "
            f"moves S_i by {100 * per_mille:.0f} %")


def check_against_camera(camera: CameraModel, image_distance: float, sigma: float,
                         method: str, *, alignment_pitch_px: float | None = None) -> list[str]:
    """Refuse or warn about a calibration far from its camera file; return the warnings.

    Parameters
    ----------
    camera : CameraModel
        The camera file the calibration was made with (its ``image_distance`` may be unset).
    image_distance, sigma : float
        The calibrated S_i,eff and its standard uncertainty, metres.
    method : str
        The method whose S_i is kept (``"focal-point"``, ``"magnification"``, ``"both"``).
    alignment_pitch_px : float, optional
        The lenslet pitch an alignment image measured (along the lattice's rows), pixels.

    Raises
    ------
    CalibrationError
        S_i ≤ f_m (no real image); S_i more than :data:`IMAGE_DISTANCE_REFUSE` (and 3 sigma)
        from the camera file's; the pitch more than :data:`PITCH_REFUSE` from ``pitch_um``.
    """
    lens = camera.main_lens
    kept = "magnification" if method == "magnification" else "focal-point"
    what = (f"the calibrated image distance S_i = {image_distance * 1e3:.4g} mm (measured by "
            f"the {kept} method, ± {sigma * 1e3:.2g} mm)")
    if not image_distance > lens.focal_length:
        raise CalibrationError(
            f"{what} is not longer than the main lens's focal length, [main_lens] "
            f"focal_length_mm = {lens.focal_length * 1e3:g}: no real image, so the calibration "
            f"cannot be right; {_causes(kept, camera, image_distance)}")
    causes = _causes(kept, camera, image_distance)
    said = []
    if alignment_pitch_px is not None:
        said += _check_pitch(camera, alignment_pitch_px)
    nominal = lens.image_distance if lens.image_distance_origin is None else None
    if nominal is not None:
        off = abs(image_distance - nominal)
        share = off / nominal
        text = (f"{what} differs from the camera file's [main_lens] image_distance_mm = "
                f"{nominal * 1e3:g} by {off * 1e3:.3g} mm, {100 * share:.1f} % of it")
        if share > IMAGE_DISTANCE_REFUSE and off > 3 * sigma:
            raise CalibrationError(
                f"{text}, more than the {100 * IMAGE_DISTANCE_REFUSE:g} % a camera's build "
                f"and focus explain (f̄ alone ±{100 * F_BAR_TOLERANCE:g} %): the calibration "
                f"cannot be right, or the camera file is not this camera's; {causes}. If "
                "image_distance_mm is a guess, remove it from the camera file")
        if share > IMAGE_DISTANCE_WARN and off > 3 * sigma:
            said.append(f"{text}, more than f̄'s build tolerance and the nominal S_i's explain "
                        f"(±{100 * IMAGE_DISTANCE_WARN:g} %); {causes}")
    for text in said:
        warnings.warn(text, PlenopivWarning, stacklevel=3)
    return said


def _check_pitch(camera: CameraModel, measured_px: float) -> list[str]:
    """The alignment image's pitch against ``pitch_um``: refused or warned beyond tolerance."""
    mla, pp = camera.microlens_array, camera.sensor.pixel_pitch
    nominal_px = mla.pitch / pp
    share = abs(measured_px / nominal_px - 1.0)
    text = (f"the alignment image's lenslets are {measured_px:.4g} px apart, "
            f"{measured_px * pp * 1e6:.4g} µm, {100 * share:.1f} % from [microlens_array] "
            f"pitch_um = {mla.pitch * 1e6:g} ({nominal_px:.4g} px of [sensor] pixel_pitch_um = "
            f"{pp * 1e6:g})")
    if share > PITCH_REFUSE:
        raise CalibrationError(
            f"{text}: more than a lenslet array's ±{100 * PITCH_REFUSE:g} % scatter, so not "
            "this array's pitch; correct pitch_um or pixel_pitch_um, or give this camera's "
            "alignment image")
    if share > PITCH_WARN:
        return [f"{text}: more than {100 * PITCH_WARN:g} %; the reconstruction's lateral scale "
                "follows pitch_um: correct it"]
    return []
