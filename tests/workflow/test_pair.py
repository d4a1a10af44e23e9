"""Pair pipeline and the vectors product: two images -> volumes -> vectors (HDF5, VTK, PNG)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.cli import main
from plenopiv.config.experiment import Experiment, ImagesConfig, OutputConfig
from plenopiv.piv.settings import PIVSettings
from plenopiv.synthetic.flows import Uniform
from plenopiv.synthetic.seeding import SeedingBox, simulate_pair
from plenopiv.workflow.pair import process_pair, save_pair
from plenopiv.workflow.vortex_case import VortexCase, aligned_grid


@pytest.fixture(scope="module")
def pair_products(tmp_path_factory):
    from plenopiv.camera.model import load_camera

    cam = load_camera("small_m1")
    cal = Calibration.from_camera(cam)
    grid = aligned_grid(cam, VortexCase(depth=2e-3, lateral_fill=0.5))
    rng = np.random.default_rng(7)
    box = SeedingBox(tuple(grid.bounds[0]), tuple(grid.bounds[1]), (-2e-3, 2e-3))
    shift = np.array([0.25e-3, -0.125e-3, 0.0])       # 2 and 1 lateral voxels
    pair = simulate_pair(cam, Uniform(tuple(shift / 1e-3)), dt=1e-3, box=box, n_particles=60,
                         rng=rng, rays_per_particle=1024)
    out = tmp_path_factory.mktemp("pair")
    exp = Experiment(camera=cam, volume=grid, piv=PIVSettings(windows=[(16, 16, 16)], passes=2),
                     images=ImagesConfig(dt_s=1e-3),
                     output=OutputConfig(directory=str(out), weights_cache=""), base_dir=out)
    res = process_pair(cal, pair.image_a, pair.image_b, exp)
    paths = save_pair(res, out, "p", exp)
    return res, paths, shift, grid, (cal, pair, exp)


def test_uniform_shift_is_measured(pair_products):
    res, _, shift, grid, _ = pair_products
    vec = res.vectors
    ok = vec.valid
    assert ok.mean() > 0.5
    # lateral components: within half a voxel of the imposed shift (velocity = shift / dt)
    assert np.median(vec.u[ok]) == pytest.approx(shift[0], abs=0.5 * grid.voxel[0])
    assert np.median(vec.v[ok]) == pytest.approx(shift[1], abs=0.5 * grid.voxel[1])
    assert abs(np.median(vec.w[ok])) < grid.voxel[2]
    assert vec.dt == 1e-3


def test_vectors_product_opens_in_xarray_and_paraview(pair_products):
    import xarray as xr  # a test dependency (pyproject [test]), with h5netcdf

    _, paths, shift, _, _ = pair_products
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
    _, paths, shift, _, _ = pair_products
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
    from plenopiv.camera.model import load_camera

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

    # issue #14: the [piv] windows change -> both pairs recomputed, and the summary says why;
    # a killed write's temporary of a volume is removed
    exp = tmp_path / "exp.toml"
    exp.write_text(exp.read_text().replace("[[12, 12, 12]]", "[[16, 16, 16]]"))
    (tmp_path / "out" / ".run_1_volume_A.h5.k1ll3d00.part").write_bytes(b"half")
    assert main(["run", str(exp), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert sorted(s["done"]) == ["run_1", "run_2"] and s["n_recomputed"] == 2
    assert {r["reason"] for r in s["recomputed"]} == {"made with other settings"}
    assert any(p.endswith(".run_1_volume_A.h5.k1ll3d00.part") for p in s["removed_parts"])

    # a corrupt pair among good ones: it fails alone, and `plenopiv run` exits 1 naming it
    (tmp_path / "pairs" / "run_3.h5").write_bytes(b"\x89HDF\r\n\x1a\n truncated")
    code = main(["run", str(exp), "--json"])
    out, err = capsys.readouterr()
    s = json.loads(out)
    assert code == 1 and "Traceback" not in err
    # (after the warnings on the experiment's settings: footprint voxels without subdivision)
    assert err.splitlines()[-1].startswith("error: 1 of 3 pairs failed: run_3 (")
    assert s["error"].startswith("1 of 3 pairs failed") and s["exit_status"] == 1
    assert sorted(s["skipped"]) == ["run_1", "run_2"] and s["failed"][0]["name"] == "run_3"

def test_vectors_product_quality_and_uncertainty(pair_products):
    """Per-vector uncertainty (units of u) and quality in the HDF5 (xarray) and the .vti."""
    import xarray as xr

    res, paths, _, _, _ = pair_products
    with xr.open_dataset(paths["vectors"], engine="h5netcdf", phony_dims="access") as ds:
        for name in ("u_uncertainty", "v_uncertainty", "w_uncertainty", "peak_ratio",
                     "peak_height", "flag", "replaced", "valid"):
            assert ds[name].dims == ("z", "y", "x"), name
        for c in "uvw":
            assert ds[f"{c}_uncertainty"].attrs["units"] == ds[c].attrs["units"] == "m s-1"
            sig = ds[f"{c}_uncertainty"].values
            assert np.all(np.isfinite(sig[ds["valid"].values == 1])) and np.all(sig >= 0)
            # the product holds velocities: the uncertainty of the displacement over dt
            np.testing.assert_allclose(sig, getattr(res.vectors, f"{c}_uncertainty") / 1e-3,
                                       rtol=1e-5)
        assert np.all(ds["peak_ratio"].values >= 1) and ds["peak_ratio"].attrs["units"] == "1"
        np.testing.assert_array_equal(ds["peak_ratio"].values, ds["snr"].values)
        assert np.all(ds["peak_height"].values <= 1.0)
        assert ds.attrs["uncertainty_method"] == "response"
        assert np.array_equal(ds["flag"].values == 0, ds["valid"].values == 1)
    text = open(paths["vtk"], "rb").read()
    for name in (b"velocity", b"u_uncertainty", b"w_uncertainty", b"peak_ratio",
                 b"peak_height", b"flag", b"replaced", b"valid"):
        assert b'Name="' + name + b'"' in text, name


def test_volume_product_opens_in_xarray_with_coordinates(pair_products):
    import xarray as xr

    res, paths, _, grid, _ = pair_products
    with xr.open_dataset(paths["volume_A"], engine="h5netcdf", phony_dims="access") as ds:
        assert ds["volume"].dims == ("z", "y", "x")
        for axis in "xyz":
            assert axis in ds.coords and ds[axis].attrs["units"] == "m"
        np.testing.assert_allclose(ds["x"].values, grid.x)
        np.testing.assert_allclose(ds["z"].values, res.volume_a.z_corrected)
        assert ds["volume"].attrs["units"] == "1" and "image counts" in ds["volume"].attrs[
            "long_name"]
        assert ds["z_effective"].dims == ("z",)
        # selecting by coordinate works as a user expects
        assert ds["volume"].sel(z=0.0, method="nearest").shape == (grid.shape[1], grid.shape[2])
    with xr.open_dataset(paths["volume_A"], engine="h5netcdf", phony_dims="access",
                         group="particles") as p:
        assert p["intensity"].attrs["units"] == "1"
        assert p["position_m"].attrs["units"] == "m"
        assert p["centroid_effective_m"].attrs["units"] == "m"    # the volume's own estimate
    from plenopiv.products.volume import load_volume

    back = load_volume(paths["volume_A"])
    np.testing.assert_array_equal(back.particle_centroid_effective,
                                  res.volume_a.particle_centroid_effective)
    np.testing.assert_array_equal(back.particle_position_effective,
                                  res.volume_a.particle_position_effective)


def test_calibration_grid_index_has_units(tmp_path):
    import h5py

    from plenopiv.camera.model import load_camera

    path = Calibration.from_camera(load_camera("small_m1")).save(tmp_path / "cal.h5")
    with h5py.File(path) as fh:
        assert fh["/lenslets/grid_index"].attrs["units"] == "1"


def test_masked_vectors_in_the_pair_pipeline(pair_products):
    """A [mask] box over part of the volume: its vectors are NaN and flagged masked."""
    from dataclasses import replace

    from plenopiv.config.experiment import BoxMask, MaskConfig
    from plenopiv.piv import FLAG_MASKED

    _, _, shift, grid, (cal, pair, exp) = pair_products
    b = grid.bounds * 1e3
    box = BoxMask(x_mm=(0.0, b[0, 1]), y_mm=tuple(b[1]), z_mm=tuple(b[2]))
    exp = replace(exp, mask=MaskConfig(box=[box]),
                  piv=dataclasses.replace(exp.piv, uncertainty="correlation"))
    vec = process_pair(cal, pair.image_a, pair.image_b, exp).vectors
    masked = vec.x[None, None, :] >= -grid.voxel[0] / 2 + np.zeros(vec.u.shape)
    assert masked.any() and (~masked).any()
    assert np.all((vec.flag[masked] & FLAG_MASKED) != 0)
    assert np.all(np.isnan(vec.u[masked])) and not vec.valid[masked].any()
    assert np.all(np.isnan(vec.u_uncertainty[masked]))
    assert np.all(vec.flag[~masked] & FLAG_MASKED == 0)
    assert vec.uncertainty_method == "correlation"


def test_piv_cli_leaves_rejected_vectors_nan(pair_products, tmp_path, capsys):
    import h5py

    _, paths, _, _, _ = pair_products
    out = tmp_path / "none.h5"
    code = main(["piv", paths["volume_A"], paths["volume_B"], "--out", str(out),
                 "--windows", "12", "12", "12", "--replacement", "none", "--json", "--no-png",
                 "--no-vtk"])
    s = json.loads(capsys.readouterr().out)
    assert code == 0 and s["uncertainty_method"] == "correlation" and s["n_replaced"] == 0
    with h5py.File(out) as fh:
        valid = fh["valid"][()] == 1
        assert np.all(np.isnan(fh["u"][()][~valid])) and np.all(np.isfinite(fh["u"][()][valid]))
        assert np.all(fh["replaced"][()] == 0) and np.all(fh["flag"][()][~valid] > 0)
        assert fh.attrs["uncertainty_method"] == "correlation"


def test_a_worker_keeps_one_processor_and_its_projector(tmp_path, monkeypatch):
    """`plenopiv run`'s per-pair work: the experiment, calibration and projector are made with
    a worker's first pair and reused; a changed experiment file makes a new processor."""
    from plenopiv.camera.model import load_camera
    from plenopiv.workflow import pair, worker

    Calibration.from_camera(load_camera("small_m1")).save(tmp_path / "cal.h5")
    exp = tmp_path / "exp.toml"
    exp.write_text('camera = "small_m1"\n[volume]\nx_mm = [-1.0625, 1.0625]\n'
                   'y_mm = [-1.0625, 1.0625]\nz_mm = [-1.5, 1.5]\nvoxel_mm = 0.125\n')
    built = []
    monkeypatch.setattr(pair, "weights_for",
                        lambda *a, **k: (built.append(a) or object(), False))
    first = worker.worker_processor(exp, tmp_path / "cal.h5")
    assert worker.worker_processor(exp, tmp_path / "cal.h5") is first
    assert first.weights() is first.weights() and len(built) == 1
    exp.write_text(exp.read_text() + "\n[piv]\npasses = 2\n")
    second = worker.worker_processor(exp, tmp_path / "cal.h5")
    assert second is not first and second.experiment.piv.passes == 2
    worker.drop_worker_processor()           # dropped: the same files make a new one
    assert worker.worker_processor(exp, tmp_path / "cal.h5") is not second


