"""Image I/O and product writing: formats, clear errors, atomic writes."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from plenopiv.errors import ImageError
from plenopiv.products.files import atomic_path
from plenopiv.products.hdf5 import write_h5
from plenopiv.products.images import check_image, read_image, write_image


def test_tiff_and_h5_round_trip_without_flips(tmp_path, rng):
    img = rng.integers(0, 4000, (30, 40)).astype(np.uint16)
    write_image(tmp_path / "a.tif", img)
    assert np.array_equal(read_image(tmp_path / "a.tif"), img)
    write_h5(tmp_path / "p.h5", {"/image_a": img, "/x/y": img.T}, units={"/x/y": "m"})
    assert np.array_equal(read_image(f"{tmp_path / 'p.h5'}:/image_a"), img)
    assert np.array_equal(read_image(tmp_path / "p.h5"), img)      # default /image_a
    assert np.array_equal(read_image(f"{tmp_path / 'p.h5'}:/x/y"), img.T)


def test_truncated_and_missing_files_are_clear_errors(tmp_path, rng):
    img = rng.integers(0, 4000, (64, 64)).astype(np.uint16)
    p = tmp_path / "t.tif"
    tifffile.imwrite(p, img)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 3])
    with pytest.raises(ImageError, match="corrupt or truncated"):
        read_image(p)
    with pytest.raises(ImageError, match="not found"):
        read_image(tmp_path / "none.tif")
    write_h5(tmp_path / "q.h5", {"/a": img})
    with pytest.raises(ImageError, match="no image dataset '/b'.*datasets: /a"):
        read_image(f"{tmp_path / 'q.h5'}:/b")


def test_check_image_rejects_bad_images():
    good = np.zeros((10, 12), np.uint16)
    good[3, 4] = 100
    assert check_image(good, shape=(10, 12)).dtype == np.float64
    with pytest.raises(ImageError, match="10 × 12 pixels but the camera's sensor is 11 × 12"):
        check_image(good, shape=(11, 12))
    nan = good.astype(float)
    nan[2, 3] = np.nan
    with pytest.raises(ImageError, match="1 NaN/inf pixels .*row 2, col 3"):
        check_image(nan)
    with pytest.raises(ImageError, match="all dark"):
        check_image(np.zeros((5, 5)))
    sat = np.full((10, 10), 65535, np.uint16)
    sat[0, 0] = 3
    with pytest.raises(ImageError, match="saturated"):
        check_image(sat)
    with pytest.raises(ImageError, match="2-D"):
        check_image(np.zeros((2, 3, 4)))


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.h5"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("crash while writing")
    assert not any(tmp_path.iterdir())


def test_products_are_checked_for_kind_and_completeness(tmp_path):
    """A volume file read as a calibration, a truncated or incomplete product: each a clear
    error naming the file, from the one product reader."""
    import h5py

    from plenopiv.calibration.model import Calibration
    from plenopiv.errors import CalibrationError, ReconstructionError
    from plenopiv.products.volume import load_volume

    with h5py.File(tmp_path / "v.h5", "w") as fh:
        fh.attrs["product"] = "volume"          # the attribute, none of the datasets
    with pytest.raises(CalibrationError, match=r"v\.h5.*not a plenopiv calibration file"):
        Calibration.load(tmp_path / "v.h5")
    with pytest.raises(ReconstructionError, match=r"volume file .*v\.h5.*corrupt or incomplete"):
        load_volume(tmp_path / "v.h5")
    (tmp_path / "t.h5").write_bytes(b"\x89HDF\r\n\x1a\n truncated")
    with pytest.raises(ReconstructionError, match="corrupt or incomplete"):
        load_volume(tmp_path / "t.h5")
    with pytest.raises(ReconstructionError, match="not found"):
        load_volume(tmp_path / "missing.h5")


@pytest.mark.parametrize("inside", ["presets/small_test.toml", "camera/model.py", "new.h5"])
def test_nothing_is_written_inside_the_installed_package(inside):
    from plenopiv.errors import OutputError
    from plenopiv.products.files import PACKAGE_DIR, check_output_path

    with pytest.raises(OutputError, match="inside the installed plenopiv package"):
        check_output_path(PACKAGE_DIR / inside)


def test_presets_out_refuses_the_package_s_own_preset(capsys):
    from plenopiv.cli import main
    from plenopiv.products.files import PACKAGE_DIR

    preset = PACKAGE_DIR / "presets" / "small_test.toml"
    before = preset.read_bytes()
    assert main(["presets", "small_test", "--out", str(preset)]) == 2
    assert "inside the installed plenopiv package" in capsys.readouterr().err
    assert preset.read_bytes() == before


@pytest.mark.parametrize("dt", [1e-250, 1e-300])
def test_a_dt_that_overflows_the_velocities_is_refused_by_name(dt):
    from plenopiv.errors import ConfigError
    from plenopiv.products.vectors import VectorResult

    n = (2, 2, 2)
    with pytest.raises(ConfigError, match=r"dt = .* velocities of"):
        VectorResult(np.arange(2.0), np.arange(2.0), np.arange(2.0), *(np.full(n, 1e-3),) * 3,
                     np.ones(n, bool), np.ones(n), dt=dt)
