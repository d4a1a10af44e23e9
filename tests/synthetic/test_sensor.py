"""A real recording in the simulator: the sensor, the lenslets' throughput and vignetting, the
light (plenopiv.synthetic.sensor), each effect alone with the statistics it claims, the camera
instance shared by its frames, and ``plenopiv simulate dark|white|--realistic``."""

from __future__ import annotations

import dataclasses
import json
import math

import h5py
import numpy as np
import pytest
import tifffile
from pydantic import ValidationError
from scipy.spatial import cKDTree

from plenopiv.camera.optics import focal_spot_exact
from plenopiv.cli import build_parser, main
from plenopiv.conventions import pixel_to_sensor, sensor_to_pixel
from plenopiv.synthetic.flows import Uniform
from plenopiv.synthetic.images import (
    Ruler,
    alignment_image,
    auto_exposure,
    finish_image,
    focal_point_image,
    particle_image,
    ruler_image,
    white_image,
)
from plenopiv.synthetic.seeding import SeedingBox, random_particles, simulate_pair
from plenopiv.synthetic.sensor import (
    REALISTIC,
    RecordingSettings,
    camera_instance,
    glow_field,
    optical_gain,
    particle_brightness,
    particle_peak_irradiance,
    sheet_illumination,
    vignetting_coefficient,
)

#: The sensor of most tests: 100 counts of black level, 3 of read noise, a 12-bit ADC.
SENSOR = RecordingSettings(black_level_counts=100.0, read_noise_counts=3.0, adc_bits=12)


@pytest.fixture(scope="module")
def patch(small_camera):
    """9 × 11 lenslets of the small camera (S_i = 200 mm, f/2.8): 159 × 193 pixels."""
    return small_camera.patch(9, 11)


def _frames(instance, irradiance, n, rng, *, noise="poisson", exposure=1.0):
    return np.stack([finish_image(irradiance, exposure=exposure, noise=noise, rng=rng,
                                  sensor=instance).astype(float) for _ in range(n)])


def _lenslet_of_pixels(camera, centre="micro-image"):
    """Each pixel's lenslet (nearest micro-image centre) and its distance from the micro-
    image's centre in half micro-image pitches (``centre="lenslet"``: from the lenslet's
    axis in half lenslet pitches), found independently of the simulator's kernel."""
    mla = camera.microlens_array
    centres = mla.centres()
    spots = focal_spot_exact(centres, camera.image_distance, mla.sensor_distance)
    rows, cols = np.indices(camera.sensor.shape)
    pix = pixel_to_sensor(np.stack([rows, cols], axis=-1), camera.sensor.shape,
                          camera.sensor.pixel_pitch).reshape(-1, 2)
    _, k = cKDTree(spots).query(pix)
    if centre == "lenslet":
        rho = np.hypot(*(pix - centres[k]).T) / (0.5 * mla.pitch)
    else:
        scale = 1 + mla.sensor_distance / camera.image_distance
        rho = np.hypot(*(pix - spots[k]).T) / (0.5 * mla.pitch * scale)
    return k.reshape(camera.sensor.shape), rho.reshape(camera.sensor.shape)


# ---- the ideal defaults ---------------------------------------------------------------------


def test_the_defaults_are_ideal_and_the_settings_strict():
    ideal = RecordingSettings()
    assert ideal.is_ideal and not ideal.has_sensor and not ideal.has_optics
    assert not REALISTIC.is_ideal and REALISTIC.has_sensor and REALISTIC.has_optics
    with pytest.raises(ValidationError, match="vignetting"):
        RecordingSettings(vignetting=1.0)
    with pytest.raises(ValidationError, match="black_level"):
        RecordingSettings(black_levels=3.0)
    with pytest.raises(ValidationError, match="adc_bits"):
        RecordingSettings(adc_bits=17)
    with pytest.raises(ValidationError):
        RecordingSettings(glow=float("nan"))
    with pytest.raises(dataclasses.FrozenInstanceError):
        ideal.glow = 1.0


