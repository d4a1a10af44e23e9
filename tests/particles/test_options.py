"""Particle extraction options of the pipeline (plenopiv.workflow.volume.particle_options)."""

from __future__ import annotations

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.camera.resolution import resolution_cell
from plenopiv.particles.peaks import find_particles
from plenopiv.particles.settings import ParticleSettings
from plenopiv.workflow.volume import particle_options


@pytest.fixture(scope="module")
def cal():
    return Calibration.from_camera(load_camera("small_m1"))


def grid_of(shape, voxel):
    nz, ny, nx = shape
    vx, vy, vz = voxel
    return VolumeGrid.from_bounds((0, nx * vx), (0, ny * vy), (0, nz * vz), voxel=voxel)


def test_resolution_cell_of_the_m1_camera(cal):
    cam = cal.effective_camera
    lat, dep = resolution_cell(cal.effective_camera)
    # M = -1: the footprint is the lenslet pitch; depth cell b S_o / D with D = f / N
    assert lat == pytest.approx(cam.microlens_array.pitch, rel=1e-9)
    d = cam.main_lens.focal_length / cam.main_lens.f_number
    assert dep == pytest.approx(lat * cam.object_distance / d, rel=1e-9)


def test_unset_separation_and_box_follow_the_resolution_cell(cal):
    lat, dep = resolution_cell(cal.effective_camera)
    grid = grid_of((40, 30, 30), (lat / 2, lat / 2, dep / 4))
    opts = particle_options(ParticleSettings(), grid, cal, np.ones(grid.shape, np.float32))
    assert opts["min_separation_vox"] == pytest.approx((4.0, 3.0, 3.0))
    assert opts["box_vox"] == (4, 2, 2)
    # explicit values are kept as given
    given = ParticleSettings(min_separation_vox=(5, 1, 1), box_vox=(3, 1, 1))
    opts = particle_options(given, grid, cal, np.ones(grid.shape, np.float32))
    assert opts["min_separation_vox"] == (5, 1, 1) and opts["box_vox"] == (3, 1, 1)


def test_bright_reference_ignores_a_hot_voxel(cal):
    """200 equal blobs and one voxel 50 times brighter: a threshold on the maximum loses every
    blob, one on the 99.9th percentile of the positive voxels keeps them all."""
    rng = np.random.default_rng(4)
    shape = (40, 60, 60)
    vol = np.zeros(shape, np.float32)
    z, y, x = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    centres = []
    while len(centres) < 200:
        c = rng.uniform([4, 4, 4], np.array(shape) - 4)
        if all(np.max(np.abs(c - o) / (4, 4, 4)) >= 1 for o in centres):
            centres.append(c)
    for c in centres:
        vol += np.exp(-0.5 * (((z - c[0]) / 1.5) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2))
    vol[20, 30, 30] = 50.0 * vol.max()
    lat, dep = resolution_cell(cal.effective_camera)
    grid = grid_of(shape, (lat, lat, dep / 4))
    found = {}
    for ref in ("bright", "maximum"):
        s = ParticleSettings(threshold=0.1, threshold_reference=ref,
                             min_separation_vox=(3, 2, 2), box_vox=(3, 1, 1))
        found[ref] = len(find_particles(vol, **particle_options(s, grid, cal, vol)).position_vox)
    assert found["maximum"] == 1                      # only the hot voxel
    assert found["bright"] >= 200                     # every blob (and the hot voxel)
