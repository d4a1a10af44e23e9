"""Calibration pipeline and `plenopiv calibrate`: images in, calibration product out."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.model import Calibration
from plenopiv.cli import main
from plenopiv.errors import CalibrationError, ImageError, PlenopivWarning
from plenopiv.products.images import write_image
from plenopiv.synthetic.images import (
    Ruler,
    alignment_image,
    finish_image,
    focal_point_image,
    ruler_image,
)

SI = 0.21
OFFSET, ROTATION = (4e-6, -3e-6), 1e-3


@pytest.fixture(scope="module")
def truth(small_camera):
    mla = dataclasses.replace(small_camera.microlens_array, offset=OFFSET, rotation=ROTATION)
    return small_camera.replace(microlens_array=mla).with_image_distance(SI)


@pytest.fixture(scope="module")
def images(truth):
    rng = np.random.default_rng(5)
    fp = finish_image(focal_point_image(truth, f_number=16), noise="poisson", rng=rng)
    al = finish_image(alignment_image(truth), noise="poisson", rng=rng)
    ru = finish_image(ruler_image(truth, Ruler(1e-3), rays_per_lenslet=1000), noise="poisson",
                      rng=rng)
    return fp, al, ru


def test_calibration_recovers_si_misplacement_and_both_methods(small_camera, truth, images):
    fp, al, ru = images
    # the user's camera file knows neither S_i nor the misplacement
    rep = calibrate(small_camera, fp, ruler_image=ru, ruler_spacing=1e-3, method="both")
    f, m = rep.focal_fit, rep.magnification
    assert abs(f.image_distance - SI) <= 4 * f.sigma_image_distance
    assert f.sigma_image_distance < 0.2e-3
    assert np.abs(f.offset - OFFSET).max() < 0.3e-6
    assert abs(f.rotation - ROTATION) < 20e-6
    assert abs(m.image_distance - SI) <= m.sigma_image_distance
    cal = rep.calibration
    assert cal.n_lenslets == 41 * 61 and rep.n_missing == 0
    # with the alignment image the lenslet centres are measured: no misplacement is left
    rep2 = calibrate(small_camera, fp, alignment_image=al)
    assert abs(rep2.focal_fit.image_distance - SI) <= 4 * rep2.focal_fit.sigma_image_distance
    assert np.abs(rep2.focal_fit.offset).max() < 0.3e-6
    assert rep2.lenslet_source == "alignment image"


def test_missing_third_of_spots_is_flagged_or_refused(small_camera, images):
    fp = images[0].copy()
    fp[:, : fp.shape[1] // 3] = 0          # the left third of the spots is gone
    with pytest.raises(CalibrationError, match="have no focal spot"):
        calibrate(small_camera, fp, max_missing_fraction=0.25)
    rep = calibrate(small_camera, fp, max_missing_fraction=0.5)
    assert rep.n_missing > 0.25 * 41 * 61
    assert any("missing" in n for n in rep.notes)
    assert abs(rep.focal_fit.image_distance - SI) < 1e-3


def test_bad_images_are_clear_errors(small_camera, images):
    fp = images[0]
    with pytest.raises(ImageError, match="camera's sensor is 700 × 1040"):
        calibrate(small_camera, fp[:-10])
    with pytest.raises(ImageError, match="all dark"):
        calibrate(small_camera, np.zeros_like(fp))
    nan = fp.astype(float)
    nan[5, 7] = np.nan
    with pytest.raises(ImageError, match="NaN"):
        calibrate(small_camera, nan)
    with pytest.raises(ImageError, match="saturated"):
        calibrate(small_camera, np.full_like(fp, 65535))
    with pytest.raises(CalibrationError, match="ruler ticks"), \
            pytest.warns(PlenopivWarning, match="focal-point image and the ruler image are "
                                                "identical"):
        calibrate(small_camera, fp, ruler_image=fp, ruler_spacing=1e-3, method="both")


def test_cli_calibrate_product_and_json(tmp_path, capsys, images):
    fp, al, ru = images
    for name, img in (("fp.tif", fp), ("al.tif", al), ("ru.tif", ru)):
        write_image(tmp_path / name, img)
    out = tmp_path / "cal.h5"
    code = main(["calibrate", "small_test", "--focal-point", str(tmp_path / "fp.tif"),
                 "--alignment", str(tmp_path / "al.tif"), "--ruler", str(tmp_path / "ru.tif"),
                 "--ruler-spacing-mm", "1", "--method", "both", "--out", str(out), "--json"])
    s = json.loads(capsys.readouterr().out)
    assert code == 0
    for key in ("image_distance_mm", "method", "offset_um", "rotation_rad", "rms_residual_px",
                "n_lenslets", "n_missing"):
        assert key in s
    assert s["image_distance_mm"] == pytest.approx(SI * 1e3, abs=0.5)
    cal = Calibration.load(out)
    assert cal.image_distance == pytest.approx(s["image_distance_mm"] * 1e-3)
    assert cal.centre_px.shape == (41 * 61, 2) and cal.grid_index.dtype.kind == "i"
    assert (tmp_path / "cal.png").stat().st_size > 10_000


def test_cli_calibrate_refuses_wrong_image_size(tmp_path, capsys, images):
    write_image(tmp_path / "fp.tif", images[0][:, :-8])
    code = main(["calibrate", "small_test", "--focal-point", str(tmp_path / "fp.tif"),
                 "--out", str(tmp_path / "cal.h5")])
    err = capsys.readouterr().err
    assert code == 2 and "700 × 1032 pixels but the camera's sensor is 700 × 1040" in err
    assert not (tmp_path / "cal.h5").exists()


def test_calibration_product_load_errors(tmp_path):
    with pytest.raises(CalibrationError, match="not found"):
        Calibration.load(tmp_path / "nope.h5")
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(CalibrationError, match="corrupt"):
        Calibration.load(tmp_path / "bad.h5")


def test_calibration_keeps_si_in_its_camera_alone(tmp_path, small_camera):
    import h5py

    cal = Calibration.from_camera(small_camera.with_image_distance(0.21))
    assert cal.image_distance == cal.camera.image_distance == 0.21
    assert cal.effective_camera is cal.camera
    # another description of the camera (its nominal S_i) takes the calibrated one
    moved = cal.with_camera(small_camera)
    assert small_camera.image_distance == 0.2 and moved.image_distance == 0.21
    assert np.array_equal(moved.focal_spot_px, cal.focal_spot_px)
    # the product's S_i is its image_distance_m attribute, read back to the bit, also from a
    # file written before the camera attribute whose config camera gives no S_i
    path = cal.save(tmp_path / "cal.h5")
    assert Calibration.load(path).image_distance == 0.21
    with h5py.File(path, "r+") as fh:
        del fh.attrs["camera"]
        cfg = json.loads(fh.attrs["config"])
        del cfg["camera"]["main_lens"]["image_distance_mm"]
        fh.attrs["config"] = json.dumps(cfg)
    old = Calibration.load(path)
    assert old.image_distance == 0.21 and old.camera.main_lens.focal_length == 0.135
    with pytest.raises(CalibrationError, match="no image distance"):
        Calibration(camera=small_camera.replace(
            main_lens=dataclasses.replace(small_camera.main_lens, image_distance=None)),
            centre_px=cal.centre_px, focal_spot_px=cal.focal_spot_px,
            grid_index=cal.grid_index, method="model")