def test_ideal_settings_reproduce_every_render_bit_for_bit(patch):
    inst = camera_instance(patch, RecordingSettings(), seed=11)
    pos = np.array([[0.0, 0.0, 0.0], [0.3e-3, -0.2e-3, 2e-3], [-0.4e-3, 0.1e-3, -3e-3]])
    pairs = [
        (focal_point_image(patch, f_number=16), focal_point_image(patch, f_number=16,
                                                                  instance=inst)),
        (alignment_image(patch), alignment_image(patch, instance=inst)),
        (ruler_image(patch, Ruler(1e-3), rays_per_lenslet=50),
         ruler_image(patch, Ruler(1e-3), rays_per_lenslet=50, instance=inst)),
        (particle_image(patch, pos, rays_per_particle=256),
         particle_image(patch, pos, rays_per_particle=256, instance=inst)),
    ]
    for plain, with_instance in pairs:
        assert np.array_equal(plain, with_instance)
    irr = pairs[3][0]
    for kw in ({}, {"noise": "poisson", "read_noise": 2.0}, {"bit_depth": None}):
        a = finish_image(irr, rng=np.random.default_rng(3), **kw)
        b = finish_image(irr, rng=np.random.default_rng(3), sensor=inst, **kw)
        assert a.dtype == b.dtype and np.array_equal(a, b)
    box = SeedingBox.field_of_view(patch, (-2e-3, 2e-3), fill=0.5)
    flow = Uniform((0.1, 0.0, 0.0))
    a = simulate_pair(patch, flow, dt=1e-3, box=box, n_particles=5, rays_per_particle=64,
                      rng=np.random.default_rng(1))
    b = simulate_pair(patch, flow, dt=1e-3, box=box, n_particles=5, rays_per_particle=64,
                      rng=np.random.default_rng(1), instance=inst)
    assert np.array_equal(a.image_a, b.image_a) and np.array_equal(a.image_b, b.image_b)
    assert np.array_equal(a.intensities, b.intensities)


def test_the_default_command_line_renders_as_the_ideal_simulator(tmp_path, capsys):
    """Without recording options ``simulate particles`` is seeding, rendering and finishing
    exactly as before the recording model; explicit ideal values change nothing."""
    from plenopiv.camera.model import load_camera

    cam = load_camera("small_test").patch(9, 11)
    common = ["simulate", "particles", "small_test", "--lenslets", "9", "11", "--n-particles",
              "6", "--rays-per-particle", "64", "--noise", "poisson", "--quiet"]
    assert main([*common, "--out", str(tmp_path / "a.tif")]) == 0
    assert main([*common, "--out", str(tmp_path / "b.tif"), "--camera-seed", "9",
                 "--black-level", "0", "--vignetting", "0", "--glow", "0"]) == 0
    capsys.readouterr()
    rng = np.random.default_rng(0)
    box = SeedingBox.field_of_view(cam, (-5e-3, 5e-3), fill=0.9)
    pos = random_particles(box, 6, rng)
    irr = particle_image(cam, pos, rays_per_particle=64, seed=0)
    want = finish_image(irr, noise="poisson", rng=rng)
    assert np.array_equal(tifffile.imread(tmp_path / "a.tif"), want)
    assert np.array_equal(tifffile.imread(tmp_path / "b.tif"), want)
    assert "recording" not in json.loads(tifffile.TiffFile(tmp_path / "a.tif")
                                         .pages[0].description)


# ---- the sensor -----------------------------------------------------------------------------


