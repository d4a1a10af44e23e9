"""The laterally subdivided reconstruction grid (``[reconstruction] lateral_subdivision``) and
the merge of its voxels back onto the volume's grid (``subdivision_kernel``)."""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.camera.resolution import footprint
from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction.build import weights_for
from plenopiv.reconstruction.choose import lateral_subdivision, subdivided_grid
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.subdivision import merge_subdivided, working_factors
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume


@pytest.fixture(scope="module")
def cal():
    return Calibration.from_camera(load_camera("small_m1"))


def grid_of(cal, voxel_footprints, half=8):
    b = footprint(cal.effective_camera)
    v = voxel_footprints * b
    return VolumeGrid.from_bounds((-half * b, half * b), (-half * b, half * b),
                                  (-1e-3, 1e-3), voxel=(v, v, b))


@pytest.mark.parametrize(("voxel", "k"), [(1.0, 3), (0.5, 2), (1 / 3, 1), (0.25, 1), (2.0, 4)])
def test_auto_subdivides_to_a_third_of_a_footprint(cal, voxel, k):
    assert lateral_subdivision(cal, grid_of(cal, voxel), ReconstructionSettings()) == (k, k)
    fixed = ReconstructionSettings(lateral_subdivision=2)
    assert lateral_subdivision(cal, grid_of(cal, voxel), fixed) == (2, 2)


def test_subdivided_grid_covers_the_same_box(cal):
    grid = grid_of(cal, 1.0)
    fine = subdivided_grid(grid, 3, 2)
    np.testing.assert_allclose(fine.bounds, grid.bounds, rtol=0, atol=1e-12)
    assert fine.shape == (grid.shape[0], grid.shape[1] * 3, grid.shape[2] * 2)
    assert working_factors(fine, grid) == (1, 3, 2)
    with pytest.raises(ReconstructionError, match="another volume grid"):
        working_factors(subdivided_grid(grid_of(cal, 1.0, half=7), 3, 3), grid)
    # a finer grid of the same box is a subdivision too
    assert working_factors(subdivided_grid(grid_of(cal, 0.5), 2, 2), grid) == (1, 4, 4)


