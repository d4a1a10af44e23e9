"""The depth-binned working grid (``[reconstruction] depth_binning``) and the resampling of its
volume back onto the volume's depth slices."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.camera.resolution import resolution_cell
from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction.choose import (
    BINNED_DEPTH_CELLS,
    choose_reconstruction,
    depth_binning,
    depth_binning_for,
    subdivided_grid,
)
from plenopiv.reconstruction.settings import MAX_DEPTH_BINNING, ReconstructionSettings
from plenopiv.reconstruction.subdivision import to_volume_grid, unbin_depth, working_factors


def grid_with(nz: int, dz: float = 1e-4, origin_z: float = 0.0, ny: int = 4,
              nx: int = 5) -> VolumeGrid:
    return VolumeGrid((0.0, 0.0, origin_z), (2e-4, 2e-4, dz), (nz, ny, nx))


@pytest.mark.parametrize("nz", [1, 2, 5, 6, 7, 30, 31])
@pytest.mark.parametrize("kz", [1, 2, 3, 4])
@pytest.mark.parametrize(("ky", "kx"), [(1, 1), (2, 3)])
def test_the_binned_grid_covers_the_depth_range_centred_and_is_recognised(nz, kz, ky, kx):
    grid = grid_with(nz, origin_z=-0.37e-3)
    work = subdivided_grid(grid, ky, kx, kz)
    wz = math.ceil(nz / kz)
    assert work.shape == (wz, grid.shape[1] * ky, grid.shape[2] * kx)
    (lo, hi), (wlo, whi) = grid.bounds[2], work.bounds[2]
    # the same centre; the overhang at each end is less than half a merged slice
    assert (wlo + whi) / 2 == pytest.approx((lo + hi) / 2, abs=1e-12)
    assert -1e-12 <= lo - wlo < 0.5 * kz * grid.voxel[2] + 1e-12
    assert working_factors(work, grid) == (kz, ky, kx)


def test_weights_of_another_depth_range_are_refused():
    grid = grid_with(12)
    for other in (grid_with(12, origin_z=0.5e-4), grid_with(13), grid_with(12, dz=1.1e-4)):
        with pytest.raises(ReconstructionError, match="another volume grid"):
            working_factors(subdivided_grid(other, 1, 1, 3), grid)


@pytest.mark.parametrize("dz_cells", [0.02, 0.05, 0.1, 0.12, 0.2, 0.3, 0.34, 0.5, 1.0])
def test_auto_bins_to_at_most_a_third_of_the_depth_cell(dz_cells):
    cell = 2.2e-3
    grid = grid_with(200, dz=dz_cells * cell)
    k = depth_binning_for(cell, grid, "auto")
    # the working slice is at most a third of the cell (5 % slack), and one slice more
    # would exceed it; slices that deep already are not binned
    assert k == 1 or k * dz_cells <= BINNED_DEPTH_CELLS * 1.05 + 1e-12
    assert (k + 1) * dz_cells > BINNED_DEPTH_CELLS * 1.05
    assert depth_binning_for(cell, grid, 2) == 2
    assert depth_binning_for(cell, grid_with(3, dz=0.01 * cell), "auto") == 3   # not > nz


def test_auto_binning_follows_the_camera_s_depth_cell_and_the_recording_s_stop():
    cal = Calibration.from_camera(load_camera("auburn_135mm"))
    lat, dep = resolution_cell(cal.effective_camera)
    cubic = grid_with(100, dz=lat)
    assert depth_binning(cal, cubic, ReconstructionSettings()) == math.floor(dep / lat / 3 * 1.05)
    assert depth_binning(cal, cubic, ReconstructionSettings(depth_binning=1)) == 1
    # stopped down, the depth cell grows with N
    n = cal.camera.main_lens.f_number
    wide = ReconstructionSettings(f_number=2 * n)
    assert depth_binning(cal, cubic, wide) == math.floor(2 * dep / lat / 3 * 1.05)


@pytest.mark.parametrize("bad", [0, -1, MAX_DEPTH_BINNING + 1, True, "2", 1.5, "none"])
def test_a_bad_depth_binning_is_refused_by_name(bad):
    with pytest.raises(ValidationError, match="depth_binning"):
        ReconstructionSettings(depth_binning=bad)


def _profile(nz_work: int, centre: float, sigma: float) -> np.ndarray:
    z = np.arange(nz_work, dtype=float)
    return np.exp(-0.5 * ((z - centre) / sigma) ** 2)


@pytest.mark.parametrize("kz", [2, 3, 4])
def test_resampling_keeps_a_particle_s_total_and_its_depth(kz):
    """A depth profile a depth cell long (σ of 1.3 working slices at a third of a cell),
    anywhere between two working slices, returns with its total and its centroid."""
    rng = np.random.default_rng(7)
    nz = 40 * kz
    grid = grid_with(nz, ny=1, nx=1)
    work = subdivided_grid(grid, 1, 1, kz)
    wz = work.shape[0]
    for centre in 10 + rng.random(8) * (wz - 20):
        v = _profile(wz, centre, 1.3).astype(np.float32)[:, None, None]
        out = unbin_depth(v, kz, grid)[:, 0, 0]
        assert out.sum() == pytest.approx(v.sum(), rel=1e-3)
        z_work = work.z[0] + centre * work.voxel[2]
        z_out = float((out * grid.z).sum() / out.sum())
        # the spline's error in the centroid: a small fraction of a grid slice
        assert abs(z_out - z_work) < 0.05 * grid.voxel[2]
        # and the peak is not locked to the working slices
        peak = grid.z[np.argmax(out)]
        assert abs(peak - z_work) <= 0.5 * grid.voxel[2] + 1e-12


def test_resampling_is_the_numpy_interpolation_of_each_column():
    """The twin: each (y, x) column is the cubic interpolating spline through its working
    slices (scipy's CubicSpline with not-a-knot ends), clipped at zero, over kz."""
    from scipy.interpolate import CubicSpline

    rng = np.random.default_rng(1)
    kz, nz = 3, 20
    grid = grid_with(nz, ny=2, nx=3)
    work = subdivided_grid(grid, 1, 1, kz)
    v = rng.random(work.shape).astype(np.float32)
    out = unbin_depth(v, kz, grid)
    z = np.clip(grid.z, work.z[0], work.z[-1])
    for iy in range(2):
        for ix in range(3):
            twin = np.maximum(CubicSpline(work.z, v[:, iy, ix])(z), 0) / kz
            np.testing.assert_allclose(out[:, iy, ix], twin, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("wz", [1, 2, 3])
def test_resampling_few_working_slices(wz):
    kz = 3
    grid = grid_with(wz * kz - 1, ny=1, nx=1)
    v = np.arange(1, wz + 1, dtype=np.float32)[:, None, None]
    out = unbin_depth(v, kz, grid)
    assert out.shape == grid.shape
    assert np.all(np.isfinite(out)) and np.all(out >= 0)
    assert out.min() >= v.min() / kz - 1e-6 and out.max() <= v.max() / kz + 1e-6


def test_to_volume_grid_merges_laterally_and_resamples_in_depth():
    grid = grid_with(9, ny=4, nx=5)
    work = subdivided_grid(grid, 2, 2, 3)
    v = np.ones(work.shape, np.float32)
    out = to_volume_grid(v, work, grid, kernel="box")
    assert out.shape == grid.shape
    # a uniform working volume: each voxel holds 2 x 2 working voxels' light over 3 slices
    np.testing.assert_allclose(out, 4 / 3, rtol=1e-6)


def test_the_choice_builds_the_binned_grid_and_reports_it():
    cal = Calibration.from_camera(load_camera("small_m1"))
    lat, dep = resolution_cell(cal.effective_camera)
    half = 6 * lat
    grid = VolumeGrid.from_bounds((-half, half), (-half, half), (-1e-3, 1e-3),
                                  voxel=(lat, lat, lat / 2))
    choice = choose_reconstruction(cal, grid, ReconstructionSettings())
    kz = depth_binning(cal, grid, ReconstructionSettings())
    assert kz > 1
    assert choice.depth_binning == kz and choice.to_dict()["depth_binning"] == kz
    assert working_factors(choice.grid, grid)[0] == kz


def test_the_same_working_slices_give_the_same_particles_whatever_slices_are_typed():
    """Invariance: a box typed with slices a third as deep, binned by 3, reconstructs on the
    working slices of the box typed with them directly; the particles found on the two grids
    agree to a small fraction of a working slice, and the fine grid's volume holds the same
    light."""
    from plenopiv.camera.resolution import footprint
    from plenopiv.synthetic.images import particle_image
    from plenopiv.workflow.volume import reconstruct_volume

    cam = load_camera("small_m1")
    cal = Calibration.from_camera(cam)
    b = footprint(cal.effective_camera)
    dz = 1.5 * b                               # a third of a depth cell is 1.47 b here
    half = 6 * b
    coarse = VolumeGrid.from_bounds((-half, half), (-half, half), (-7.5 * dz, 7.5 * dz),
                                    voxel=(b, b, dz))
    fine = VolumeGrid.from_bounds((-half, half), (-half, half), (-7.5 * dz, 7.5 * dz),
                                  voxel=(b, b, dz / 3))
    settings = ReconstructionSettings(lateral_subdivision=1)
    assert depth_binning(cal, coarse, settings) == 1 and depth_binning(cal, fine, settings) == 3
    truth = [(0.3 * b, -0.2 * b, 1.1 * dz), (-2.2 * b, 1.4 * b, -3.4 * dz),
             (2.6 * b, 2.1 * b, 4.2 * dz)]
    img = particle_image(cam, truth, rays_per_particle=4000, seed=1)
    a = reconstruct_volume(cal, img, coarse, settings=settings)
    f = reconstruct_volume(cal, img, fine, settings=settings)
    assert f.volume.shape == fine.shape
    assert f.volume.sum() == pytest.approx(a.volume.sum(), rel=0.02)
    # the volume's centroids within a tenth of a working slice; the light-field positions
    # they seed converge to the same points
    for which, within in (("particle_centroid_effective", 0.1),
                          ("particle_position_effective", 0.01)):
        pa, pf = np.asarray(getattr(a, which)), np.asarray(getattr(f, which))
        assert len(pa) == len(pf) >= len(truth)
        for p in pa:
            d = np.abs(pf - p) / np.array([b, b, dz])
            assert d.max(axis=1).min() < within, which