def test_a_dark_frame_has_its_black_level_fixed_pattern_read_noise_and_hot_pixels(
        small_camera, rng):
    s = dataclasses.replace(SENSOR, column_offset_counts=1.5, pixel_offset_counts=2.6,
                            hot_pixel_fraction=1e-4, hot_pixel_counts=1000.0)
    inst = camera_instance(small_camera, s, seed=5)
    n = 8
    dark = _frames(inst, np.zeros(small_camera.sensor.shape), n, rng)
    hot = inst.hot_mask
    # about 1e-4 of the 728,000 pixels are hot, at the seeded places in every frame
    assert 40 <= hot.sum() <= 110
    for frame in dark:
        assert np.array_equal(np.flatnonzero(frame > 100 + 20 * 3), inst.hot_index)
    # their dark signal: 0.5 to 1.5 times 1000 counts, with its shot noise (~0.205 counts/e)
    excess = dark[:, hot].mean(axis=0) - 100
    assert np.allclose(excess, inst.hot_counts, atol=5 * math.sqrt(1500 * 4095 / 2e4 / n) + 5)
    good = dark[:, ~hot]
    assert abs(good.mean() - 100) < 0.2       # the column offsets' mean: 1.5/sqrt(1040)
    # read noise (and rounding) from frame to frame
    temporal = np.sqrt(((dark - dark.mean(axis=0)) ** 2).sum(axis=0) / (n - 1))[~hot]
    assert np.sqrt((temporal ** 2).mean()) == pytest.approx(math.sqrt(9 + 1 / 12), rel=0.02)
    # the fixed pattern: per column, then per pixel
    mean = np.where(hot, np.nan, dark.mean(axis=0))
    columns = np.nanmean(mean, axis=0) - np.nanmean(mean)
    assert columns.std() == pytest.approx(1.5, rel=0.08)
    assert np.corrcoef(columns, inst.column_offset)[0, 1] > 0.99
    pixels = (mean - np.nanmean(mean, axis=0))[~hot]
    assert pixels.std() == pytest.approx(math.sqrt(2.6 ** 2 + (9 + 1 / 12) / n), rel=0.03)
    assert np.corrcoef(pixels, inst.pixel_offset[~hot])[0, 1] > 0.9


def test_counts_saturate_at_the_adc_full_scale_and_the_full_well(patch):
    irr = focal_point_image(patch, f_number=4)
    for bits in (12, 10):
        inst = camera_instance(patch, dataclasses.replace(SENSOR, adc_bits=bits))
        img = finish_image(irr, exposure=10 * auto_exposure(irr, sensor=inst),
                           rng=np.random.default_rng(0), sensor=inst)
        assert img.dtype == np.uint16 and img.max() == 2 ** bits - 1
        assert (img == 2 ** bits - 1).mean() > 0.3
    # a small gain: the full well (20,000 e at 0.1 counts/e = 2000 counts) fills first
    inst = camera_instance(patch, dataclasses.replace(SENSOR, read_noise_counts=0.0,
                                                      gain_counts_per_electron=0.1))
    img = finish_image(irr, exposure=1e6, sensor=inst)
    assert img.max() == 100 + 2000
    with pytest.raises(Exception, match="integer counts"):
        finish_image(irr, bit_depth=None, sensor=inst)
    with pytest.raises(Exception, match="adc_bits = 12"):
        finish_image(irr, bit_depth=8, rng=np.random.default_rng(0),
                     sensor=camera_instance(patch, SENSOR))


def test_dead_pixels_do_not_see_light(patch):
    s = dataclasses.replace(SENSOR, read_noise_counts=0.0, dead_pixel_fraction=0.01)
    inst = camera_instance(patch, s, seed=2)
    white = finish_image(white_image(patch), sensor=inst)
    assert 0.006 < inst.dead_mask.mean() < 0.014
    assert np.all(white[inst.dead_mask] == 100)
    assert not np.intersect1d(inst.dead_index, inst.hot_index).size


# ---- optics and light -----------------------------------------------------------------------


@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.3, -0.7)])
def test_optical_gain_kernel_matches_its_numpy_twin(auburn_camera, shift):
    mla = dataclasses.replace(auburn_camera.microlens_array, grid="hexagonal", rotation=0.01,
                              offset=(3e-6, -2e-6))
    for cam in (auburn_camera.patch(5, 7), auburn_camera.replace(microlens_array=mla)
                .patch(5, 7)):
        for centre in ("micro-image", "lenslet"):
            s = RecordingSettings(throughput_spread=0.1, vignetting=0.2,
                                  vignetting_centre=centre)
            inst = camera_instance(cam, s, seed=4)
            a = optical_gain(cam, inst, sensor_shift_px=shift)
            b = optical_gain(cam, inst, sensor_shift_px=shift, engine="numpy")
            assert np.allclose(a, b, rtol=0, atol=1e-12)


