"""Two particles that make one peak in the volume, told apart by their rays."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import Sensor, load_camera
from plenopiv.camera.resolution import resolution_cell
from plenopiv.particles.settings import ParticleSettings
from plenopiv.particles.split import blob_axes
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume


@pytest.fixture(scope="module")
def case():
    """The 50 mm lens at M = -1 on 41 x 41 lenslets: footprint 0.125 mm, depth cell 0.55 mm."""
    a = load_camera("auburn_50mm")
    mla = dataclasses.replace(a.microlens_array, rows=41, cols=41, substrate=None)
    cam = a.replace(sensor=Sensor(700, 700, 7.4e-6), microlens_array=mla)
    cal = Calibration.from_camera(cam)
    lateral, depth = resolution_cell(cal.effective_camera)
    grid = VolumeGrid.from_bounds((-1.8e-3, 1.8e-3), (-1.8e-3, 1.8e-3), (-5e-3, 5e-3),
                                  voxel=(0.125e-3, 0.125e-3, 0.25e-3))
    return cam, cal, grid, np.array([lateral, lateral, depth])


#: Centres of the merged pairs (x, y, z), metres.
PAIR_CENTRES = np.array([(0.0, 0.0, 2.5e-3), (0.2e-3, -0.3e-3, -2.0e-3),
                         (-0.9e-3, 0.8e-3, 0.8e-3), (-0.5e-3, 0.1e-3, -3.5e-3),
                         (0.9e-3, -0.9e-3, 3.5e-3)])


def pairs(cell):
    """Five pairs of particles closer than a resolution cell: side by side along x, y and a
    diagonal, apart along x and z at once, and straight behind one another. Each makes one
    peak on footprint voxels; its rays carry 1.8-2.0 times a single particle's light (the
    volume's intensity of the pair behind one another only 1.2-1.4 times). The last pair's
    shared fits meet; the mixture of lines parts it."""
    half = np.array([[0.5 * cell[0], 0.0, 0.0], [0.0, 0.5 * cell[1], 0.0],
                     [0.35 * cell[0], 0.35 * cell[1], 0.0], [0.3 * cell[0], 0.0, 0.3 * cell[2]],
                     [0.0, 0.0, 0.45 * cell[2]]])
    return np.concatenate([[c - h, c + h] for c, h in zip(PAIR_CENTRES, half, strict=True)])


def singles(cell, n=30):
    """``n`` particles more than 2.5 resolution cells from each other and from the pairs,
    spread over the box (seeded)."""
    rng = np.random.default_rng(7)
    out = list(PAIR_CENTRES)
    while len(out) < n + len(PAIR_CENTRES):
        p = rng.uniform((-1.4e-3, -1.4e-3, -4e-3), (1.4e-3, 1.4e-3, 4e-3))
        if np.min(np.linalg.norm((np.array(out) - p) / cell, axis=1)) > 2.5:
            out.append(p)
    return np.array(out[len(PAIR_CENTRES):])


def matched(true, found, cell) -> int:
    """True particles matched one-to-one within the resolution cell's ellipsoid."""
    d = np.linalg.norm((true[:, None, :] - found[None, :, :]) / cell, axis=2)
    n, used = 0, set()
    for i, j in sorted(np.ndindex(d.shape), key=lambda ij: d[ij]):
        if d[i, j] > 1.0:
            break
        if i in {u[0] for u in used} or j in {u[1] for u in used}:
            continue
        used.add((i, j))
        n += 1
    return n


def found_particles(case, true, brightness=None, *, scale=1.0, split=None, grid=None):
    """The particles of ``true`` rendered and found; ``split``: ``split_brighter`` (None: the
    default); ``grid``: another voxel grid than the case's."""
    cam, cal, case_grid, _ = case
    img = scale * particle_image(cam, true, brightness, rays_per_particle=20000, seed=3)
    settings = ParticleSettings() if split is None else ParticleSettings(split_brighter=split)
    return reconstruct_volume(cal, img, case_grid if grid is None else grid, particles=settings)


@pytest.mark.parametrize("shift_vox", [(0.0, 0.0, 0.0), (0.37, 0.21, 0.4), (0.5, -0.5, -0.3)])
def test_merged_pairs_are_found_as_two(case, shift_vox):
    """Each pair makes one bright peak; the default splits it into two particles within the
    resolution cell of the true ones, and leaves the isolated ones single, on the case's
    voxel grid and on grids moved by fractions of a voxel (the voxels are a footprint wide:
    a split that hung on where a pair falls within its voxel would come and go)."""
    cell, grid = case[3], case[2]
    moved = VolumeGrid(tuple(np.asarray(grid.origin) + np.asarray(shift_vox) * grid.voxel),
                       grid.voxel, grid.shape)
    true = np.concatenate([singles(cell), pairs(cell)])
    off = found_particles(case, true, split=0.0, grid=moved)
    on = found_particles(case, true, grid=moved)
    assert matched(true, off.particle_position_effective, cell) <= len(true) - len(PAIR_CENTRES)
    assert matched(true, on.particle_position_effective, cell) == len(true)
    assert len(on.particle_position_effective) == len(true)
    # the halves carry half the peak's light, and their centroid is the peak's
    assert np.isclose(on.particle_intensity.sum(), off.particle_intensity.sum(), rtol=1e-6)


