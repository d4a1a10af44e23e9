"""The camera's resolution cell, the lenslet footprint and the depth it resolves."""

from __future__ import annotations

from plenopiv.camera.model import CameraModel


def footprint(camera: CameraModel) -> float:
    """Lenslet footprint on the nominal focal plane, p_m S_o/S_i, metres."""
    return camera.microlens_array.pitch * camera.object_distance / camera.image_distance


def resolution_cell(camera: CameraModel, f_number: float | None = None) -> tuple[float, float]:
    """Lateral and depth resolution of the camera near the focal plane, metres.

    Lateral: one lenslet footprint b = p_m S_o/S_i. Depth: the views at the two edges of the
    aperture (diameter D = f_m/N) see a particle at depth Z displaced by D Z/S_o relative to
    each other, so two depths are told apart when that shift changes by one footprint:
    ΔZ = b S_o/D (0.55 mm for the 50 mm lens at M = -1, f/2.2). The ratio ΔZ/b = S_o/D is the
    depth elongation expected of a reconstructed particle. Give the effective camera
    (``calibration.effective_camera``) for effective coordinates.
    """
    n = camera.main_lens.f_number if f_number is None else f_number
    b = footprint(camera)
    return b, b * camera.object_distance * n / camera.main_lens.focal_length


#: Modelled and measured micro-image diameters may differ by this factor before a warning.
MICRO_IMAGE_TOLERANCE = 1.25


def micro_image_diameter_px(camera, image_distance: float, f_number: float) -> float:
    """Modelled micro-image diameter, px: the aperture ``f_m / N`` seen from the lenslets.

    ``f_m / N * f̄ / S_i`` on the sensor (divided by the plate's index with the "thesis" back
    side, whose rays keep their in-glass angle). :func:`light_field` takes each lenslet's
    pixels within this disc (plus a pixel).
    """
    d = camera.main_lens.focal_length / f_number
    mla = camera.microlens_array
    if mla.back_side == "thesis" and mla.substrate is not None:
        d /= mla.substrate.refractive_index
    return d * camera.microlens_array.sensor_distance / image_distance / camera.sensor.pixel_pitch
