"""The lenslet pitch of a fitted lattice, whatever its packing, and every calibration path
that compares it with the camera file's pitch.

On a hexagonal lattice the row spacing is sqrt(3)/2 of the lenslet pitch; the mean of the
two spacings (7 % short) once made the focal-point method refuse every hexagonal camera
calibrated without an alignment image ("the focal spots are 15.8 px apart and the lenslets
16.89 px").
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.lattice_fit import fit_lattice
from plenopiv.calibration.spot_detection import detect_spots
from plenopiv.synthetic.images import alignment_image, finish_image, focal_point_image

PACKINGS = [("square", 0.0), ("square", 2e-3), ("hexagonal", 0.0), ("hexagonal", 1e-3)]


def _camera(small_camera, grid, rotation):
    patch = small_camera.patch(21, 31, margin_px=12)
    mla = dataclasses.replace(patch.microlens_array, grid=grid, rotation=rotation)
    return patch.replace(microlens_array=mla)


@pytest.mark.parametrize(("grid", "rotation"), PACKINGS)
def test_the_lenslet_pitch_is_the_distance_between_neighbours(small_camera, grid, rotation):
    cam = _camera(small_camera, grid, rotation)
    img = alignment_image(cam)
    lat = fit_lattice(detect_spots(img))
    assert lat.grid == grid
    # collimated light: the spots lie under the lenslets, one lenslet pitch apart
    assert lat.lenslet_pitch_px == pytest.approx(cam.pitch_px, rel=2e-3)
    if grid == "hexagonal":
        assert lat.pitch_px[0] == pytest.approx(cam.pitch_px * math.sqrt(3) / 2, rel=2e-3)
    assert lat.quality["lenslet_pitch_px"] == lat.lenslet_pitch_px


@pytest.mark.parametrize("with_alignment", [False, True])
@pytest.mark.parametrize(("grid", "rotation"), PACKINGS)
def test_every_packing_calibrates_by_the_focal_point_method(small_camera, grid, rotation,
                                                            with_alignment):
    """S_i within three of its reported standard errors (about 0.05 mm on this 21 x 31 patch),
    every lenslet found, from the focal-point image alone (the nominal lattice's pitch) and
    with an alignment image."""
    cam = _camera(small_camera, grid, rotation)
    rng = np.random.default_rng(3)
    fp = finish_image(focal_point_image(cam, f_number=16, psf_px=0.5), noise="poisson",
                      rng=rng)
    al = finish_image(alignment_image(cam), noise="poisson", rng=rng) if with_alignment \
        else None
    user = cam.replace(main_lens=dataclasses.replace(cam.main_lens, image_distance=None))
    rep = calibrate(user, fp, alignment_image=al, method="focal-point",
                    focal_point_f_number=16)
    assert rep.calibration.n_lenslets == cam.microlens_array.count
    sigma_m = rep.summary()["focal_point"]["sigma_mm"] * 1e-3
    assert 0 < sigma_m < 0.1e-3
    assert abs(rep.calibration.image_distance - cam.image_distance) < 3 * sigma_m
