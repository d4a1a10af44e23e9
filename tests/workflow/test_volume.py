"""One image -> volume -> particles -> depth corrections (thesis §5.1 geometry, reduced)."""

from __future__ import annotations

import dataclasses
import json

import h5py
import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import ExternalInterface, Sensor, load_camera
from plenopiv.cli import main
from plenopiv.errors import ConfigError, ImageError, ReconstructionError
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume

# the thesis's span (±10 mm) in 4 mm steps; per-particle depth errors of ~0.08 mm (two thirds
# of a voxel) then leave the fitted slope uncertain by about ±0.005
DEPTHS = np.arange(-10e-3, 10.1e-3, 4e-3)


@pytest.fixture(scope="module")
def camera_50mm():
    """The Auburn optics with the 50 mm lens at M = -1 on a 41 × 41-lenslet patch."""
    a = load_camera("auburn_50mm")
    mla = dataclasses.replace(a.microlens_array, rows=41, cols=41, substrate=None)
    return a.replace(sensor=Sensor(700, 700, 7.4e-6), microlens_array=mla)


def thesis_grid(half_xy=1.5625e-3, depth=10.5e-3):
    """0.125 mm voxels (one lenslet footprint at M = -1), aligned with the footprints."""
    return VolumeGrid.from_bounds((-half_xy, half_xy), (-half_xy, half_xy), (-depth, depth),
                                  voxel=0.125e-3)


def reconstructed_depths(cam, depths, grid, tmp_cache):
    cal = Calibration.from_camera(cam)
    found, lateral = [], []
    for z in depths:
        img = particle_image(cam, [(0.0, 0.0, z)], rays_per_particle=20000)
        res = reconstruct_volume(cal, img, grid, cache_dir=tmp_cache)
        assert len(res.particle_position) >= 1
        found.append((res.particle_position_effective[0, 2], res.particle_position[0, 2]))
        lateral.append(np.abs(res.particle_position[0, :2]).max() / grid.voxel[0])
    return np.array(found), np.array(lateral)


def test_single_particle_depth_no_interface(camera_50mm, tmp_path):
    """Thesis Table 5.1 'without refraction' (slope 0.9925): slope within 0.01 of 1, lateral
    error ≤ 0.1 voxel for an on-axis particle."""
    found, lateral = reconstructed_depths(camera_50mm, DEPTHS, thesis_grid(), tmp_path)
    slope, icpt = np.polyfit(DEPTHS, found[:, 1], 1)
    assert abs(slope - 1) <= 0.01, slope
    assert abs(icpt) <= 0.125e-3                       # within one voxel
    assert lateral.max() <= 0.1


def test_external_interface_depth_and_correction(camera_50mm, tmp_path):
    """Water (n1 = 1.33) 40 mm deep in front of the focal plane: effective depths compress by
    n2/n1 (Eq. 4.7, slope 1/1.33 ± 0.02), and the correction restores slope 1.000 ± 0.015
    with every depth within 0.3 mm.

    The reconstruction subdivides the footprint voxels laterally (``lateral_subdivision =
    "auto"``): the largest single-depth error falls from 0.68 mm (no subdivision, slope
    1.006) to 0.21 mm (slope 0.990); over six depths the slope moves by ±0.01 with the
    error at the two ends, so it is bounded by 0.015 and each depth by 0.3 mm.
    """
    cam = camera_50mm.replace(external_interface=ExternalInterface(1.33, 1.0, 0.04))
    found, _ = reconstructed_depths(cam, DEPTHS, thesis_grid(), tmp_path)
    raw_slope = np.polyfit(DEPTHS, found[:, 0], 1)[0]
    corrected_slope = np.polyfit(DEPTHS, found[:, 1], 1)[0]
    assert raw_slope == pytest.approx(1 / 1.33, abs=0.02)
    assert corrected_slope == pytest.approx(1.0, abs=0.015)
    assert np.abs(found[:, 1] - DEPTHS).max() <= 0.3e-3


