"""An experiment's calibration and the identity of the settings that shape its products."""

from __future__ import annotations

import math

from plenopiv.calibration.model import Calibration
from plenopiv.camera.model import CameraModel
from plenopiv.errors import CalibrationError


def _camera_differences(made_for: CameraModel, used: CameraModel) -> list[str]:
    """What differs between the camera a calibration was made for and the one it is used with.

    Sensor, lattice, main-lens focal length (S_i is the calibration's to give).
    """
    def close(a, b):
        return math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-12)

    out = []
    a, b = made_for, used
    if a.sensor.shape != b.sensor.shape:
        out.append(f"sensor {a.sensor.rows} × {a.sensor.cols} px ≠ "
                   f"{b.sensor.rows} × {b.sensor.cols} px")
    if not close(a.sensor.pixel_pitch, b.sensor.pixel_pitch):
        out.append(f"pixel pitch {a.sensor.pixel_pitch * 1e6:g} µm ≠ "
                   f"{b.sensor.pixel_pitch * 1e6:g} µm")
    ma, mb = a.microlens_array, b.microlens_array
    if (ma.rows, ma.cols, ma.grid) != (mb.rows, mb.cols, mb.grid):
        out.append(f"lattice {ma.rows} × {ma.cols} {ma.grid} ≠ {mb.rows} × {mb.cols} {mb.grid}")
    for name, va, vb in (("lenslet pitch", ma.pitch, mb.pitch),
                         ("lenslet focal length", ma.focal_length, mb.focal_length),
                         ("lenslet-sensor distance", ma.sensor_distance, mb.sensor_distance)):
        if not close(va, vb):
            out.append(f"{name} {va * 1e6:g} µm ≠ {vb * 1e6:g} µm")
    if not close(a.main_lens.focal_length, b.main_lens.focal_length):
        out.append(f"main lens focal length {a.main_lens.focal_length * 1e3:g} mm ≠ "
                   f"{b.main_lens.focal_length * 1e3:g} mm")
    return out


#: The experiment camera's nominal S_i may differ from the calibrated one by this fraction;
#: beyond it the camera was refocused (or is another one) and needs its own calibration.
IMAGE_DISTANCE_TOLERANCE = 0.1


def _describe(camera: CameraModel, image_distance: float | None) -> str:
    si = "" if image_distance is None else f", S_i = {image_distance * 1e3:.5g} mm"
    mla = camera.microlens_array
    return (f"{camera.name!r} (main lens f = {camera.main_lens.focal_length * 1e3:g} mm{si}, "
            f"{mla.rows} × {mla.cols} lenslets of {mla.pitch * 1e6:g} µm, sensor "
            f"{camera.sensor.rows} × {camera.sensor.cols} px)")


def product_settings(experiment) -> dict:
    """The settings of an experiment that shape a pair's products.

    The camera, the grid, the reconstruction, particle, PIV, tracking, preprocessing and mask
    tables, dt and the side products (vtk, png). Not the image patterns, the batch, the
    folders or the weight cache (the preprocessing's and the masks' files count by their
    content, in the batch's identities).
    """
    d = experiment.to_dict()
    return {"camera": d["camera"], "volume": d["volume"],
            "reconstruction": d["reconstruction"], "particles": d["particles"],
            "piv": d["piv"], "tracking": d.get("tracking"), "dt_s": d["images"].get("dt_s"),
            "vtk": d["output"].get("vtk"), "png": d["output"].get("png"),
            # only with a [preprocess] table or a mask: experiments without keep their identity
            **({"preprocess": d["preprocess"]} if d.get("preprocess") is not None else {}),
            **({"mask": d["mask"]} if masks_anything(experiment) else {})}


def masks_anything(experiment) -> bool:
    """Whether the experiment's ``[mask]`` table names a file, a box or a cylinder."""
    m = experiment.mask
    return m is not None and bool(m.image or m.volume or m.box or m.cylinder)


def settings_identity(experiment) -> str:
    """SHA-256 of :func:`product_settings` (canonical JSON).

    Equal when, and only when, the products would be made with the same settings.
    """
    import hashlib

    from plenopiv.products.jsonio import to_json

    return hashlib.sha256(to_json(product_settings(experiment)).encode()).hexdigest()


def calibration_for_camera(calibration_path, camera: CameraModel, *,
                           whose: str = "the experiment's camera") -> Calibration:
    """The calibration product at ``calibration_path``, for use with ``camera``.

    S_i and the lenslets come from the calibration product, the interfaces and back-side
    model from ``camera``. The product records the camera it was made for; with another
    camera (sensor, lattice or main-lens focal length differ, or the camera's nominal S_i is
    more than 10 % from the calibrated one) it is a
    :class:`~plenopiv.errors.CalibrationError` naming the file, both cameras and what differs.
    ``plenopiv reconstruct``, ``track``, ``run`` and ``plan --calibration`` all check here.
    """
    cal = Calibration.load(calibration_path)
    diffs = _camera_differences(cal.camera, camera)
    nominal = camera.main_lens.image_distance
    if not diffs and nominal is not None and \
            abs(nominal - cal.image_distance) > IMAGE_DISTANCE_TOLERANCE * cal.image_distance:
        diffs.append(f"calibrated S_i {cal.image_distance * 1e3:.5g} mm against the "
                     f"camera's image_distance_mm = {nominal * 1e3:.5g} (more than "
                     f"{IMAGE_DISTANCE_TOLERANCE:.0%} apart: refocused?)")
    if diffs:
        raise CalibrationError(
            f"the calibration {str(calibration_path)!r} was made for camera "
            f"{_describe(cal.camera, cal.image_distance)} but {whose} is "
            f"{_describe(camera, nominal)}: {'; '.join(diffs)}. Use this camera's calibration "
            "(plenopiv calibrate) or the camera file of the calibrated camera")
    return cal.with_camera(camera)


def experiment_calibration(experiment, calibration_path) -> Calibration:
    """The calibration to use with an experiment (:func:`calibration_for_camera`)."""
    return calibration_for_camera(calibration_path, experiment.camera)