def test_a_bright_single_particle_stays_one(case):
    """A particle twice as bright as the others is one particle: its rays carry twice the
    light and it is tried, but its two fits find the same point (nearer than
    ``PARTED_CELLS[0]``) and it stays one."""
    cell = case[3]
    true = singles(cell)
    brightness = np.ones(len(true))
    brightness[::6] = 2.0
    res = found_particles(case, true, brightness)
    assert len(res.particle_position_effective) == len(true)
    assert matched(true, res.particle_position_effective, cell) == len(true)


def test_split_does_not_depend_on_the_exposure(case):
    """Scaling the image (exposure, gain) changes no particle: the tried peaks are relative
    to the median, the ray weights to the image's maximum."""
    cell = case[3]
    true = np.concatenate([singles(cell), pairs(cell)])
    a = found_particles(case, true).particle_position_effective
    b = found_particles(case, true, scale=7.3).particle_position_effective
    assert a.shape == b.shape
    assert np.abs((a - b) / cell).max() < 1e-3


@pytest.mark.parametrize("axis", [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0),
                                  (0.6, 0.8, 0.0), (0.6, 0.0, 0.8)])
def test_blob_axes_finds_the_long_axis(axis):
    """A Gaussian blob three times longer along ``axis`` (in cell units) than across it."""
    grid = VolumeGrid((0.0, 0.0, 0.0), (1e-4, 1e-4, 4e-4), (21, 21, 21))
    cell = np.array([1e-4, 1e-4, 4e-4])
    centre = np.array([10, 10, 10]) * np.asarray(grid.voxel)
    z, y, x = np.meshgrid(*(np.arange(21),) * 3, indexing="ij")
    at = (np.stack([x, y, z], -1) * np.asarray(grid.voxel) - centre) / cell
    e = np.asarray(axis) / np.linalg.norm(axis)
    along = at @ e
    across = np.linalg.norm(at - along[..., None] * e, axis=-1)
    vol = np.exp(-0.5 * (along / 0.9) ** 2 - 0.5 * (across / 0.3) ** 2)
    got = blob_axes(vol, grid, centre[None, :], cell)[0]
    # the window is ±1 voxel across: a diagonal is found to within about 10°
    assert abs(got @ e) > np.cos(np.radians(12))


def test_what_the_volume_peaks_feed_does_not_change(case):
    """The split adds particles to the particle table only: the PIV's particles per window
    and the tracks' seeds are the volume's peaks (``VolumeResult.volume_peaks``), one per
    peak with the split halves' intensities summed, as without the split."""
    from plenopiv.particles.bundle import PARTICLE_BUNDLE
    from plenopiv.piv.settings import PIVSettings
    from plenopiv.workflow.correlation import correlate
    from plenopiv.workflow.tracking import physical_bundle

    cam, cal, grid, cell = case
    true = np.concatenate([singles(cell), pairs(cell)])
    off = found_particles(case, true, split=0.0)
    on = found_particles(case, true)
    assert len(on.particle_position_effective) > len(off.particle_position_effective)
    for got, want in zip(on.volume_peaks(), (off.volume_position_effective,
                                             off.particle_intensity), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12)
    piv = PIVSettings(windows=((16, 8, 8),), overlap=0.5, min_particles_per_window=1)
    a, b = correlate(on, on, piv, names=None), correlate(off, off, piv, names=None)
    np.testing.assert_array_equal(a.particles_per_window, b.particles_per_window)
    np.testing.assert_array_equal(a.valid, b.valid)
    from plenopiv.lightfield import light_field
    img = particle_image(cam, true, rays_per_particle=20000, seed=3)
    lf = light_field(cal)
    pos_on = physical_bundle(lf, img, on, PARTICLE_BUNDLE, cell[2], forward=None)[0]
    pos_off = physical_bundle(lf, img, off, PARTICLE_BUNDLE, cell[2], forward=None)[0]
    np.testing.assert_allclose(pos_on, pos_off, rtol=0, atol=1e-12)


@pytest.mark.parametrize("value, words", [("0.5", "above 1"), ("-1", "greater than or equal"),
                                          ("nan", "finite"), ('"x"', "valid number")])
def test_a_bad_split_factor_is_refused_naming_the_key(tmp_path, value, words):
    """``[particles] split_brighter`` is 0 (off) or a factor above 1: a factor at or below 1
    would try every peak."""
    from plenopiv.config.experiment import load_experiment
    from plenopiv.errors import ConfigError

    path = tmp_path / "exp.toml"
    path.write_text('camera = "small_test"\n[volume]\nx_mm = [-1.0, 1.0]\ny_mm = [-1.0, 1.0]\n'
                    f'z_mm = [-1.0, 1.0]\nvoxel_mm = 0.1\n[particles]\nsplit_brighter = {value}\n')
    with pytest.raises(ConfigError, match=rf"\[particles\] split_brighter.*{words}"):
        load_experiment(path)
    path.write_text(path.read_text().replace(f"split_brighter = {value}", "split_brighter = 0"))
    assert load_experiment(path).particles.split_brighter == 0