def test_bad_inputs(camera_50mm, tmp_path):
    cal = Calibration.from_camera(camera_50mm)
    grid = thesis_grid(depth=2e-3)
    img = particle_image(camera_50mm, [(0.0, 0.0, 0.0)], rays_per_particle=2000)
    with pytest.raises(ImageError, match="NaN"):
        bad = img.copy()
        bad[3, 3] = np.nan
        reconstruct_volume(cal, bad, grid)
    with pytest.raises(ImageError, match="all dark"):
        reconstruct_volume(cal, np.zeros_like(img), grid)
    with pytest.raises(ImageError, match="camera's sensor"):
        reconstruct_volume(cal, img[:-1], grid)
    with pytest.raises(ReconstructionError, match="outside the field of view"):
        far = VolumeGrid.from_bounds((40e-3, 41e-3), (0, 1e-3), (-1e-3, 1e-3), voxel=0.25e-3)
        reconstruct_volume(cal, img, far)
    with pytest.raises(ValueError, match="iterations"):
        ReconstructionSettings(iterations=-1)
    from plenopiv.config.experiment import experiment_from_dict

    with pytest.raises(ConfigError, match="unknown key .reconstruction. iteration;.*iterations"):
        experiment_from_dict({"camera": "small_test", "reconstruction": {"iteration": 3},
                              "volume": {"x_mm": [-1, 1], "y_mm": [-1, 1], "z_mm": [-1, 1],
                                         "voxel_mm": 0.25}})
    with pytest.raises(ConfigError, match="at least one voxel|voxel_mm"):
        experiment_from_dict({"camera": "small_test", "volume": {
            "x_mm": [-1, 1], "y_mm": [-1, 1], "z_mm": [-1, 1], "shape": [0, 4, 4]}})


def test_cli_reconstruct_product(tmp_path, capsys, small_camera):
    cal = Calibration.from_camera(small_camera)
    cal.save(tmp_path / "cal.h5")
    img = particle_image(small_camera, [(0.3e-3, -0.2e-3, 1e-3), (-0.5e-3, 0.4e-3, -2e-3)],
                         rays_per_particle=8000)
    from plenopiv.products.images import write_image

    write_image(tmp_path / "img.tif", (img / img.max() * 60000).astype(np.uint16))
    (tmp_path / "exp.toml").write_text('camera = "small_test"\n[volume]\nx_mm = [-1.5, 1.5]\n'
                                       'y_mm = [-1.5, 1.5]\nz_mm = [-4, 4]\n'
                                       'voxel_mm = [0.13, 0.13, 0.25]\n')
    out = tmp_path / "vol.h5"
    code = main(["reconstruct", str(tmp_path / "cal.h5"), str(tmp_path / "img.tif"), "--config",
                 str(tmp_path / "exp.toml"), "--out", str(out), "--json"])
    s = json.loads(capsys.readouterr().out)
    assert code == 0 and s["n_particles"] >= 2
    with h5py.File(out) as fh:
        assert fh["/volume"].dtype == np.float32
        assert fh["/volume"].shape == (len(fh["/z"]), len(fh["/y"]), len(fh["/x"]))
        assert fh["/particles/position_m"].shape[1] == 3
        assert fh["/x"].attrs["units"] == "m"
        assert json.loads(fh.attrs["config"])["volume"]["shape"] == list(fh["/volume"].shape)
    # another camera's calibration is refused, nothing written
    other = Calibration.from_camera(load_camera("auburn_135mm"))
    other.save(tmp_path / "other.h5")
    code = main(["reconstruct", str(tmp_path / "other.h5"), str(tmp_path / "img.tif"),
                 "--config", str(tmp_path / "exp.toml"), "--out", str(tmp_path / "v2.h5")])
    err = capsys.readouterr().err
    assert code == 2 and "was made for camera 'Auburn" in err
    assert "sensor 3280 × 4904 px ≠ 700 × 1040 px" in err
    assert not (tmp_path / "v2.h5").exists()