def test_the_throughput_spread_over_lenslets_of_a_white_frame(small_camera, rng):
    """A white frame, dark-subtracted and divided by the ideal white, gives back each
    lenslet's throughput, uniform in 1 ± 0.1 (rms 0.1/√3), within photon noise."""
    cam = small_camera.patch(21, 31)
    s = dataclasses.replace(SENSOR, column_offset_counts=1.5, pixel_offset_counts=2.6,
                            throughput_spread=0.1)
    inst = camera_instance(cam, s, seed=8)
    ideal = white_image(cam)
    irr = white_image(cam, instance=inst)
    exposure = auto_exposure(irr, sensor=inst)
    white = _frames(inst, irr, 1, rng, exposure=exposure)[0]
    dark = _frames(inst, np.zeros(cam.sensor.shape), 8, rng).mean(axis=0)
    mla = cam.microlens_array
    spots = sensor_to_pixel(focal_spot_exact(mla.centres(), cam.image_distance,
                                             mla.sensor_distance),
                            cam.sensor.shape, cam.sensor.pixel_pitch)
    r0, c0 = np.rint(spots).astype(int).T
    box = [(dr, dc) for dr in (-2, -1, 0, 1, 2) for dc in (-2, -1, 0, 1, 2)]
    signal = np.mean([white[r0 + dr, c0 + dc] - dark[r0 + dr, c0 + dc] for dr, dc in box],
                     axis=0)
    expected = np.mean([exposure * ideal[r0 + dr, c0 + dc] for dr, dc in box], axis=0)
    factor = signal / expected
    # photon noise of ~16,000 e per pixel over 25 pixels: 0.16 %
    assert np.abs(factor - inst.throughput).max() < 0.01
    assert factor.std() == pytest.approx(0.1 / math.sqrt(3), rel=0.08)
    assert 0.9 <= inst.throughput.min() and inst.throughput.max() <= 1.1
    # a calibration image carries the same throughputs: each focal spot's light
    fp0 = focal_point_image(cam, f_number=16)
    fp = focal_point_image(cam, f_number=16, instance=inst)
    k, _ = _lenslet_of_pixels(cam)
    sums = np.bincount(k.ravel(), fp.ravel(), mla.count)
    sums0 = np.bincount(k.ravel(), fp0.ravel(), mla.count)
    assert np.allclose(sums / sums0, inst.throughput, rtol=1e-9)


