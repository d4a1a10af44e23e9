"""Bad input from Python (issue #14): the library refuses it with the figure that gave it away.

Images (saturation at the data's own ceiling, complex, negative background, pure noise),
calibration-camera consistency (and old calibration files), volume sizes, argument checks of
the correlation, the vectors product and the simulator, output paths.
"""

from __future__ import annotations

import json
import os

import h5py
import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.corrections import DepthCorrection
from plenopiv.camera.grid import VolumeGrid, volume_from_dict
from plenopiv.camera.model import load_camera
from plenopiv.config.experiment import Experiment, experiment_from_dict
from plenopiv.errors import (
    CalibrationError,
    ConfigError,
    ImageError,
    OutputError,
    PIVError,
    PlenopivWarning,
    ResourceError,
)
from plenopiv.products.files import check_output_path
from plenopiv.products.images import check_image, saturation
from plenopiv.products.jsonio import to_json
from plenopiv.products.vectors import VectorResult
from plenopiv.products.volume import VolumeResult
from plenopiv.workflow.experiment import experiment_calibration
from plenopiv.workflow.pair import correlate


def sparse_image(rng, shape=(120, 160), dtype=np.float64):
    img = np.zeros(shape)
    idx = rng.integers(0, img.size, img.size // 100)
    img.flat[idx] = rng.uniform(0.5, 1.0, len(idx))
    return img.astype(dtype)


# ---- images ----------------------------------------------------------------------------------


def test_saturation_is_measured_at_the_datas_own_ceiling(rng):
    img = (sparse_image(rng) * 3000).astype(np.uint16)
    assert saturation(img)[0] == 0.0                     # 3000 is no ceiling of its own
    img.flat[:img.size // 10] = 4095                     # 12-bit data in a 16-bit file
    frac, ceiling, what = saturation(img)
    assert frac == pytest.approx(0.1, abs=1e-3) and ceiling == 4095
    assert what == "12-bit data in uint16"
    with pytest.raises(ImageError, match=r"10\.0% of the pixels are at 4095 \(12-bit data"):
        check_image(img)
    f = sparse_image(rng).astype(np.float32) * 0.8
    f.flat[:f.size * 12 // 100] = 1.0                    # floats clipped at 1.0
    with pytest.raises(ImageError, match=r"12\.0% of the pixels are at 1 \(clipped floats\)"):
        check_image(f)
    # a little saturation is used, with a warning that gives the fraction
    f = sparse_image(rng) * 0.8
    f.flat[:f.size // 100] = 1.0
    with pytest.warns(PlenopivWarning, match=r"1\.00% of the pixels are at 1 \(clipped"):
        check_image(f)
    # the full scale of the dtype still counts; one bright pixel is no saturation
    u = (sparse_image(rng) * 60000).astype(np.uint16)
    u.flat[0] = 65535
    check_image(u)


def test_complex_negative_background_and_noise_are_refused(rng):
    img = sparse_image(rng)
    with pytest.raises(ImageError, match="complex values"):
        check_image(img + 1j * img)
    with pytest.raises(ImageError, match=r"negative background: median -0\.05"):
        check_image(img - 0.05)
    few = img.copy()
    few.flat[:few.size // 20] = -0.01                    # background subtraction noise
    with pytest.warns(PlenopivWarning, match=r"5\.0% of the pixels are negative"):
        out = check_image(few)
    assert out.min() == 0.0
    noise = rng.uniform(0, 1, (120, 160))
    with pytest.raises(ImageError, match=r"looks like pure noise.*rise only (0\.9|1\.0)\d times"):
        check_image(noise, particles=True)
    gauss = 100 + 5 * rng.standard_normal((120, 160))
    with pytest.raises(ImageError, match="pure noise"):
        check_image(gauss, particles=True)
    check_image(img, particles=True)                     # a sparse particle image is fine
    check_image(noise)                                   # calibration images: no noise test


def test_read_image_refuses_complex(tmp_path, rng):
    from plenopiv.products.images import read_image

    with h5py.File(tmp_path / "c.h5", "w") as fh:
        fh["image"] = sparse_image(rng) * (1 + 1j)
    with pytest.raises(ImageError, match="complex"):
        read_image(f"{tmp_path / 'c.h5'}:/image")


# ---- calibration and camera ------------------------------------------------------------------


def experiment(camera: str) -> Experiment:
    return experiment_from_dict({"camera": camera, "volume": {
        "x_mm": [-1, 1], "y_mm": [-1, 1], "z_mm": [-1, 1], "voxel_mm": 0.25}})


def test_calibration_records_its_camera_and_refuses_another(tmp_path):
    Calibration.from_camera(load_camera("small_test")).save(tmp_path / "cal_135.h5")
    with h5py.File(tmp_path / "cal_135.h5") as fh:
        made_for = json.loads(fh.attrs["camera"])
        assert made_for["main_lens"]["focal_length_mm"] == 135.0
        assert made_for["main_lens"]["image_distance_mm"] == 200.0
        assert made_for["microlens_array"]["rows"] == 41
        assert "f = 135 mm, S_i = 200 mm, 41 x 61 square" in fh.attrs["camera_summary"]
    # same sensor and lattice, another lens: refused, naming both cameras
    with pytest.raises(CalibrationError) as err:
        experiment_calibration(experiment("small_m1"), tmp_path / "cal_135.h5")
    msg = str(err.value)
    assert "'small test camera (41 x 61 lenslets)' (main lens f = 135 mm, S_i = 200 mm" in msg
    assert "'small camera, 50 mm lens at M = -1" in msg and "f = 50 mm, S_i = 100 mm" in msg
    assert "main lens focal length 135 mm ≠ 50 mm" in msg
    # its own camera is fine; the experiment's camera takes the calibrated S_i
    cal = experiment_calibration(experiment("small_test"), tmp_path / "cal_135.h5")
    assert cal.image_distance == pytest.approx(0.2)


def test_a_refocused_camera_needs_its_own_calibration(tmp_path):
    cam = load_camera("small_test")
    Calibration.from_camera(cam.with_image_distance(0.25)).save(tmp_path / "cal.h5")
    with pytest.raises(CalibrationError, match=r"calibrated S_i 250 mm against .* = 200"):
        experiment_calibration(experiment("small_test"), tmp_path / "cal.h5")
    # within 10 %: the calibration measures S_i, the camera file gives a nominal one
    Calibration.from_camera(cam.with_image_distance(0.205)).save(tmp_path / "near.h5")
    assert experiment_calibration(experiment("small_test"),
                                  tmp_path / "near.h5").image_distance == pytest.approx(0.205)


def test_old_calibration_files_stay_readable(tmp_path):
    path = tmp_path / "old.h5"
    Calibration.from_camera(load_camera("small_test")).save(path)
    with h5py.File(path, "r+") as fh:                    # as written before #14
        del fh.attrs["camera"]
        del fh.attrs["camera_summary"]
    cal = Calibration.load(path)
    assert cal.camera.main_lens.focal_length == pytest.approx(0.135)
    with pytest.raises(CalibrationError, match="135 mm ≠ 50 mm"):
        experiment_calibration(experiment("small_m1"), path)


def test_load_camera_refuses_what_is_not_a_name():
    for bad in (42, None, "", 3.5):
        with pytest.raises(ConfigError, match="expected a camera TOML file or a preset name"):
            load_camera(bad)


# ---- volume ----------------------------------------------------------------------------------


@pytest.mark.parametrize("volume, words", [
    ({"voxel_mm": 50}, "voxel_mm = 50 is larger than the box along x (6 mm"),
    ({"voxel_mm": [0.1, 0.1]}, "voxel_mm = [0.1, 0.1]: expected one number"),
    ({"voxel_mm": "fine"}, "voxel_mm = 'fine': expected a number or a list of 3 numbers"),
    ({"voxel_mm": 0.0006}, "voxels: expected at most 2e+09"),
    ({"shape": [10000, 10000, 10000]}, "is 1e+12 voxels"),
    ({"shape": [10, 10]}, "expected a list of 3 voxel counts"),
    ({"voxel_mm": 0.1, "z_mm": [float("-inf"), 3]}, "z_mm = [-inf, 3.0]: expected finite"),
    ({"voxel_mm": float("nan")}, "voxel_mm"),
    ({"voxel_mm": 0.1, "y_mm": [4.5, -4.5]}, "y_mm = [4.5, -4.5]: expected [lo, hi] with hi > lo"),
    ({"voxel_mm": 0.1, "x_mm": [2, 2]}, "x_mm = [2, 2]: expected [lo, hi] with hi > lo"),
])
def test_volume_errors_say_what_is_wrong(volume, words):
    cfg = {"x_mm": [-3, 3], "y_mm": [-3, 3], "z_mm": [-3, 3], **volume}
    with pytest.raises(ConfigError) as err:
        volume_from_dict(cfg)
    assert words in str(err.value)
    assert "-9223372036854775808" not in str(err.value)


def test_grids_beyond_memory_are_refused_before_estimating(monkeypatch):
    from plenopiv import resources

    monkeypatch.setattr(resources, "available_memory", lambda: 1 << 30)   # 1 GiB
    grid = VolumeGrid((0, 0, 0), (1e-4,) * 3, (800, 800, 800))
    with pytest.raises(ResourceError, match=r"5\.12e\+08 voxels needs about 15\.3 GiB of "
                                            r"memory but this machine has 1 GiB available"):
        resources.check_grid(grid)
    from plenopiv.reconstruction.build import weights_for

    cal = Calibration.from_camera(load_camera("small_test"))
    with pytest.raises(ResourceError, match="voxels needs about"):
        weights_for(cal, grid, experiment("small_test").reconstruction)
    with pytest.raises(ResourceError, match="1e\\+12 pixels needs about"):
        resources.check_sensor(load_camera("small_test").replace(
            sensor=load_camera("small_test").sensor.__class__(10 ** 6, 10 ** 6, 7.4e-6)))


def test_iterations_are_bounded():
    with pytest.raises(ConfigError, match=r"\[reconstruction\] iterations = 1000000000"):
        experiment_from_dict({"camera": "small_test", "volume": {
            "x_mm": [-1, 1], "y_mm": [-1, 1], "z_mm": [-1, 1], "voxel_mm": 0.25},
            "reconstruction": {"iterations": 10 ** 9}})


# ---- correlation and the vectors product -----------------------------------------------------


def volume(seed=0, shape=(8, 10, 12)):
    grid = VolumeGrid((0.0, 0.0, 0.0), (1e-4,) * 3, shape)
    v = np.random.default_rng(seed).random(shape).astype(np.float32)
    e = np.zeros((0, 3))
    return VolumeResult(v, grid, DepthCorrection(1.0, 1.0), e, e, np.zeros(0), e)


def test_correlate_checks_its_arguments():
    a = volume()
    with pytest.raises(PIVError, match="result_b is a NoneType: expected a VolumeResult"):
        correlate(a, None)
    with pytest.raises(PIVError, match="settings is a dict"):
        correlate(a, a, {"windows": 8})
    for dt in (0, -1e-3, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="expected a finite time > 0"):
            correlate(a, a, dt=dt)
    with pytest.raises(ConfigError, match="expected a time in seconds"):
        correlate(a, a, dt="1ms")


def test_vectors_with_a_bad_dt_are_never_made():
    n = (2, 2, 2)
    for dt in (0.0, -1e-3, float("nan")):
        with pytest.raises(ConfigError, match="VectorResult dt"):
            VectorResult(np.zeros(2), np.zeros(2), np.zeros(2), *(np.zeros(n),) * 3,
                         np.ones(n, bool), np.ones(n), dt=dt)


def test_piv_settings_errors_are_config_errors():
    volume = {"x_mm": [-1, 1], "y_mm": [-1, 1], "z_mm": [-1, 1], "voxel_mm": 0.25}
    with pytest.raises(ConfigError, match=r"\[piv\] windows.*edge must be at least 4 voxels"):
        experiment_from_dict({"camera": "small_test", "volume": volume,
                              "piv": {"windows": [[0, 0, 0]]}})
    with pytest.raises(ConfigError, match=r"\[piv\] passes"):
        experiment_from_dict({"camera": "small_test", "volume": volume,
                              "piv": {"windows": [[8, 8, 8], [8, 8, 8]], "passes": 1}})
    with pytest.raises(ConfigError, match=r"unknown key \[piv\] window; valid keys here: "
                                          r"broad_peaks, continuity, deformation"):
        experiment_from_dict({"camera": "small_test", "volume": volume,
                              "piv": {"window": [8, 8, 8]}})


# ---- the simulator's arguments --------------------------------------------------------------


def test_simulator_arguments_are_checked():
    from plenopiv.synthetic.flows import Uniform
    from plenopiv.synthetic.images import finish_image, focal_point_image, particle_image
    from plenopiv.synthetic.seeding import SeedingBox, random_particles, simulate_pair

    cam = load_camera("small_test")
    irr = np.ones((4, 4))
    for kw, words in (({"full_well": 0}, "full_well = 0"), ({"blur_px": -1}, "blur_px = -1"),
                      ({"read_noise": float("nan")}, "read_noise"),
                      ({"exposure": 0}, "exposure = 0")):
        with pytest.raises(ConfigError, match=words):
            finish_image(irr, **kw)
    with pytest.raises(ConfigError, match="rays_per_particle = 0"):
        particle_image(cam, [(0, 0, 0)], rays_per_particle=0)
    with pytest.raises(ConfigError, match="f_number = 0"):
        particle_image(cam, [(0, 0, 0)], f_number=0)
    with pytest.raises(ConfigError, match="f_number = 0"):
        focal_point_image(cam, f_number=0)
    box = SeedingBox((-1e-3, 1e-3), (-1e-3, 1e-3), (-1e-3, 1e-3))
    with pytest.raises(ConfigError, match="particle count = -1"):
        random_particles(box, -1, np.random.default_rng(0))
    for dt in (0.0, float("inf")):
        with pytest.raises(ConfigError, match="expected a finite time > 0"):
            simulate_pair(cam, Uniform((1.0, 0.0, 0.0)), dt=dt, box=box, n_particles=1,
                          rng=np.random.default_rng(0))


# ---- output paths -----------------------------------------------------------------------------


def test_output_paths_are_checked_before_work(tmp_path):
    a = tmp_path / "a.h5"
    a.write_bytes(b"input")
    link = tmp_path / "link.h5"
    os.link(a, link)                                      # the same file under another name
    with pytest.raises(OutputError, match="is the input"):
        check_output_path(link, suffixes=(".h5",), inputs=[str(a)])
    with pytest.raises(OutputError, match="is the input"):
        check_output_path(tmp_path / "sub" / ".." / "a.h5", suffixes=(".h5",),
                          inputs=[f"{a}:/image"])
    (tmp_path / "d.h5").mkdir()
    with pytest.raises(OutputError, match="is a folder"):
        check_output_path(tmp_path / "d.h5", suffixes=(".h5",))
    with pytest.raises(OutputError, match="is a file, not a folder"):
        check_output_path(a / "x.h5", suffixes=(".h5",))
    with pytest.raises(OutputError, match="is an existing file"):
        check_output_path(a, folder=True)
    with pytest.raises(OutputError, match="not a regular file"):
        check_output_path("/dev/null", suffixes=None)
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() != 0:                                 # root writes anywhere: /proc instead
        ro.chmod(0o500)
        with pytest.raises(OutputError, match="cannot create files"):
            check_output_path(ro / "x.h5", suffixes=(".h5",))
    with pytest.raises(OutputError, match="cannot create files in '/proc'"):
        check_output_path("/proc/x.h5", suffixes=(".h5",))
    assert check_output_path(tmp_path / "new" / "deeper" / "x.h5", suffixes=(".h5",)) \
        == tmp_path / "new" / "deeper" / "x.h5"
    assert not (tmp_path / "new").exists()                # nothing made by the check
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.h5", "d.h5", "link.h5", "ro"]


def test_json_text_is_always_valid():
    text = to_json({"s_i": float("nan"), "xs": np.array([1.0, np.inf])})
    assert json.loads(text) == {"s_i": None, "xs": [1.0, None]}
    assert "NaN" not in text and "Infinity" not in text


def test_prefer_small_pages_turns_numpy_huge_pages_off_unless_the_user_chose(monkeypatch):
    """The command and batch workers stop NumPy's huge-page advice (compaction stalls: the
    16 MP light field spent 33 of 40 s in the kernel); an explicit NUMPY_MADVISE_HUGEPAGE
    is the user's choice and stays."""
    from numpy._core.multiarray import _set_madvise_hugepage

    from plenopiv.resources import prefer_small_pages

    before = _set_madvise_hugepage(True)
    try:
        monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
        assert prefer_small_pages() is True
        assert _set_madvise_hugepage(True) is False            # it was off
        monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
        assert prefer_small_pages() is False
        assert _set_madvise_hugepage(True) is True             # left on
    finally:
        _set_madvise_hugepage(before)


@pytest.mark.parametrize("dataset", ["/lenslets/centre_px", "/lenslets/focal_spot_px"])
def test_a_nan_in_a_calibration_product_is_refused_naming_the_dataset(tmp_path, dataset):
    import h5py

    from plenopiv.calibration.model import Calibration
    from plenopiv.camera.model import load_camera
    from plenopiv.errors import CalibrationError

    path = tmp_path / "cal.h5"
    Calibration.from_camera(load_camera("small_test")).save(path)
    with h5py.File(path, "r+") as fh:
        fh[dataset][3, 1] = np.nan
    with pytest.raises(CalibrationError, match=f"{dataset} holds 1 NaN"):
        Calibration.load(path)