def test_a_worker_sets_its_memory_up_by_the_allocator_settings_it_is_given(tmp_path,
                                                                           monkeypatch):
    """The allocator variables the command hands on reach own_process_memory through the
    pair's process and the worker's processor, not the worker's own environment (which its
    dask nanny set)."""
    from plenopiv.camera.model import load_camera
    from plenopiv.workflow import pair, worker

    Calibration.from_camera(load_camera("small_m1")).save(tmp_path / "cal.h5")
    exp = tmp_path / "exp.toml"
    exp.write_text('camera = "small_m1"\n[volume]\nx_mm = [-1.0625, 1.0625]\n'
                   'y_mm = [-1.0625, 1.0625]\nz_mm = [-1.5, 1.5]\nvoxel_mm = 0.125\n')
    monkeypatch.setattr(pair, "weights_for", lambda *a, **k: (object(), False))
    seen = []
    monkeypatch.setattr(worker, "own_process_memory", seen.append)
    real = worker.worker_processor

    class Stop(Exception):
        pass

    def processor_then_stop(*args, **kwargs):
        real(*args, **kwargs)
        raise Stop

    monkeypatch.setattr(worker, "worker_processor", processor_then_stop)
    given = [(), (("MALLOC_TRIM_THRESHOLD_", "131072"),), None]
    for allocator in given:
        worker.drop_worker_processor()
        process = worker.ExperimentPairProcess(str(exp), str(tmp_path / "cal.h5"),
                                               str(tmp_path), allocator=allocator)
        with pytest.raises(Stop):
            process(None)
    worker.drop_worker_processor()
    assert seen == given


