"""The recording checked against its calibration (plenopiv.calibration.recording).

The lenslet array of a 25 x 31-lenslet camera moves on the sensor after its calibration (its
offset and rotation change); particle images recorded then are checked against the
calibration made before. Shifts and rotations drawn at random, of sub-pixel and of
multi-pixel size: below the tolerance (0.25 px) they are accepted, above it refused with the
figure, or corrected when allowed, and the corrected reconstruction finds the particles
where a reconstruction with the moved array's own calibration does.

A micro-image moves by k = 1 + f̄/S_i times the array's offset (p = k d), 7.4 µm pixels:
0.1355 px per µm.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from plenopiv.calibration.model import Calibration
from plenopiv.calibration.recording import check_recording
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import CalibrationError, PlenopivWarning
from plenopiv.lightfield import light_field
from plenopiv.reconstruction.mart import reconstruction_quality
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.synthetic.images import finish_image, particle_image
from plenopiv.synthetic.seeding import SeedingBox, random_particles
from plenopiv.workflow.volume import reconstruct_volume

PX_PER_M = (1 + 500e-6 / 0.2) / 7.4e-6


@pytest.fixture(scope="module")
def camera(small_camera):
    return small_camera.patch(25, 31, margin_px=12)


@pytest.fixture(scope="module")
def calibration(camera):
    return Calibration.from_camera(camera)


@pytest.fixture(scope="module")
def particles(camera):
    box = SeedingBox.field_of_view(camera, (-2e-3, 2e-3))
    return random_particles(box, 500, np.random.default_rng(8))


def moved(camera, offset_px, rotation):
    """The camera with its array moved so that its micro-images shift by ``offset_px``
    ``(row, col)`` and rotate by ``rotation`` about the axis."""
    mla = dataclasses.replace(camera.microlens_array, rotation=rotation,
                              offset=(offset_px[1] / PX_PER_M, offset_px[0] / PX_PER_M))
    return camera.replace(microlens_array=mla)


def recording(camera, positions, seed):
    """A noisy 12-bit-like particle image (photon noise, black level 30 counts)."""
    irr = particle_image(camera, positions, rays_per_particle=1500, seed=seed)
    rng = np.random.default_rng(seed)
    return finish_image(irr, noise="poisson", bit_depth=16, full_well=20000.0,
                        peak_fraction=0.5, read_noise=3.0, rng=rng) + np.uint16(30)


def expected_displacement(calibration, shift, rotation):
    """The largest displacement of a micro-image by ``shift`` and ``rotation``, px."""
    centre = (np.array(calibration.camera.sensor.shape) - 1) / 2.0
    d = np.asarray(calibration.focal_spot_px) - centre
    c, s = math.cos(rotation), math.sin(rotation)
    moved_d = np.column_stack([s * d[:, 1] + c * d[:, 0], c * d[:, 1] - s * d[:, 0]])
    return float(np.hypot(*(moved_d - d + shift).T).max())


def random_moves(n, scale, seed):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        angle = rng.uniform(0, 2 * np.pi)
        size = rng.uniform(0.5, 1.0) * scale
        out.append(((size * np.sin(angle), size * np.cos(angle)),
                    rng.uniform(-1, 1) * scale / 300.0))
    return out


# sub-pixel moves well below the tolerance, sub-pixel ones above it, multi-pixel ones
BELOW = random_moves(2, 0.08, 1)
ABOVE = random_moves(2, 0.7, 2) + random_moves(2, 4.0, 3)


@pytest.mark.parametrize("shift, rotation", BELOW)
def test_below_the_tolerance_is_accepted(camera, calibration, particles, shift, rotation):
    img = recording(moved(camera, shift, rotation), particles, 1)
    check = check_recording(calibration, img)
    assert check.calibration is calibration and check.measured and not check.corrected
    assert check.max_displacement_px < 0.25
    assert abs(check.max_displacement_px
               - expected_displacement(calibration, shift, rotation)) < 0.06


@pytest.mark.parametrize("shift, rotation", ABOVE)
def test_above_the_tolerance_is_refused_or_corrected(camera, calibration, particles, shift,
                                                     rotation):
    pair = [recording(moved(camera, shift, rotation), particles, s) for s in (2, 3)]
    want = expected_displacement(calibration, shift, rotation)
    assert want > 0.35
    with pytest.raises(CalibrationError, match=r"micro-images lie up to (\d+\.\d+) ± \d\.\d+ px "
                                               r"from the calibration's \(shift .* rotation "
                                               r".* mrad.*lattice_tolerance_px = 0\.25.*"
                                               r"lattice_check = \"correct\""):
        check_recording(calibration, pair)
    with pytest.warns(PlenopivWarning, match="moved onto the recording"):
        check = check_recording(calibration, np.stack(pair), correct=True)
    cal = check.calibration
    assert check.corrected and cal is not calibration
    np.testing.assert_allclose(check.shift_px, shift, atol=0.06)
    assert check.rotation_rad == pytest.approx(rotation, abs=0.2e-3)
    assert check.max_displacement_px == pytest.approx(want, abs=0.08)
    # the corrected calibration's micro-images are where the moved camera's are
    truth = Calibration.from_camera(moved(camera, shift, rotation)).focal_spot_px
    assert np.abs(np.asarray(cal.focal_spot_px) - truth).max() < 0.08
    again = check_recording(cal, pair)
    assert again.calibration is cal and again.max_displacement_px < 0.1


def test_images_without_micro_images_are_not_measured(calibration, camera):
    dots = np.zeros(camera.sensor.shape)
    dots[::37, ::41] = 3000.0
    check = check_recording(calibration, dots)
    assert not check.measured and check.calibration is calibration
    assert "no micro-image lattice" in check.note
    one = particle_image(camera, np.zeros((1, 3)), rays_per_particle=2000, seed=1)
    check = check_recording(calibration, one)
    assert not check.measured and "too little light" in check.note
    with pytest.raises(CalibrationError, match="image 0 is 10 × 10 pixels"):
        check_recording(calibration, np.zeros((10, 10)))
    with pytest.raises(ValueError, match="tolerance_px"):
        check_recording(calibration, one, tolerance_px=0.0)


def _grid(calibration, n=(14, 12, 10)):
    b = light_field(calibration).footprint
    vx, vz = b, 2.5 * b
    nx, ny, nz = n
    return VolumeGrid.from_bounds((-nx / 2 * vx, nx / 2 * vx), (-ny / 2 * vx, ny / 2 * vx),
                                  (-nz / 2 * vz, nz / 2 * vz), voxel=(vx, vx, vz))


@pytest.mark.parametrize("shift, rotation", [((1.9, -1.8), 1.5e-3), ((3.1, 2.2), -3e-3)])
def test_the_corrected_reconstruction_finds_the_particles_as_an_unmoved_one(
        camera, calibration, shift, rotation):
    """Twelve particles within ±6 footprints of focus, the array moved by 2.6 or 3.8 px and
    1.5 or 3 mrad. The reconstruction with the calibration made before is refused by default;
    corrected, it is the reconstruction with the moved array's own calibration (Q > 0.99,
    most particles within 0.1 footprint, to the 0.02-0.05 px the check measures the shift
    to); unchecked, it is not (Q 0.65-0.85, particles 0.5-7
    footprints away). The unmoved camera itself samples the particles through other
    lenslets, so its volume is not the reference."""
    grid = _grid(calibration, (16, 14, 12))
    b = light_field(calibration).footprint
    positions = np.random.default_rng(4).uniform(-1, 1, (12, 3)) * np.array([6.0, 5.0, 6.0]) * b
    moved_camera = moved(camera, shift, rotation)
    image = particle_image(moved_camera, positions, rays_per_particle=4000, seed=5)
    base = ReconstructionSettings(iterations=5)
    with pytest.raises(CalibrationError, match="lattice_tolerance_px"):
        reconstruct_volume(calibration, image, grid, settings=base)
    exact = reconstruct_volume(Calibration.from_camera(moved_camera), image, grid,
                               settings=dataclasses.replace(base, lattice_check="off"))
    with pytest.warns(PlenopivWarning, match="moved onto the recording"):
        fixed = reconstruct_volume(calibration, image, grid, settings=dataclasses.replace(
            base, lattice_check="correct"))
    off = reconstruct_volume(calibration, image, grid,
                             settings=dataclasses.replace(base, lattice_check="off"))
    want = exact.particle_position_effective
    assert len(want) >= 6

    def distance(result):
        d, _ = cKDTree(result.particle_position_effective).query(want)
        return d / b

    assert reconstruction_quality(fixed.volume, exact.volume) > 0.99
    assert np.median(distance(fixed)) < 0.1 and np.mean(distance(fixed) < 0.1) >= 0.7
    assert reconstruction_quality(off.volume, exact.volume) < 0.9
    assert np.median(distance(off)) > 0.5


# ---- the kernels against their twins ---------------------------------------------------------


def test_soft_discs_kernel_matches_its_numpy_twin(rng):
    """Discs near and across the image's edges, overlapping where spots are close."""
    from plenopiv.calibration._recording_kernels import soft_discs, soft_discs_numpy

    spots = np.vstack([rng.uniform(-5, 45, (30, 2)), [[0.5, 0.5], [20.5, 20.49999]]])
    for radius, edge in ((3.2, 1.0), (6.0, 0.5)):
        np.testing.assert_allclose(soft_discs((40, 52), spots, radius, edge),
                                   soft_discs_numpy((40, 52), spots, radius, edge),
                                   rtol=0, atol=1e-12)


