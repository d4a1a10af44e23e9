"""The matrix-free lattice projector against the explicit weights (plenopiv.reconstruction.lattice).

With the same ray model (cell-centre rays for edge pixels, no weight dropped) the lattice
projector is the explicit W computed in another order, so forward and back projections agree
to float32 summation error: |Δ| ≤ 1e-5 of the largest value (a sum of a few hundred float32
terms, each rounded at 6e-8). With the pipeline's default ray model (edge pixels through the
centroid of their lit part) the two reconstructions differ only at the micro-images' rims:
Q ≥ 0.99 between them, the issue's bar.
"""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import light_field
from plenopiv.reconstruction.build import cached_weights
from plenopiv.reconstruction.choose import (
    BYTES_PER_NONZERO,
    choose_projector,
    estimate_matrix_free_gb,
    estimate_nnz,
)
from plenopiv.reconstruction.geometry import separable_axes
from plenopiv.reconstruction.lattice import LatticeProjector
from plenopiv.reconstruction.mart import reconstruction_quality
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.weights import build_weights
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume

RTOL = 1e-5


def small_grid(lf, nx=30, ny=20, nz=24, lateral=1.0, depth=1.0):
    b = lf.footprint
    vx, vz = b * lateral, b * depth
    return VolumeGrid.from_bounds((-nx / 2 * vx, nx / 2 * vx), (-ny / 2 * vx, ny / 2 * vx),
                                  (-nz / 2 * vz, nz / 2 * vz), voxel=(vx, vx, vz))


@pytest.fixture(scope="module")
def pair(request):
    from plenopiv.camera.model import load_camera

    cal = Calibration.from_camera(load_camera("small_test"))
    lf = light_field(cal, edge_centroid=False)
    grid = small_grid(lf, lateral=0.75, depth=1.7)   # voxels not matched to the footprint
    return lf, grid, build_weights(lf, grid, min_weight=0.0).projector, \
        LatticeProjector.from_light_field(lf, grid)


def test_forward_back_equal_explicit_weights(pair, rng):
    lf, grid, explicit, lattice = pair
    assert lattice.n_pixels == explicit.n_pixels == lf.n_rays
    e = rng.random(grid.n_voxels).astype(np.float32)
    f0, f1 = explicit.forward(e), lattice.forward(e)
    assert np.abs(f1 - f0).max() <= RTOL * np.abs(f0).max()
    i = rng.random(lf.n_rays).astype(np.float32)
    b0, b1 = explicit.back(i), lattice.back(i)
    assert np.abs(b1 - b0).max() <= RTOL * np.abs(b0).max()
    r0, r1 = explicit.row_max(), lattice.row_max()
    assert np.abs(r1 - r0).max() <= RTOL * r0.max()
    c0, c1 = explicit.column_sums(), lattice.column_sums()
    assert np.abs(c1 - c0).max() <= RTOL * c0.max()


def test_adjoint_and_row_views(pair, rng):
    lf, grid, _, lattice = pair
    e = rng.random(grid.n_voxels).astype(np.float32)
    i = rng.random(lf.n_rays).astype(np.float32)
    lhs = float(np.dot(lattice.forward(e).astype(np.float64), i))
    rhs = float(np.dot(e.astype(np.float64), lattice.back(i)))
    assert lhs == pytest.approx(rhs, rel=RTOL)
    mask = rng.random(lf.n_rays) < 0.3
    sub = lattice.select_rows(mask)
    assert sub.n_pixels == mask.sum()
    np.testing.assert_allclose(sub.forward(e), lattice.forward(e)[mask], rtol=RTOL, atol=0)
    full = np.where(mask, i, 0).astype(np.float32)
    np.testing.assert_allclose(sub.back(i[mask]), lattice.back(full), rtol=RTOL,
                               atol=RTOL * float(lattice.back(full).max()))
    f = rng.uniform(0.5, 2.0, lf.n_rays)
    np.testing.assert_allclose(lattice.scale_rows(f).forward(e), lattice.forward(e) * f,
                               rtol=1e-5)


def test_rotated_lattice_is_refused(small_camera):
    mla = dataclasses.replace(small_camera.microlens_array, rotation=2e-3)
    cal = Calibration.from_camera(small_camera.replace(microlens_array=mla))
    lf = light_field(cal)
    assert separable_axes(lf) is None
    grid = small_grid(lf)
    with pytest.raises(ReconstructionError, match="axis-aligned"):
        LatticeProjector.from_light_field(lf, grid)
    with pytest.raises(ReconstructionError, match="max_weights_gb"):
        choose_projector(lf, grid, max_weights_gb=1e-6)
    assert choose_projector(lf, grid, max_weights_gb=1e3) == "sparse"


def test_auto_takes_the_lattice_when_weights_do_not_fit(small_camera):
    cal = Calibration.from_camera(small_camera)
    lf = light_field(cal)
    grid = small_grid(lf)
    assert choose_projector(lf, grid, max_weights_gb=1e3) == "sparse"
    budget = 1.01 * estimate_matrix_free_gb(lf, grid)
    assert BYTES_PER_NONZERO * estimate_nnz(lf, grid) / 1e9 > budget
    w, cached = cached_weights(cal, grid, cache_dir=None, max_weights_gb=budget)
    assert w.matrix_free and not cached and w.nnz == 0


