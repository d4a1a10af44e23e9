"""The sensor's point spread, measured on the focal-point image.

A focal spot is the image of the stopped-down main lens's pupil through its lenslet: a small
disc, which the optics and the sensor blur further (diffraction, aberrations, pixel cross
talk). The model of :mod:`plenopiv.synthetic` renders the disc alone. The blur adds its
variance to the spot's: per axis ``σ² = (r_measured² - r_model²) / 2``, with ``r`` the rms
radius of the stacked spots (:attr:`plenopiv.calibration.spot_types.SpotSet.spot_rms_radius_px`,
two axes), measured the same way on the focal-point image and on the model's rendering of
it. The chain's response uncertainty renders its test images with this blur
(:func:`plenopiv.workflow.response.measure_response`): the reconstruction places particles
differently in depth when the micro-images are blurred (docs/validation/uncertainty.md).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MODEL_PATCH_LENSLETS", "point_spread_sigma"]

MODEL_PATCH_LENSLETS = 15
"""Lenslets per side of the central patch on which the model's focal spots are rendered."""


def point_spread_sigma(camera, spots, f_number: float | None, *,
                       threshold: float = 0.1) -> float | None:
    """Standard deviation of the sensor's Gaussian point spread, px.

    Parameters
    ----------
    camera : CameraModel
        The calibrated camera (its S_i sets the size of the model's spots).
    spots : SpotSet
        The focal-point image's spots
        (:func:`~plenopiv.calibration.spot_detection.detect_spots`): their rms radius and
        the estimator that measured them.
    f_number : float or None
        The stop of the focal-point image; None: unknown, and so is the blur.
    threshold : float
        The threshold ``spots`` were measured with.

    Returns
    -------
    float or None
        ``sqrt(max(0, r_measured² - r_model²) / 2)``, px (0 for spots no larger than the
        model's); None without the f-number or a measured radius.
    """
    from plenopiv.calibration.spot_detection import detect_spots
    from plenopiv.synthetic.images import focal_point_image

    measured = spots.spot_rms_radius_px
    if f_number is None or not np.isfinite(measured):
        return None
    mla = camera.microlens_array
    patch = camera.patch(min(MODEL_PATCH_LENSLETS, mla.rows),
                         min(MODEL_PATCH_LENSLETS, mla.cols))
    model = detect_spots(focal_point_image(patch, f_number=f_number), method=spots.method,
                         threshold=threshold, grid=mla.grid).spot_rms_radius_px
    if not np.isfinite(model):
        return None
    return float(np.sqrt(max(measured**2 - model**2, 0.0) / 2.0))
