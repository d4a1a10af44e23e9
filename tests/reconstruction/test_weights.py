"""Voxel-pixel weights, checked against their NumPy twin and the ray tracer."""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ConfigError, ReconstructionError
from plenopiv.lightfield import light_field
from plenopiv.reconstruction._kernels import weights as WK
from plenopiv.reconstruction.build import cached_weights
from plenopiv.reconstruction.weights import build_weights, weights_reference
from plenopiv.synthetic.images import particle_image


@pytest.fixture(scope="module")
def lf(small_camera):
    return light_field(Calibration.from_camera(small_camera))


def grid_around_axis(lf, fraction, half_lenslets=6.5, depth=6.25e-3, dz=0.25e-3):
    b = lf.footprint
    v = b * fraction
    return VolumeGrid.from_bounds((-half_lenslets * b, half_lenslets * b),
                                  (-half_lenslets * b, half_lenslets * b), (-depth, depth),
                                  voxel=(v, v, dz))


def trilinear_blob(grid, point):
    vol = np.zeros(grid.shape, np.float32)
    f = (np.asarray(point) - np.asarray(grid.origin)) / np.asarray(grid.voxel)
    i0 = np.floor(f).astype(int)
    fr = f - i0
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = ((fr[0] if dx else 1 - fr[0]) * (fr[1] if dy else 1 - fr[1])
                     * (fr[2] if dz else 1 - fr[2]))
                vol[i0[2] + dz, i0[1] + dy, i0[0] + dx] += w
    return vol


@pytest.mark.parametrize("alpha, beta", [(0.3, 1.0), (1.0, 0.3), (0.0, 0.7), (0.5, 0.5)])
def test_box_sum_cdf_kernel_matches_numerical_convolution(alpha, beta):
    x = np.linspace(-1.2, 1.4, 41)
    got = np.array([WK.box_sum_cdf(v, 0.1, alpha, beta) for v in x])
    assert np.allclose(got, WK.box_sum_cdf_numpy(x, 0.1, alpha, beta), atol=2e-6)


def test_weight_kernel_matches_numpy_twin(lf):
    grid = grid_around_axis(lf, 0.5, half_lenslets=3.5, depth=2e-3, dz=0.5e-3)
    w = build_weights(lf, grid, min_weight=0.0)
    rows = np.flatnonzero(np.diff(w.projector.indptr) > 0)[::97][:25]
    dense = w.projector.to_scipy()[rows].toarray()
    ref = weights_reference(lf, grid, rows)
    assert np.allclose(dense, ref, rtol=1e-4, atol=1e-6 * ref.max())


def test_forward_projection_reproduces_the_simulated_particle(small_camera, lf):
    """A trilinear blob at the particle's position, projected through W, correlates with the
    ray-traced image of the particle: NC ≥ 0.9 with voxels of half a lenslet footprint, and
    ≥ 0.95 with a quarter (the model converges to the point image)."""
    for fraction, bound in ((0.5, 0.9), (0.25, 0.95)):
        grid = grid_around_axis(lf, fraction)
        w = build_weights(lf, grid)
        b = lf.footprint
        for depth in (-5e-3, -2e-3, 0.0, 1e-3, 3e-3, 5e-3):
            p = (2.13 * b, -2.69 * b, depth)
            sim = particle_image(small_camera, [p], rays_per_particle=20000).ravel()
            fwd = w.forward_image(trilinear_blob(grid, p), small_camera.sensor.shape)
            fwd = fwd.ravel().astype(float)
            nc = (sim * fwd).sum() / np.sqrt((sim ** 2).sum() * (fwd ** 2).sum())
            assert nc >= bound, f"voxel {fraction} footprint, Z = {depth}: NC = {nc:.3f}"
            # energy: the lit pixels catch the particle's light but for the cut aperture edge
            assert fwd.sum() == pytest.approx(1.0, abs=0.04)


def test_grid_outside_view_and_empty_grid_are_errors(lf):
    with pytest.raises(ReconstructionError, match="outside the field of view"):
        build_weights(lf, VolumeGrid.from_bounds((0.1, 0.11), (0, 0.01), (-1e-3, 1e-3),
                                                 voxel=1e-3))
    with pytest.raises(ConfigError, match="at least one voxel"):
        VolumeGrid((0, 0, 0), (1e-3, 1e-3, 1e-3), (0, 4, 4))
    with pytest.raises(ReconstructionError, match="main lens"):
        build_weights(lf, VolumeGrid.from_bounds((-1e-3, 1e-3), (-1e-3, 1e-3), (-0.5, 1e-3),
                                                 voxel=1e-3))


def test_weight_cache_is_keyed_by_geometry(tmp_path, small_camera):
    cal = Calibration.from_camera(small_camera)
    grid = VolumeGrid.from_bounds((-1e-3, 1e-3), (-1e-3, 1e-3), (-1e-3, 1e-3), voxel=0.25e-3)
    w1, hit1 = cached_weights(cal, grid, cache_dir=tmp_path)
    w2, hit2 = cached_weights(cal, grid, cache_dir=tmp_path)
    assert not hit1 and hit2 and w1.key == w2.key
    assert np.array_equal(w1.projector.data, w2.projector.data)
    # another image distance: another key, rebuilt, never the cached matrix
    other = Calibration.from_camera(small_camera.with_image_distance(0.21))
    w3, hit3 = cached_weights(other, grid, cache_dir=tmp_path)
    assert not hit3 and w3.key != w1.key
    # a corrupt cache file is rebuilt, not trusted
    for f in tmp_path.glob("weights-*.h5"):
        f.write_bytes(b"garbage")
    w4, hit4 = cached_weights(cal, grid, cache_dir=tmp_path)
    assert not hit4 and np.array_equal(w4.projector.data, w1.projector.data)