@pytest.mark.parametrize("user_env", [{}, {"MALLOC_TRIM_THRESHOLD_": "131072"},
                                      {"MALLOC_MMAP_MAX_": "0"}])
def test_a_pair_process_takes_the_allocator_settings_where_it_is_made(monkeypatch, user_env):
    """Whoever makes the pair's process (plenopiv run, a benchmark, a script) hands on the
    allocator variables of its own environment, never the worker's."""
    from plenopiv.workflow import worker

    for key in ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_MAX_"):
        monkeypatch.delenv(key, raising=False)
    for key, value in user_env.items():
        monkeypatch.setenv(key, value)
    process = worker.ExperimentPairProcess("exp.toml", "cal.h5", "out")
    assert process.allocator == tuple(user_env.items())


def test_a_volume_correlated_with_itself_is_warned_about(rng):
    """``plenopiv piv A.h5 A.h5``: a zero field by construction, said so."""
    from plenopiv.camera.corrections import DepthCorrection
    from plenopiv.camera.grid import VolumeGrid
    from plenopiv.errors import PlenopivWarning
    from plenopiv.piv import PIVSettings
    from plenopiv.products.volume import VolumeResult
    from plenopiv.workflow.pair import correlate

    grid = VolumeGrid((0.0, 0.0, 0.0), (1e-4, 1e-4, 1e-4), (16, 16, 16))
    vol = rng.random(grid.shape).astype(np.float32)
    res = VolumeResult(vol, grid, DepthCorrection(), np.zeros((0, 3)), np.zeros((0, 3)),
                       np.zeros(0), np.zeros((0, 3)))
    # a noise volume has no particle table: no minimum of particles per window
    with pytest.warns(PlenopivWarning, match="identical"):
        correlate(res, res, PIVSettings(windows=((8, 8, 8),), passes=1,
                                        min_particles_per_window=0))


