"""Calibration images of the demo camera through a real camera's effects, for the tests.

:func:`record` renders the focal-point image (f/16), the alignment image, a white at the
working aperture (four frames averaged) and a dark (eight frames averaged; None without a
sensor effect) of ``small_m1`` through one :class:`~plenopiv.synthetic.sensor.RecordingSettings`
(camera seed 7), with photon noise (20 000 electrons at full scale, 16-bit files).
"""

from __future__ import annotations

import numpy as np

from plenopiv.synthetic.images import (
    alignment_image,
    auto_exposure,
    finish_image,
    focal_point_image,
    white_image,
)
from plenopiv.synthetic.sensor import RecordingSettings, camera_instance

FOCAL_POINT_F_NUMBER = 16.0


def record(camera, settings: RecordingSettings, seed: int):
    """Focal-point, alignment, white (mean of 4) and dark (mean of 8, None without a sensor)."""
    inst = camera_instance(camera, settings, seed=7)
    sensor = inst if settings.has_sensor else None
    rng = np.random.default_rng(seed)

    def finish(irr, exposure=None):
        return finish_image(irr, exposure=exposure, noise="poisson", full_well=20000.0,
                            bit_depth=16, rng=rng, sensor=sensor)
    fp = finish(focal_point_image(camera, f_number=FOCAL_POINT_F_NUMBER, instance=inst))
    al = finish(alignment_image(camera, instance=inst))
    irr = white_image(camera, instance=inst)
    e = auto_exposure(irr, bit_depth=16, sensor=sensor)
    white = np.mean([finish(irr, e) for _ in range(4)], axis=0)
    dark = None
    if sensor is not None:
        zero = np.zeros(camera.sensor.shape)
        dark = np.mean([finish(zero, 1.0) for _ in range(8)], axis=0)
    return fp, al, white, dark
