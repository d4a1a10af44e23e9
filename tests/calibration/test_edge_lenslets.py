"""Every lenslet on the sensor is calibrated, whatever the array's rotation, offset or packing.

The demo's camera puts its outer focal spots about 8 px from the sensor's edge, a spot window
from it. A rotation of 1.5 mrad moves the ends of the outer rows by 0.8 px, a hexagonal
array's shifted rows reach 3 px from the edge: their lenslets' spots can no longer be measured
in a whole window, but their micro-images still see the volume. The calibration keeps them,
predicts the spots it cannot measure from the fitted model (counted in ``n_missing``), and
every spot agrees with the true camera's within the photon-noise scatter of the measured
ones.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.model import Calibration
from plenopiv.camera.model import load_camera
from plenopiv.synthetic.images import alignment_image, finish_image, focal_point_image

#: (rotation rad, offset m, packing) of the array.
ARRAYS = [(1.5e-3, (0.0, 0.0), "square"), (-1.5e-3, (4e-6, -3e-6), "square"),
          (5e-3, (0.0, 0.0), "square"), (0.0, (0.0, 0.0), "hexagonal")]
#: Spot error bound, px: ten times the measured spots' photon-noise rms (0.003 px).
SPOT_PX = 0.03


@pytest.mark.slow
@pytest.mark.parametrize("rotation, offset, grid", ARRAYS)
def test_every_lenslet_on_the_sensor_is_calibrated(rotation, offset, grid):
    cam = load_camera("small_m1")
    cam = cam.replace(microlens_array=dataclasses.replace(
        cam.microlens_array, rotation=rotation, offset=offset, grid=grid))
    rng = np.random.default_rng(1)
    fp = finish_image(focal_point_image(cam, f_number=16), noise="poisson", rng=rng)
    al = finish_image(alignment_image(cam), noise="poisson", rng=rng)
    user = cam.replace(main_lens=dataclasses.replace(cam.main_lens, image_distance=None))
    rep = calibrate(user, fp, alignment_image=al, method="focal-point",
                    focal_point_f_number=16)
    cal, true = rep.calibration, Calibration.from_camera(cam)
    assert cal.n_lenslets == cam.microlens_array.count
    d, j = cKDTree(true.centre_px).query(cal.centre_px)
    assert len(set(j.tolist())) == cal.n_lenslets and d.max() < SPOT_PX
    err = np.abs(cal.focal_spot_px - true.focal_spot_px[j])
    assert err.max() < SPOT_PX, err.max()
    assert abs(cal.image_distance - cam.image_distance) < 0.02e-3
