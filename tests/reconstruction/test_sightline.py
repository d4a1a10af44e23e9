"""The sub-voxel line-of-sight mask (reconstruction.sightline) and grid independence of a particle.

The camera is the thesis §5.1 one (50 mm lens at M = -1, f/2.2, 125 µm lenslets, footprint
b = 0.125 mm) cut to 15 or 16 lenslets: with an odd count a lenslet sits on the axis, with an
even count lenslet edges do. A plenoptic 1.0 camera resolves a footprint laterally and
ΔZ = b S_o N/f = 0.55 mm in depth near the focal plane (pipeline.resolution_cell), so:

- an in-focus particle lights its own lenslet only: the reconstruction must put it inside
  that lenslet's footprint (|x - x_lenslet| ≤ b/2) whatever the grid;
- in depth it must land within one resolution cell of the truth.

Grids: random sub-voxel offsets (fixed seed), voxels of 0.5, 1 and 1.5 footprints.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipelines.studies.depth import thesis_camera
from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.resolution import footprint, resolution_cell
from plenopiv.reconstruction.build import cached_weights
from plenopiv.reconstruction.geometry import subcell_factors
from plenopiv.reconstruction.sightline import pool_min, refined_grid, subcell_line_of_sight
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume


def small_camera(lenslets):
    return thesis_camera(lenslets=lenslets, sensor_px=int(math.ceil(lenslets * 125 / 7.4)) + 4)


@pytest.fixture(scope="module")
def odd():
    cam = small_camera(15)
    return cam, Calibration.from_camera(cam)


def noisy_image(cam, position, seed):
    img = particle_image(cam, [position], rays_per_particle=20000, seed=seed)
    return np.random.default_rng(seed + 1).poisson(img * 50 / img.max()).astype(np.float32)


# ---- helpers -----------------------------------------------------------------------------


def test_subcell_factors_keep_cells_within_half_a_footprint():
    b = 0.125e-3
    for v, k in ((0.5 * b, 1), (b, 2), (1.25 * b, 3), (1.5 * b, 3), (2 * b, 4)):
        g = VolumeGrid((0.0, 0.0, 0.0), (v, v, v), (2, 3, 4))
        kx, ky = subcell_factors(g, b)
        assert (kx, ky) == (k, k)
        assert v / kx <= b / 2 + 1e-15


def test_refined_grid_tiles_each_voxel():
    g = VolumeGrid((1e-3, -2e-3, 5e-3), (1e-4, 2e-4, 3e-4), (3, 4, 5))
    f = refined_grid(g, 3, 2)
    assert f.shape == (3, 8, 15)
    np.testing.assert_allclose(f.bounds, g.bounds, atol=1e-15)
    np.testing.assert_allclose(f.x.reshape(5, 3).mean(axis=1), g.x, atol=1e-15)
    np.testing.assert_allclose(f.y.reshape(4, 2).mean(axis=1), g.y, atol=1e-15)
    np.testing.assert_array_equal(f.z, g.z)


def test_pool_min_matches_a_loop():
    rng = np.random.default_rng(0)
    cells = rng.random((2, 6, 9)).astype(np.float32)
    out = pool_min(cells, 3, 2)
    ref = np.empty((2, 3, 3), np.float32)
    for z in range(2):
        for y in range(3):
            for x in range(3):
                ref[z, y, x] = cells[z, 2 * y:2 * y + 2, 3 * x:3 * x + 3].min()
    np.testing.assert_array_equal(out, ref)


# ---- the mask ----------------------------------------------------------------------------


@pytest.mark.parametrize("kx,ky", [(2, 2), (3, 2), (1, 1)])
def test_pool_cells_kernel_equals_its_numpy_twin(kx, ky):
    """The one-pass kernel against the NumPy expressions, on cells some of which no row,
    no used row or no dark row sees. The float32 divisions and comparisons are the same
    operations (equal to the bit); only the used sums' order of addition may differ."""
    from plenopiv.reconstruction._kernels import sightline as ks

    rng = np.random.default_rng(3)
    shape = (4, 5 * ky, 6 * kx)
    seen = (rng.random(shape) * (rng.random(shape) < 0.8)).astype(np.float32)
    dark = (seen * rng.random(shape) * (rng.random(shape) < 0.7)).astype(np.float32)
    used = (seen * rng.random(shape) * (rng.random(shape) < 0.7)).astype(np.float32)
    seen[:, :ky, :kx] = dark[:, :ky, :kx] = used[:, :ky, :kx] = 0.0   # a voxel no row sees
    used[:, ky:2 * ky, :kx] = 0.0                                        # one no used row sees
    log_sum = (-used * rng.random(shape) * 5).astype(np.float32)
    coarse = (4, 5, 6)
    out = (np.empty(coarse, np.float32), np.empty(coarse, np.float32), np.empty(coarse, bool),
           np.empty(coarse, np.float32), np.empty(coarse, bool))
    ks.pool_cells(seen, dark, used, log_sum, kx, ky, *out)
    want = ks.pool_cells_numpy(seen, dark, used, log_sum, kx, ky)
    for i in (0, 1, 2, 4):
        np.testing.assert_array_equal(out[i], want[i])
    np.testing.assert_allclose(out[3], want[3], rtol=1e-6, atol=0)
    assert np.isinf(out[0]).any() and (~out[2]).any() and out[4].any() and (~out[4]).any()