def test_tiles_and_their_correlations_are_those_of_one_tile_at_a_time(rng):
    """The tiles holding spots (sorted search) are those a tile-by-tile count finds, and the
    correlations transformed together (FFT sizes rounded up) are each tile's own."""
    from plenopiv.calibration import recording as rec

    shape, size, pitch, reach = (95, 130), 24, 7.5, 6
    spots = rng.uniform(-10, 140, (160, 2)) * (0.75, 1.0)
    tiles = rec._tiles_with_spots(shape, spots, size, pitch)
    expected = []
    for r0 in range(0, shape[0] - size // 2, size):
        for c0 in range(0, shape[1] - size // 2, size):
            r1, c1 = min(r0 + size, shape[0]), min(c0 + size, shape[1])
            inside = np.all((spots >= (r0 - pitch, c0 - pitch))
                            & (spots < (r1 + pitch, c1 + pitch)), axis=1)
            if inside.sum() >= 4:
                expected.append((r0, c0, r1, c1))
    assert tiles == expected and len({(t[2] - t[0], t[3] - t[1]) for t in tiles}) > 1
    image, model = rng.random(shape), rng.random(shape)
    corrs = rec._tile_correlations(image, model, tiles, reach)
    for (r0, c0, r1, c1), corr in zip(tiles, corrs, strict=True):
        m, w = image[r0:r1, c0:c1], model[r0:r1, c0:c1]
        np.testing.assert_allclose(corr, rec._correlation(m - m.mean(), w - w.mean(), reach),
                                   rtol=0, atol=1e-9 * m.size)
    lights = rec._tile_lights(image, tiles)
    for (r0, c0, r1, c1), light in zip(tiles, lights, strict=True):
        m = image[r0:r1, c0:c1]
        assert light == pytest.approx(np.sum(np.clip(m - np.median(m), 0.0, None)), rel=1e-12)