def test_volumes_beyond_the_memory_limit_are_refused_before_allocating(small_camera):
    """Explicit weights asked for, or the matrix-free estimate, beyond max_weights_gb: an
    error naming the figure and what to change, before anything is built."""
    lf = light_field(Calibration.from_camera(small_camera))
    grid = small_grid(lf)
    mf = estimate_matrix_free_gb(lf, grid)
    # the estimate holds the two projection buffers at least
    nz, ny, _ = grid.shape
    assert mf * 1e9 >= 2 * 4 * nz * ny * len(np.unique(lf.pixel % lf.shape[1]))
    with pytest.raises(ReconstructionError, match=r"explicit weights need ~.* GB.*projector"):
        choose_projector(lf, grid, projector="sparse", max_weights_gb=1e-6)
    with pytest.raises(ReconstructionError, match=r"matrix-free reconstruction .* needs ~"
                                                  r".* GB.*fewer or larger voxels"):
        choose_projector(lf, grid, projector="lattice", max_weights_gb=0.5 * mf)


def test_reconstruction_agrees_with_explicit_path(small_camera):
    """Same image, same settings, both projectors: the volumes agree (Q >= 0.99)."""
    cal = Calibration.from_camera(small_camera)
    lf = light_field(cal)
    grid = small_grid(lf, nx=24, ny=16, nz=20, depth=4.0)
    rng = np.random.default_rng(5)
    half = np.array([12, 8, 40]) * lf.footprint * np.array([0.8, 0.8, 0.8])
    pos = rng.uniform(-half, half, (40, 3))
    img = particle_image(small_camera, pos, rays_per_particle=4000, seed=2)
    vols = {}
    for kind in ("sparse", "lattice"):
        s = ReconstructionSettings(projector=kind, iterations=5)
        vols[kind] = reconstruct_volume(cal, img, grid, settings=s).volume
    assert reconstruction_quality(vols["lattice"], vols["sparse"]) >= 0.99


def test_lattice_needs_smart(small_camera):
    cal = Calibration.from_camera(small_camera)
    grid = small_grid(light_field(cal))
    img = particle_image(small_camera, [(0.0, 0.0, 0.0)], rays_per_particle=2000)
    with pytest.raises(ReconstructionError, match="smart"):
        reconstruct_volume(cal, img, grid,
                           settings=ReconstructionSettings(projector="lattice", method="mart"))


def test_a_calibration_from_noisy_images_is_separable_and_reconstructs_alike():
    """Calibrated focal spots scatter by the spot noise (here 0.014 px rms about the lattice
    fit); the lattice projector takes each sensor column's mean, so it must accept them and
    reconstruct what the explicit weights of the same calibration reconstruct (Q ≥ 0.99)."""
    from dataclasses import replace

    from plenopiv.calibration.calibrate import calibrate
    from plenopiv.camera.model import load_camera
    from plenopiv.synthetic.images import alignment_image, finish_image, focal_point_image

    cam = load_camera("small_m1")
    rng = np.random.default_rng(3)
    fp = finish_image(focal_point_image(cam, f_number=16), noise="poisson", rng=rng)
    al = finish_image(alignment_image(cam), noise="poisson", rng=rng)
    user = cam.replace(main_lens=replace(cam.main_lens, image_distance=None))
    cal = calibrate(user, fp, alignment_image=al, method="focal-point").calibration
    lf = light_field(cal)
    assert separable_axes(lf) is not None
    grid = small_grid(lf, nx=24, ny=16, nz=20, depth=4.0)
    half = np.array([12, 8, 40]) * lf.footprint * 0.8
    img = particle_image(cam, np.random.default_rng(5).uniform(-half, half, (40, 3)),
                         rays_per_particle=4000, seed=2)
    vols = [reconstruct_volume(cal, img, grid, settings=ReconstructionSettings(
        projector=kind, iterations=5)).volume for kind in ("sparse", "lattice")]
    assert reconstruction_quality(vols[1], vols[0]) >= 0.99


def test_the_reused_projection_buffer_changes_nothing(pair, rng):
    """Views share one projection buffer; calls in turn, into ``out`` or from several
    threads at once give what a fresh projector gives, to the bit."""
    from concurrent.futures import ThreadPoolExecutor

    lf, grid, _, lattice = pair
    fresh = LatticeProjector.from_light_field(lf, grid)
    views = [lattice, lattice.select_rows(rng.random(lf.n_rays) < 0.5),
             lattice.scale_rows(rng.uniform(0.5, 2.0, lf.n_rays))]
    e = [rng.random(grid.n_voxels).astype(np.float32) for _ in range(3)]
    i = rng.random(lf.n_rays).astype(np.float32)
    want_f = [fresh.forward(x) for x in e]
    want_b = fresh.back(i)
    for keep in (False, True):
        kept = lattice.reusing_buffers() if keep else contextlib.nullcontext()
        with kept:
            _calls_in_turn(lattice, e, want_f, i, want_b)
        assert lattice._scratch._array is None          # given back after the sweeps
    with ThreadPoolExecutor(4) as pool, views[1].reusing_buffers():
        got = list(pool.map(lambda x: lattice.forward(x), e * 4))
    for g, want in zip(got, want_f * 4, strict=True):
        np.testing.assert_array_equal(g, want)
    assert views[2].forward(e[0]).shape == (views[2].n_pixels,)
    with pytest.raises(ReconstructionError, match="contiguous float32"):
        lattice.back(i, out=np.zeros(grid.n_voxels, np.float64))


def _calls_in_turn(lattice, e, want_f, i, want_b):
    for _ in range(2):
        for x, want in zip(e, want_f, strict=True):
            np.testing.assert_array_equal(lattice.forward(x), want)
        out = np.full(lattice.n_voxels, np.nan, np.float32)
        assert lattice.back(i, out=out) is out
        np.testing.assert_array_equal(out, want_b)