@pytest.mark.study
def test_in_focus_particle_keeps_its_voxels_when_voxel_edges_cross_its_lenslet(odd):
    """Voxel edges through the lenslet centre: every voxel around an in-focus particle covers
    a quarter of the lit lenslet, so ~3/4 of its weight is dark and the whole-voxel rule
    (dark fraction ≤ 0.5) empties it; the best sub-cell lies inside the lit lenslet."""
    cam, cal = odd
    b = footprint(cal.effective_camera)
    grid = VolumeGrid.from_bounds((-4 * b, 4 * b), (-4 * b, 4 * b), (-1e-3, 1e-3), voxel=b)
    w, _ = cached_weights(cal, grid, cache_dir=None, projector="sparse")
    img = noisy_image(cam, (0.0, 0.0, 0.0), 0)
    proj, row_scale = w.normalised
    raw = w.image_vector(img)
    dark = raw <= 0.003 * img.max()
    from plenopiv.lightfield import light_field

    keep, _, best = subcell_line_of_sight(w, lambda: light_field(cal), dark, tolerance=0.5,
                                          footprint=b)
    k = int(np.argmin(np.abs(grid.z)))
    around = [(k, 3, 3), (k, 3, 4), (k, 4, 3), (k, 4, 4)]
    seen = np.asarray(proj.column_sums())
    whole = np.asarray(proj.back(dark.astype(np.float32))) / np.where(seen > 0, seen, 1)
    for idx in around:
        flat = int(np.ravel_multi_index(idx, grid.shape))
        assert whole[flat] > 0.5                     # the whole-voxel rule would empty it
        assert best[idx] < 0.25 and keep[flat]       # its best-lit cell is inside the lenslet


# ---- grid independence -------------------------------------------------------------------


@pytest.mark.parametrize("lenslets,position", [
    (15, (0.0, 0.0, 0.0)), (15, (0.0, 0.0, 0.4e-3)), (15, (0.0, 0.0, -0.8e-3)),
    (16, (0.3 * 0.125e-3 + 62.5e-6, -0.2 * 0.125e-3 - 62.5e-6, 0.0)),
    (16, (62.5e-6, 62.5e-6, 0.4e-3)),
    (16, (0.3 * 0.125e-3 + 62.5e-6, 62.5e-6, 0.4e-3))])