def test_a_white_image_of_the_same_camera_is_its_flat_field(patch):
    """The optical gain multiplies every render of one camera alike: a focal-point image
    divided by the white image is the ideal one divided by the ideal white."""
    inst = camera_instance(patch, RecordingSettings(throughput_spread=0.1, vignetting=0.2),
                           seed=6)
    ideal_white = white_image(patch, f_number=4)
    lit = ideal_white > 0.05 * ideal_white.max()
    flat = white_image(patch, f_number=4, instance=inst)[lit]
    for render in (lambda **kw: focal_point_image(patch, f_number=16, **kw),
                   lambda **kw: alignment_image(patch, **kw)):
        assert np.allclose(render(instance=inst)[lit] / flat,
                           render()[lit] / ideal_white[lit], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("centre", ["micro-image", "lenslet"])
def test_the_vignetting_profile_inside_a_micro_image(patch, centre):
    """20 % lost at the rim, half a pitch from the centre, falling as (1 + a ρ²)^-2."""
    inst = camera_instance(patch, RecordingSettings(vignetting=0.2, vignetting_centre=centre))
    ideal = white_image(patch)
    ratio = white_image(patch, instance=inst) / np.where(ideal > 0, ideal, 1.0)
    lit = ideal > 0.5 * ideal.max()
    _, rho = _lenslet_of_pixels(patch, centre)
    a = vignetting_coefficient(0.2)
    assert np.allclose(ratio[lit], (1 + a * rho[lit] ** 2) ** -2, rtol=1e-9)
    # measured: the coefficient fitted on the lit pixels gives 80 % at the rim
    outer = lit & (rho > 0.3)
    assert outer.sum() > 500
    a_fit = np.median((ratio[outer] ** -0.5 - 1) / rho[outer] ** 2)
    assert (1 + a_fit) ** -2 == pytest.approx(0.8, abs=1e-6)
    centre = lit & (rho < 0.15)
    assert centre.sum() > 50
    assert ratio[centre].mean() == pytest.approx(1.0, abs=0.005)
    bins = np.digitize(rho[lit], [0.2, 0.4, 0.6, 0.8])
    profile = [ratio[lit][bins == b].mean() for b in range(5)]
    assert np.all(np.diff(profile) < 0)


def test_particle_brightness_is_log_normal(patch, rng):
    s = RecordingSettings(brightness_sigma_ln=0.3)
    w = particle_brightness(20000, s, rng)
    assert np.log(w).std() == pytest.approx(0.3, rel=0.02)
    assert np.median(w) == pytest.approx(1.0, abs=0.01)
    assert particle_brightness(5, RecordingSettings(), rng) is None
    # an image is the sum of its particles: its light scales with their brightness
    inst = camera_instance(patch, s)
    box = SeedingBox.field_of_view(patch, (-1e-3, 1e-3), fill=0.5)
    pair = simulate_pair(patch, Uniform((0.0, 0.0, 0.0)), dt=1e-3, box=box, n_particles=400,
                         rays_per_particle=16, rng=rng, instance=inst)
    assert np.log(pair.intensities).std() == pytest.approx(0.3, abs=3 * 0.3 / math.sqrt(400))
    ones = particle_image(patch, pair.positions_a, rays_per_particle=16)
    bright = particle_image(patch, pair.positions_a, pair.intensities, rays_per_particle=16)
    assert bright.sum() / ones.sum() == pytest.approx(pair.intensities.mean(), rel=1e-3)


def test_the_second_pulse_carries_its_energy_ratio(small_camera, rng):
    """Totals of B over A, dark-subtracted, are 0.85 within photon and read noise."""
    s = dataclasses.replace(SENSOR, pulse_ratio=0.85)
    inst = camera_instance(small_camera, s, seed=1)
    box = SeedingBox.field_of_view(small_camera, (-3e-3, 3e-3), fill=0.6)
    pair = simulate_pair(small_camera, Uniform((0.05, 0.0, 0.0)), dt=1e-3, box=box,
                         n_particles=300, rays_per_particle=64, rng=rng, instance=inst)
    ideal = pair.image_b.sum() / pair.image_a.sum()
    assert ideal == pytest.approx(0.85, rel=2e-3)      # a few rays leave the array's edge
    exposure = auto_exposure(pair.image_a, sensor=inst)
    a, b = (finish_image(im, exposure=exposure, noise="poisson", rng=rng, sensor=inst)
            - inst.offset for im in (pair.image_a, pair.image_b))
    total_a, total_b = a.sum(), b.sum()
    gain = 4095 / 2e4
    sigma = math.sqrt(gain * total_a + a.size * (9 + 1 / 12)) / total_a
    assert total_b / total_a == pytest.approx(ideal, abs=4 * math.sqrt(2) * sigma)


def test_the_depth_profile_of_the_light(patch):
    zs = np.array([-4e-3, -2e-3, -1e-3, 0.0, 1e-3, 3e-3])
    gauss = RecordingSettings(sheet_profile="gaussian", sheet_centre_mm=0.5,
                              sheet_thickness_mm=4.0)
    tophat = dataclasses.replace(gauss, sheet_profile="tophat")
    g = sheet_illumination(zs, gauss)
    assert sheet_illumination(np.array([-1.5e-3, 2.5e-3, 0.5e-3]), gauss) == \
        pytest.approx([0.5, 0.5, 1.0])
    assert np.array_equal(sheet_illumination(zs, tophat), [0, 0, 1, 1, 1, 0])
    assert np.array_equal(sheet_illumination(zs, RecordingSettings()), np.ones(6))
    inst = camera_instance(patch, gauss)
    for z, want in zip(zs, g, strict=True):
        pos = np.array([[0.0, 0.0, z]])
        lit = particle_image(patch, pos, rays_per_particle=256, instance=inst)
        plain = particle_image(patch, pos, rays_per_particle=256)
        assert lit.sum() / plain.sum() == pytest.approx(want, rel=1e-9)


def test_the_glow_is_smooth_and_a_fraction_of_a_particle_peak(patch):
    inst = camera_instance(patch, RecordingSettings(glow=0.02), seed=3)
    pos = np.array([[0.0, 0.0, 0.0]])        # in focus, on the axis: one lenslet's light
    plain = particle_image(patch, pos, rays_per_particle=4096)
    glowing = particle_image(patch, pos, rays_per_particle=4096, instance=inst)
    second = particle_image(patch, pos, rays_per_particle=4096, instance=inst,
                            pulse_energy=0.5)
    glow = glowing - plain
    ref = particle_peak_irradiance(patch)
    assert glow.max() == pytest.approx(0.02 * ref, rel=1e-9)
    assert np.allclose(second - 0.5 * plain, 0.5 * glow, rtol=1e-9, atol=1e-18)
    # the in-focus particle fills its micro-image at about the reference irradiance
    assert plain.max() == pytest.approx(ref, rel=0.15)
    field = glow_field(inst)
    assert field.max() == pytest.approx(1.0) and field.min() > 0
    assert np.abs(np.diff(field, axis=1)).max() < 0.01     # low frequency
    other = glow_field(camera_instance(patch, RecordingSettings(glow=0.02), seed=4))
    assert not np.allclose(field, other)


# ---- one camera instance, many frames -------------------------------------------------------


def test_dark_white_and_particle_frames_of_one_camera_seed_share_its_camera(small_camera,
                                                                           rng):
    cam = small_camera.patch(15, 21)
    s = dataclasses.replace(REALISTIC, hot_pixel_fraction=1e-3, glow=0.0)
    darks = {seed: _frames(camera_instance(cam, s, seed=seed), np.zeros(cam.sensor.shape), 8,
                           rng) for seed in (7, 8)}
    hot = {seed: camera_instance(cam, s, seed=seed).hot_mask for seed in (7, 8)}
    for seed in (7, 8):
        assert all(np.array_equal(f > 300, hot[seed]) for f in darks[seed])
    assert (hot[7] & hot[8]).sum() <= 2 and hot[7].sum() > 40
    dark = {seed: d.mean(axis=0) for seed, d in darks.items()}
    # a particle frame of seed 7: its background is seed 7's dark frame, not seed 8's
    inst = camera_instance(cam, s, seed=7)
    box = SeedingBox.field_of_view(cam, (-2e-3, 2e-3), fill=0.8)
    pos = random_particles(box, 20, rng)
    irr = particle_image(cam, pos, rays_per_particle=256, instance=inst)
    frame = finish_image(irr, noise="poisson", rng=rng, sensor=inst).astype(float)
    plain = particle_image(cam, pos, rays_per_particle=256)
    background = plain == 0
    same = (frame - dark[7])[background]
    assert 30 < np.count_nonzero(hot[7] & background)
    assert np.sqrt((same ** 2).mean()) < 3.3        # read noise: 3 × sqrt(1 + 1/8)
    other = (frame - dark[8])[background & ~hot[7] & ~hot[8]]
    assert other.std() > 4.5                           # two fixed patterns of 3 counts
    # a white frame of seed 7, without photon noise: dark-subtracted, it is its light
    w_irr = white_image(cam, instance=inst)
    exposure = auto_exposure(w_irr, sensor=inst)
    white = finish_image(w_irr, exposure=exposure, rng=rng, sensor=inst).astype(float)
    ok = (white < 4095) & ~inst.dead_mask
    resid = (white - dark[7] - exposure * w_irr)[ok]
    assert np.sqrt((resid ** 2).mean()) < 3.4
    assert np.abs(white - dark[8] - exposure * w_irr)[ok & hot[7]].min() > 300
    # and its lenslets are seed 7's, not seed 8's
    other_inst = camera_instance(cam, s, seed=8)
    assert np.array_equal(optical_gain(cam, inst), optical_gain(cam, camera_instance(cam, s,
                                                                                     seed=7)))
    assert not np.allclose(inst.throughput, other_inst.throughput)


def test_each_effect_draws_from_its_own_stream(patch):
    a = camera_instance(patch, RecordingSettings(hot_pixel_fraction=1e-3), seed=3)
    b = camera_instance(patch, dataclasses.replace(REALISTIC, hot_pixel_fraction=1e-3,
                                                   dead_pixel_fraction=0.0), seed=3)
    assert np.array_equal(a.hot_index, b.hot_index)
    c = camera_instance(patch, RecordingSettings(hot_pixel_fraction=2e-3), seed=3)
    assert np.isin(a.hot_index, c.hot_index).all()      # more hot pixels: the same and more
    with pytest.raises(Exception, match="camera seed"):
        camera_instance(patch, REALISTIC, seed=-1)


# ---- the command line -----------------------------------------------------------------------


def _description(path, page=0) -> dict:
    with tifffile.TiffFile(path) as t:
        return json.loads(t.pages[page].description)


RECORDING_KEYS = {"preset", "camera_seed", "settings", "seed", "noise", "full_well",
                  "bit_depth", "blur_px", "exposure_counts_per_irradiance"}


def _check_recording(rec: dict, *, camera_seed: int, seed: int) -> None:
    assert set(rec) == RECORDING_KEYS
    assert rec["camera_seed"] == camera_seed and rec["seed"] == seed
    assert rec["settings"] == {**dataclasses.asdict(REALISTIC), **rec["settings"]}
    assert set(rec["settings"]) == {f.name for f in dataclasses.fields(RecordingSettings)}
    assert RecordingSettings(**rec["settings"]) is not None


def test_simulate_dark_and_white_write_their_frames_and_camera(tmp_path, capsys):
    from plenopiv.camera.model import load_camera

    cam = load_camera("small_test").patch(9, 11)
    common = ["small_test", "--lenslets", "9", "11", "--realistic", "--camera-seed", "3",
              "--hot-pixels", "1e-3", "--json", "--quiet"]
    assert main(["simulate", "dark", *common, "--frames", "3", "--seed", "1",
                 "--out", str(tmp_path / "dark.tif")]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["frames"] == 3 and summary["shape"] == [3, *cam.sensor.shape]
    assert summary["recording"]["effects"]["hot_pixel_fraction"] == 1e-3
    dark = tifffile.imread(tmp_path / "dark.tif")
    assert dark.shape == (3, *cam.sensor.shape) and dark.dtype == np.uint16
    meta = _description(tmp_path / "dark.tif")
    _check_recording(meta["recording"], camera_seed=3, seed=1)
    assert meta["recording"]["settings"]["hot_pixel_fraction"] == 1e-3
    inst = camera_instance(cam, RecordingSettings(**meta["recording"]["settings"]), seed=3)
    assert all(np.array_equal(np.flatnonzero(f > 300), inst.hot_index) for f in dark)
    assert abs(np.median(dark) - 100) <= 1

    assert main(["simulate", "white", *common, "--frames", "2",
                 "--out", str(tmp_path / "white.h5")]) == 0
    capsys.readouterr()
    with h5py.File(tmp_path / "white.h5") as fh:
        frames = fh["/frames"][()]
        assert fh.attrs["product"] == "synthetic white" and fh.attrs["frames"] == 2
        config = json.loads(fh.attrs["config"])
    assert frames.shape == (2, *cam.sensor.shape) and frames.max() == 4095   # hot pixels
    _check_recording(config["recording"], camera_seed=3, seed=0)
    assert np.all(frames[:, inst.hot_mask] > dark.mean(axis=0)[inst.hot_mask] - 100)
    assert not np.array_equal(frames[0], frames[1])                # each its own noise
    lit = frames[0] > 0.5 * frames[0].max()
    assert 0.3 < lit.mean() < 0.9

    assert main(["simulate", "dark", "small_test", "--lenslets", "9", "11", "--realistic",
                 "--out", str(tmp_path / "dark.h5"), "--quiet"]) == 0
    with h5py.File(tmp_path / "dark.h5") as fh:
        assert fh["/frames"].shape == (1, *cam.sensor.shape)
        assert fh.attrs["product"] == "synthetic dark"


def test_realistic_calibration_particle_and_pair_images_record_their_recording(tmp_path,
                                                                              capsys):
    lens = ["--lenslets", "9", "11"]
    runs = {"focal-point": [*lens, "--f-number", "16", "--out", "fp.tif"],
            "alignment": [*lens, "--out", "al.tif"],
            "ruler": [*lens, "--rays-per-lenslet", "50", "--out", "ru.tif"],
            "particles": [*lens, "--n-particles", "10", "--rays-per-particle", "64",
                          "--out", "p.h5"],
            "pair": ["--n-particles", "10", "--rays-per-particle", "64", "--out", "pair.h5"]}
    for kind, argv in runs.items():
        argv = [a if not a.endswith((".tif", ".h5")) else str(tmp_path / a) for a in argv]
        assert main(["simulate", kind, "small_test", "--realistic", "--camera-seed", "2",
                     "--seed", "4", "--json", "--quiet", *argv]) == 0, kind
        out = json.loads(capsys.readouterr().out)
        assert out["recording"]["preset"] == "realistic" and out["recording"]["camera_seed"] == 2
    for name in ("fp.tif", "al.tif", "ru.tif", "pair_A.tif", "pair_B.tif"):
        rec = _description(tmp_path / name)["recording"]
        _check_recording(rec, camera_seed=2, seed=4)
        assert rec["noise"] == "poisson" and rec["exposure_counts_per_irradiance"] > 0
        img = tifffile.imread(tmp_path / name)
        assert img.max() <= 4095 and np.median(img) > 90          # 12 bits over a black level
    for name in ("p.h5", "pair.h5"):
        with h5py.File(tmp_path / name) as fh:
            _check_recording(json.loads(fh.attrs["config"])["recording"], camera_seed=2,
                             seed=4)
            assert np.log(fh["/truth/intensity"][()]).std() > 0.1
    a = _description(tmp_path / "pair_A.tif")["recording"]
    assert a == _description(tmp_path / "pair_B.tif")["recording"]   # one exposure for both


def test_recording_options_override_the_preset_and_are_checked(tmp_path, capsys):
    out = str(tmp_path / "d.tif")
    assert main(["simulate", "dark", "small_test", "--lenslets", "5", "7", "--realistic",
                 "--black-level", "64", "--read-noise", "0", "--column-offset", "0",
                 "--pixel-offset", "0", "--hot-pixels", "0", "--out", out, "--quiet"]) == 0
    assert np.all(tifffile.imread(out) == 64)
    capsys.readouterr()
    bad = [(["dark", "--vignetting", "0.5"], "unrecognized"),
           (["white", "--vignetting", "1.5"], "--vignetting 1.5"),
           (["white", "--hot-pixels", "-1"], "--hot-pixels -1"),
           (["dark", "--frames", "0"], "--frames 0"),
           (["dark", "--camera-seed", "-2"], "--camera-seed -2"),
           (["focal-point", "--realistic", "--bit-depth", "0"], "integer counts"),
           (["focal-point", "--realistic", "--bit-depth", "8"], "adc_bits = 12"),
           (["particles", "--sheet", "cone"], "invalid choice")]
    for argv, message in bad:
        code = main(["simulate", argv[0], "small_test", "--lenslets", "5", "7", *argv[1:],
                     "--out", out])
        assert code == 2, argv
        assert message in capsys.readouterr().err, argv


def _kind_parsers():
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices["simulate"]
    return next(a for a in sub._actions if a.dest == "kind").choices


def test_help_lists_every_recording_option_with_the_preset_values():
    from plenopiv.cli import simulate as C

    kinds = _kind_parsers()
    assert {"dark", "white"} <= set(kinds)
    for kind, parser in kinds.items():
        text = parser.format_help()
        options = C.SENSOR_OPTIONS + (() if kind == "dark" else C.OPTICS_OPTIONS)
        if kind in ("particles", "pair"):
            options += C.LIGHT_OPTIONS
        if kind == "pair":
            options += C.PAIR_OPTIONS
        flags = [o[0] for o in options] + ["--realistic", "--camera-seed", "--read-noise"]
        flags += ["--frames"] if kind in ("dark", "white") else []
        for flag in flags:
            assert flag in text, (kind, flag)
    # the values the help gives for --realistic are the preset's
    for flag, field, _, _, helptext in (C.SENSOR_OPTIONS + C.OPTICS_OPTIONS + C.LIGHT_OPTIONS
                                        + C.PAIR_OPTIONS):
        if "with --realistic" in helptext:
            value = float(helptext.split(" with --realistic")[0].rsplit(" ", 1)[1])
            assert value == getattr(REALISTIC, field), flag
    assert "3 with --realistic" in kinds["dark"].format_help()          # --read-noise
    assert REALISTIC.read_noise_counts == 3