def test_box_merge_sums_and_gaussian_merge_keeps_total_and_position():
    rng = np.random.default_rng(3)
    fine = rng.random((2, 12, 18)).astype(np.float32)
    box = merge_subdivided(fine, 3, 3, kernel="box")
    np.testing.assert_allclose(box, fine.reshape(2, 4, 3, 6, 3).sum(axis=(2, 4)), rtol=1e-6)
    for k in (2, 3):
        for offset in range(k):                 # a point at each sub-voxel position
            v = np.zeros((1, 12 * k, 12 * k), np.float32)
            v[0, 6 * k + offset, 6 * k + k // 2] = 1.0
            merged = merge_subdivided(v, k, k)
            # samples of a Gaussian of half a voxel sum to 1 within 2 exp(-2 pi² / 4) = 1.4 %
            # per axis (the ripple with the position inside the voxel)
            assert merged.sum() == pytest.approx(1.0, rel=0.03)
            profile = merged[0].sum(axis=1)
            centroid = profile @ np.arange(12) / profile.sum()
            true = 6 + (offset - (k - 1) / 2) / k
            assert centroid == pytest.approx(true, abs=0.03)
            # the box merge puts the point in its voxel whatever its position inside
            box = merge_subdivided(v, k, k, kernel="box")[0].sum(axis=1)
            assert box @ np.arange(12) / box.sum() == 6
    with pytest.raises(ValueError, match="kernel"):
        merge_subdivided(fine, 3, 3, kernel="cubic")


def test_reconstruction_on_the_subdivided_grid_returns_the_volume_grid(cal):
    grid = grid_of(cal, 1.0)
    cam = load_camera("small_m1")
    b = footprint(cal.effective_camera)
    img = particle_image(cam, [(0.3 * b, -0.2 * b, 0.6e-3)], rays_per_particle=4000, seed=1)
    w, _ = weights_for(cal, grid, ReconstructionSettings())
    assert w.grid.shape == (grid.shape[0], 3 * grid.shape[1], 3 * grid.shape[2])
    assert w.matrix_free            # a square lattice: the matrix-free projector
    res = reconstruct_volume(cal, img, grid, weights=w)
    assert res.volume.shape == grid.shape and res.grid == grid
    assert len(res.particle_position) >= 1
    # weights on the volume's own grid reconstruct without subdivision
    own, _ = weights_for(cal, grid, ReconstructionSettings(lateral_subdivision=1))
    assert own.grid == grid
    assert reconstruct_volume(cal, img, grid, weights=own).volume.shape == grid.shape


@pytest.mark.parametrize("times", [1, 3.99, 4, 8.99, 9, 100])
def test_auto_gives_up_a_subdivision_whose_working_grid_is_too_large(cal, monkeypatch, times):
    """Every cap between 1 and 9 times the grid: the finest k with k² voxels within it."""
    from plenopiv.reconstruction import choose

    grid = grid_of(cal, 1.0)                         # a third of a footprint wants 3 x 3
    monkeypatch.setattr(choose, "MAX_AUTO_WORKING_VOXELS", times * grid.n_voxels)
    k = max(k for k in (1, 2, 3) if k * k <= max(times, 1))
    assert lateral_subdivision(cal, grid, ReconstructionSettings()) == (k, k)
    fixed = ReconstructionSettings(lateral_subdivision=3)     # a given k is never capped
    assert lateral_subdivision(cal, grid, fixed) == (3, 3)
    choice = choose.choose_reconstruction(cal, grid, ReconstructionSettings())
    assert choice.subdivision == (k, k)
    assert choice.grid.shape == (grid.shape[0], grid.shape[1] * k, grid.shape[2] * k)
    if k < 3:       # said, with what the user can set: the next cut first
        hint = "lateral_subdivision = 3" if k == 2 else "lateral_subdivision = 2 (or up to 3)"
        assert any("3 x 3 subdivision would make" in t and hint in t
                   for t in choice.fallbacks)
    else:
        assert not choice.fallbacks


@pytest.mark.parametrize("depth_voxel", [0.25e-3, 0.06e-3])
@pytest.mark.parametrize("rotation", [0.0, 2e-3])
def test_the_cap_bounds_the_working_grid_the_reconstruction_runs_on(cal, monkeypatch,
                                                                    rotation, depth_voxel):
    """The cut "auto" takes keeps the working grid the reconstruction runs on within the cap
    (its binned working voxels counted at the projector's cost, LENSLET_COST for the
    per-lenslet projector of a rotated lattice), and the next finer cut would not; with
    depth slices binned or not, the judgement and the plan's rates take the same cut."""
    import dataclasses

    from plenopiv.reconstruction import choose
    from plenopiv.workflow.judgement import camera_resolution, camera_subdivision
    from plenopiv.workflow.rates import _subdivision

    cam = cal.camera
    cam = cam.replace(microlens_array=dataclasses.replace(cam.microlens_array,
                                                          rotation=rotation))
    turned = Calibration.from_camera(cam)
    b = footprint(cal.effective_camera)
    grid = VolumeGrid.from_bounds((-8 * b, 8 * b), (-8 * b, 8 * b), (-1.5e-3, 1.5e-3),
                                  voxel=(b, b, depth_voxel))
    cap = 9 * grid.n_voxels
    monkeypatch.setattr(choose, "MAX_AUTO_WORKING_VOXELS", cap)
    cost = choose.model_projector_cost(cam)
    assert cost == (1.0 if rotation == 0 else choose.LENSLET_COST)
    choice = choose.choose_reconstruction(turned, grid, ReconstructionSettings())
    (k, _), kz = choice.subdivision, choice.depth_binning
    assert kz == (1 if depth_voxel > 0.1e-3 else 3)       # a third of the 0.55 mm depth cell
    assert choice.grid.n_voxels == -(-grid.shape[0] // kz) * grid.shape[1] * grid.shape[2] * k * k
    assert grid.n_voxels * k * k <= cap and cost * choice.grid.n_voxels <= cap
    if k < 3:
        assert rotation != 0           # the lattice projector: the cap on memory alone
        assert cost * subdivided_grid(grid, k + 1, k + 1, kz).n_voxels > cap
    else:
        assert rotation == 0 or kz >= cost        # binning buys the per-lenslet projector k
    # every place that decides the cut before a run takes the same one
    judged = camera_resolution(turned.effective_camera)
    assert camera_subdivision(judged, grid) == (k, k)
    assert _subdivision(turned.camera, grid, ("auto", "auto", None)) == (k, k)


def test_the_16_mp_volume_is_subdivided_2_x_2_on_every_lattice_and_a_deep_box_is_not():
    """The full camera's volume (287 x 193 x 201 footprint voxels, binned 3 to 67 working
    slices): 45 million working voxels on 2 x 2 fit the cap on an aligned lattice and on a
    turned or hexagonal one (measured: 16 s and 60-66 s a volume, 3.5-3.9 GB,
    docs/performance.md); 3 x 3 does not fit. The same 201 slices three times as deep (no
    binning) would make the per-lenslet projector's sweeps three times as long: it stays on
    the footprints, the lattice projector is cut 2 x 2."""
    from plenopiv.reconstruction import choose

    b, cell = 0.2596e-3, 2.24e-3                 # footprint and depth cell of auburn_135mm
    for dz, kz_wanted, per_lenslet in ((b, 3, (2, 2)), (3 * b, 1, (1, 1))):
        grid = VolumeGrid.from_bounds((-143.5 * b, 143.5 * b), (-96.5 * b, 96.5 * b),
                                      (-100.5 * dz, 100.5 * dz), voxel=(b, b, dz))
        assert grid.shape == (201, 193, 287)
        kz = choose.depth_binning_for(cell, grid, "auto")
        assert kz == kz_wanted
        assert choose.subdivision_for(b, grid, "auto", depth_binning=kz) == (2, 2)
        assert choose.subdivision_for(b, grid, "auto", cost=choose.LENSLET_COST,
                                      depth_binning=kz) == per_lenslet
        assert choose.wanted_subdivision(b, grid.voxel, "auto") == (3, 3)
        # another origin of the same grid (moved off the footprints) is cut alike
        moved = VolumeGrid(tuple(o + f * v for o, f, v in zip(grid.origin, (0.37, 0.61, 0.5),
                                                              grid.voxel, strict=True)),
                           grid.voxel, grid.shape)
        assert choose.subdivision_for(b, moved, "auto", cost=choose.LENSLET_COST,
                                      depth_binning=kz) == per_lenslet


def test_the_judgement_names_the_subdivision_auto_gave_up(cal, monkeypatch):
    from plenopiv.reconstruction import choose
    from plenopiv.workflow.judgement import camera_resolution, lateral_voxel_finding

    grid = grid_of(cal, 1.0)
    monkeypatch.setattr(choose, "MAX_AUTO_WORKING_VOXELS", 2 * grid.n_voxels)
    k = lateral_subdivision(cal, grid, ReconstructionSettings())
    assert k == (1, 1)
    finding = lateral_voxel_finding(camera_resolution(cal.effective_camera), grid, k)
    assert "lateral_subdivision = 3" in finding.change and "9 times" in finding.change


def test_the_cap_depends_on_the_box_s_voxel_count_not_its_place_or_turn(cal, monkeypatch):
    """A box moved, or turned a quarter (nx and ny swapped), gets the same cut."""
    from plenopiv.reconstruction import choose

    b = footprint(cal.effective_camera)
    base = VolumeGrid((0.0, 0.0, 0.0), (b, b, b), (10, 12, 18))
    moved = VolumeGrid((3.7 * b, -1.3 * b, 0.4 * b), (b, b, b), (10, 12, 18))
    turned = VolumeGrid((0.0, 0.0, 0.0), (b, b, b), (10, 18, 12))
    for cap in (1, 4, 9):
        monkeypatch.setattr(choose, "MAX_AUTO_WORKING_VOXELS", cap * base.n_voxels)
        cuts = {choose.subdivision_for(b, g, "auto") for g in (base, moved, turned)}
        assert len(cuts) == 1