@pytest.mark.parametrize("entry", ["run", "track", "piv"])
def test_identical_inputs_are_warned_about_once_by_every_pair_verb(pair_products, entry,
                                                                   tmp_path, capsys):
    """``run`` (the pair processor), ``track`` and ``piv`` given one input twice: one warning.

    Images are checked where they are prepared (``ImagePreparation.pair``), volumes where
    they are correlated; volumes made from checked images are not warned about again.
    """
    import warnings

    from plenopiv.errors import PlenopivWarning
    from plenopiv.workflow.pair import PairProcessor
    from plenopiv.workflow.tracking import track_images

    res, paths, _, _, (cal, pair, exp) = pair_products
    if entry == "piv":
        code = main(["piv", paths["volume_A"], paths["volume_A"], "--out",
                     str(tmp_path / "v.h5"), "--no-png", "--no-vtk"])
        err = capsys.readouterr().err
        assert code == 0 and err.count("are identical") == 1
        assert f"volume {paths['volume_A']!r} and volume {paths['volume_A']!r}" in err
        return
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if entry == "run":
            PairProcessor(exp, cal)(pair.image_a, pair.image_a)
        else:
            track_images(cal, pair.image_a, pair.image_a, exp, volume_a=res.volume_a,
                         volume_b=res.volume_a, vectors=res.vectors)
    said = [str(w.message) for w in caught if issubclass(w.category, PlenopivWarning)
            and "identical" in str(w.message)]
    assert said == ["image A and image B are identical (the same file or frame given twice?): "
                    "the field is zero by construction and says nothing of the flow"]