@pytest.mark.study
def test_particle_is_found_whatever_the_grid(lenslets, position):
    """Random sub-voxel grids, voxels of 0.5-1.5 footprints: always found, and the position
    (from the light field, seeded by each grid's centroid) the same on every grid: within
    0.1 voxel laterally and 0.25 depth cells (the image is the same; only the grid moved).
    The last case is the hard one: 0.3 footprint off its lenslet's axis at +0.4 mm, the image
    fixes only the ratio of lateral offset to depth, and the volume's centroid spread 0.78
    footprint and 0.85 cells over these grids."""
    cam = small_camera(lenslets)
    cal = Calibration.from_camera(cam)
    b = footprint(cal.effective_camera)
    _, cell = resolution_cell(cal.effective_camera)
    img = noisy_image(cam, position, 3)
    pitch = cam.microlens_array.pitch * cal.effective_camera.object_distance / cam.image_distance
    offset = 0.0 if lenslets % 2 else 0.5 * pitch           # lenslet centres on the focal plane
    lens = np.round((np.array(position[:2]) - offset) / pitch) * pitch + offset
    rng = np.random.default_rng(lenslets * 100 + int(position[2] * 1e4) + 7)
    x0, y0, z0 = position
    found = []
    for size in (0.5, 1.0, 1.5):
        v = size * b
        for _ in range(2):
            sx, sy, sz = rng.uniform(-0.5, 0.5, 3) * v
            grid = VolumeGrid.from_bounds((x0 - 5 * b + sx, x0 + 5 * b + sx),
                                          (y0 - 5 * b + sy, y0 + 5 * b + sy),
                                          (z0 - 2.5e-3 + sz, z0 + 2.5e-3 + sz), voxel=v)
            w, _ = cached_weights(cal, grid, cache_dir=None, projector="lattice")
            res = reconstruct_volume(cal, img, grid, weights=w)
            assert len(res.particle_intensity) >= 1, (size, sx, sy, sz)
            p = res.particle_position_effective[int(np.argmax(res.particle_intensity))]
            if abs(z0) < 1e-9:                               # in focus: inside its lenslet
                assert np.abs(p[:2] - lens).max() <= b / 2, (size, p, lens)
            assert abs(p[2] - z0) <= cell, (size, p[2], z0)
            found.append(p)
    found = np.array(found)
    spread = found.max(0) - found.min(0)
    assert spread[:2].max() <= 0.1 * 0.5 * b, spread / b          # the smallest voxel's 0.1
    assert spread[2] <= 0.25 * cell, spread[2] / cell


@pytest.mark.study
def test_volume_positions_keep_the_centroid(odd):
    """``position = "volume"`` gives the voxels' centroid; the light field's positions keep
    it as ``particle_centroid_effective``; a fully masked image leaves every seed."""
    from plenopiv.particles.settings import ParticleSettings
    from plenopiv.reconstruction.geometry import ProjectionGeometry
    from plenopiv.workflow.volume import light_field_positions

    cam, cal = odd
    b = footprint(cal.effective_camera)
    img = noisy_image(cam, (0.0, 0.0, -0.8e-3), 3)
    grid = VolumeGrid.from_bounds((-5.2 * b, 4.8 * b), (-5.3 * b, 4.7 * b), (-2.5e-3, 2.5e-3),
                                  voxel=b)
    w, _ = cached_weights(cal, grid, cache_dir=None, projector="lattice")
    lf_res = reconstruct_volume(cal, img, grid, weights=w)
    vol_res = reconstruct_volume(cal, img, grid, weights=w,
                                 particles=ParticleSettings(position="volume"))
    assert vol_res.particle_centroid_effective is None
    np.testing.assert_array_equal(lf_res.particle_centroid_effective,
                                  vol_res.particle_position_effective)
    assert not np.array_equal(lf_res.particle_position_effective,
                              vol_res.particle_position_effective)
    seeds = vol_res.particle_position_effective
    lf = ProjectionGeometry(cal, grid).light_field
    kept = light_field_positions(lf, img, seeds, vol_res.particle_intensity, cal,
                                 image_mask=np.ones(img.shape, bool))
    np.testing.assert_array_equal(kept, seeds)
