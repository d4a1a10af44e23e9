"""Pair pipeline and the vectors product: two images -> volumes -> vectors (HDF5, VTK, PNG)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.cli import main
from plenopiv.config import Experiment, ImagesConfig, OutputConfig, PIVConfig
from plenopiv.pipeline import process_pair, save_pair
from plenopiv.synthetic.flows import Uniform
from plenopiv.synthetic.seeding import SeedingBox, simulate_pair
from plenopiv.validation.vortex import VortexCase, aligned_grid


@pytest.fixture(scope="module")
def pair_products(tmp_path_factory):
    from plenopiv.camera import load_camera

    cam = load_camera("small_m1")
    cal = Calibration.from_camera(cam)
    grid = aligned_grid(cam, VortexCase(depth=2e-3, lateral_fill=0.5))
    rng = np.random.default_rng(7)
    box = SeedingBox(tuple(grid.bounds[0]), tuple(grid.bounds[1]), (-2e-3, 2e-3))
    shift = np.array([0.25e-3, -0.125e-3, 0.0])       # 2 and 1 lateral voxels
    pair = simulate_pair(cam, Uniform(tuple(shift / 1e-3)), dt=1e-3, box=box, n_particles=60,
                         rng=rng, rays_per_particle=1024)
    out = tmp_path_factory.mktemp("pair")
    exp = Experiment(camera=cam, volume=grid, piv=PIVConfig(windows=[(16, 16, 16)], passes=2),
                     images=ImagesConfig(dt_s=1e-3),
                     output=OutputConfig(directory=str(out), weights_cache=""), base_dir=out)
    res = process_pair(cal, pair.image_a, pair.image_b, exp)
    paths = save_pair(res, out, "p", exp)
    return res, paths, shift, grid


def test_uniform_shift_is_measured(pair_products):
    res, _, shift, grid = pair_products
    vec = res.vectors
    ok = vec.valid
    assert ok.mean() > 0.5
    # lateral components: within half a voxel of the imposed shift (velocity = shift / dt)
    assert np.median(vec.u[ok]) == pytest.approx(shift[0], abs=0.5 * grid.voxel[0])
    assert np.median(vec.v[ok]) == pytest.approx(shift[1], abs=0.5 * grid.voxel[1])
    assert abs(np.median(vec.w[ok])) < grid.voxel[2]
    assert vec.dt == 1e-3


def test_vectors_product_opens_in_xarray_and_paraview(pair_products):
    import xarray as xr   # a test dependency (pyproject [test]), with h5netcdf

    _, paths, shift, _ = pair_products
    ds = xr.open_dataset(paths["vectors"], engine="h5netcdf", phony_dims="access")
    assert set(ds["u"].dims) == {"z", "y", "x"}
    assert ds["u"].attrs["units"] == "m s-1" and ds.attrs["quantity"] == "velocity"
    assert bool(ds.attrs["complete"])
    assert json.loads(ds.attrs["config"])["volume"]["shape"] == list(
        ds["u"].shape[:0] or json.loads(ds.attrs["config"])["volume"]["shape"])
    ds.close()
    vti = paths["vtk"]
    text = open(vti, "rb").read(400)
    assert b"VTKFile" in text and b"ImageData" in text


def test_piv_cli_on_volume_products(pair_products, tmp_path, capsys):
    _, paths, shift, _ = pair_products
    out = tmp_path / "v.h5"
    code = main(["piv", paths["volume_A"], paths["volume_B"], "--out", str(out),
                 "--windows", "16", "16", "16", "--json", "--no-png"])
    s = json.loads(capsys.readouterr().out)
    assert code == 0 and s["quantity"] == "displacement" and s["valid_fraction"] > 0.5
    code = main(["piv", paths["volume_A"], str(tmp_path / "missing.h5"), "--out",
                 str(tmp_path / "x.h5")])
    assert code == 2 and "not found" in capsys.readouterr().err


def test_plenopiv_run_batch_with_resume(tmp_path, capsys):
    """`plenopiv run`: two pairs on a real LocalCluster; a second run skips both."""
    from plenopiv.camera import load_camera

    cam = load_camera("small_m1")
    Calibration.from_camera(cam).save(tmp_path / "cal.h5")
    (tmp_path / "pairs").mkdir()
    for i in (1, 2):
        assert main(["simulate", "pair", "small_m1", "--n-particles", "30",
                     "--rays-per-particle", "256", "--depth-mm", "-1.5", "1.5", "--fill", "0.4",
                     "--seed", str(i), "--no-tiff", "--quiet",
                     "--out", str(tmp_path / "pairs" / f"run_{i}.h5")]) == 0
    (tmp_path / "exp.toml").write_text(
        'camera = "small_m1"\n[volume]\nx_mm = [-1.0625, 1.0625]\ny_mm = [-1.0625, 1.0625]\n'
        'z_mm = [-1.5, 1.5]\nvoxel_mm = 0.125\n'
        # explicit weights on the volume's own grid, so that the second run finds them cached
        # (a subdivided grid takes the matrix-free projector, which is never cached)
        '[reconstruction]\nlateral_subdivision = 1\n'
        '[piv]\nwindows = [[12, 12, 12]]\npasses = 2\n'
        '[images]\npairs = "pairs/*.h5"\ncalibration = "cal.h5"\ndt_s = 1e-3\n'
        '[output]\ndirectory = "out"\npng = false\nvtk = false\n')
    capsys.readouterr()
    assert main(["run", str(tmp_path / "exp.toml"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert sorted(s["done"]) == ["run_1", "run_2"] and s["n_failed"] == 0
    assert (tmp_path / "out" / "run_1_vectors.h5").exists()
    assert main(["run", str(tmp_path / "exp.toml"), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert sorted(s["skipped"]) == ["run_1", "run_2"] and s["weights_from_cache"]