def test_the_pair_is_corrected_by_its_tracks_and_the_product_says_so(pair_products):
    """[tracking] correct_vectors (default): the pair's field is the correlation's plus the
    tracks' correction, the same as correcting the uncorrected field by the same tracks;
    the vectors product records it; off, the field is the correlation's."""
    import h5py

    from plenopiv.tracking.correction import correct_with_tracks
    from plenopiv.workflow.correlation import fitted_to_continuity

    res, paths, _, _, (cal, pair, exp) = pair_products
    assert exp.tracking.correct_vectors and res.tracks is not None
    assert res.track_correction["applied"] and res.track_correction["tracks"] > 0
    assert "track_s" in res.timings
    plain = process_pair(cal, pair.image_a, pair.image_b, dataclasses.replace(
        exp, tracking=dataclasses.replace(exp.tracking, correct_vectors=False),
        piv=dataclasses.replace(exp.piv, continuity=False)))
    assert plain.tracks is None and plain.track_correction is None
    assert plain.continuity == {"applied": False, "reason": "[piv] continuity = false"}
    again, _ = correct_with_tracks(plain.vectors, res.tracks,
                                   prior_tracks=exp.tracking.prior_tracks)
    # continuity comes last, on the corrected field
    again, continuity = fitted_to_continuity(again, exp.piv)
    assert continuity == res.continuity
    for c in "uvw":
        assert np.allclose(getattr(again, c), getattr(res.vectors, c), rtol=0,
                           atol=1e-9 * 1e-3, equal_nan=True)
    assert not np.allclose(plain.vectors.u, res.vectors.u, rtol=0, atol=1e-12)
    with h5py.File(paths["vectors"]) as fh:
        record = json.loads(fh.attrs["track_correction"])
    assert record["applied"] and record["tracks"] == res.track_correction["tracks"]
    assert record["prior_tracks"] == exp.tracking.prior_tracks
    with h5py.File(paths["vectors"]) as fh:
        assert json.loads(fh.attrs["continuity"]) == res.continuity


def test_a_pair_that_cannot_be_tracked_keeps_its_correlation_field(pair_products,
                                                                  monkeypatch):
    import plenopiv.workflow.tracking as T
    from plenopiv.errors import PlenopivWarning, ReconstructionError

    res, _, _, _, (cal, pair, exp) = pair_products

    def fail(*a, **k):
        raise ReconstructionError("no particle to fit")
    monkeypatch.setattr(T, "track_pair", fail)
    with pytest.warns(PlenopivWarning, match="could not be tracked.*correct_vectors"):
        vec, tracks, record = T.corrected_by_tracks(
            cal, (pair.image_a, pair.image_b), (res.volume_a, res.volume_b), res.vectors, exp)
    assert vec is res.vectors and tracks is None
    assert record == {"applied": False, "reason": "no particle to fit"}
