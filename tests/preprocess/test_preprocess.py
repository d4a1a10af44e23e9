"""The preprocessing stage: kernels and twins, invariance to a sensor's defects, the contract.

A realistic frame is made here with NumPy on top of the ideal renders: a black level with a
fixed pattern (per column and per row), an amplifier glow in a corner, hot pixels (a dark
current of 200-2000 counts), read noise, each lenslet's transmission (±10 %) and the main
lens's vignetting, quantised to 12 bits. The stage, given the matching dark and white frames,
must give back the ideal render within that noise.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass

import h5py
import numpy as np
import pytest
import tifffile
from scipy.spatial import cKDTree

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.camera.resolution import resolution_cell
from plenopiv.cli import main
from plenopiv.errors import ConfigError, ImageError, PlenopivWarning
from plenopiv.preprocess import (
    PreprocessSettings,
    batch_background,
    dark_defects,
    exposure_level,
    flat_field,
    isolated_pixels,
    master_dark,
    micro_images,
    micro_images_from_centres,
    neighbour_stats,
    prepare_frames,
    prepare_image,
    prepare_pair,
    repair_pixels,
)
from plenopiv.synthetic.images import particle_image

#: Read noise of one frame, counts.
SIGMA = 3.0
#: Frames of the dark and of the white stacks.
N_DARK, N_WHITE = 8, 8
#: Peak of the ideal particle render and plateau of the ideal white, counts.
PEAK, WHITE = 3000.0, 2500.0


@dataclass
class Sensor:
    """The defects of a sensor and its optics, on the small_m1 camera's 700 × 1040 pixels."""

    black: np.ndarray          # black level with its fixed pattern, counts
    glow: np.ndarray           # amplifier glow, counts
    dark_current: np.ndarray   # of the hot pixels, counts
    hot: np.ndarray            # bool
    gain: np.ndarray           # lenslet transmission x vignetting (median 1 at the centres)

    def frame(self, light, rng, *, bits: int = 12) -> np.ndarray:
        """One recorded frame of ``light`` (counts at gain 1): uint16, clipped at 2^bits - 1."""
        counts = (self.black + self.glow + self.dark_current + self.gain * light
                  + rng.normal(0.0, SIGMA, light.shape if np.ndim(light) else self.black.shape))
        return np.clip(np.rint(counts), 0, 2 ** bits - 1).astype(np.uint16)

    @property
    def offset(self) -> np.ndarray:
        """What a dark frame holds on average."""
        return self.black + self.glow + self.dark_current


@pytest.fixture(scope="module")
def camera():
    return load_camera("small_m1")


@pytest.fixture(scope="module")
def cal(camera):
    return Calibration.from_camera(camera)


@pytest.fixture(scope="module")
def micro(cal):
    return micro_images(cal)


@pytest.fixture(scope="module")
def sensor(cal):
    rng = np.random.default_rng(7)
    shape = cal.camera.sensor.shape
    rows, cols = np.indices(shape)
    # each pixel's lenslet, found here independently of the stage (nearest focal spot)
    _, nearest = cKDTree(cal.focal_spot_px).query(np.c_[rows.ravel(), cols.ravel()])
    transmission = 1.0 + rng.uniform(-0.1, 0.1, cal.n_lenslets)
    r = np.hypot(rows - (shape[0] - 1) / 2, cols - (shape[1] - 1) / 2) / np.hypot(*shape) * 2
    gain = transmission[nearest.reshape(shape)] * (1.0 - 0.25 * r ** 2)
    centre = np.floor(cal.focal_spot_px + 0.5).astype(int)
    gain /= np.median(gain[centre[:, 0], centre[:, 1]])
    black = (100.0 + rng.normal(0, 2.0, shape[1])[None, :] + rng.normal(0, 1.0, shape[0])[:, None])
    glow = 40.0 * np.exp(-np.hypot(rows, cols) / 150.0)
    hot = rng.random(shape) < 5e-4
    dark_current = np.where(hot, rng.uniform(200.0, 2000.0, shape), 0.0)
    return Sensor(black, glow, dark_current, hot, gain)


@pytest.fixture(scope="module")
def coverage(cal):
    """The ideal white: each pixel's share of its aperture cell inside the aperture."""
    from plenopiv.lightfield import light_field

    lf = light_field(cal, min_lit=1e-6)
    w = np.zeros(cal.camera.sensor.shape)
    w.flat[lf.pixel] = lf.lit
    return w


@pytest.fixture(scope="module")
def positions():
    rng = np.random.default_rng(11)
    n = 16
    return np.c_[rng.uniform(-0.8e-3, 0.8e-3, (n, 2)), rng.uniform(-1.0e-3, 1.0e-3, n)]


@pytest.fixture(scope="module")
def light(camera, positions):
    """The ideal render of the particles, counts (peak 3000)."""
    img = particle_image(camera, positions, rays_per_particle=2048, seed=3)
    return img * (PEAK / img.max())


@pytest.fixture(scope="module")
def frames_of(sensor, coverage):
    """The dark stack and the mean white of the sensor."""
    rng = np.random.default_rng(5)
    darks = np.stack([sensor.frame(0.0, rng) for _ in range(N_DARK)])
    whites = np.stack([sensor.frame(coverage * WHITE, rng) for _ in range(N_WHITE)])
    return darks, whites.mean(axis=0)


@pytest.fixture(scope="module")
def frames(micro, frames_of):
    darks, white = frames_of
    return prepare_frames(micro, dark=master_dark(darks), white=white)


def assert_same_particles(a, b, cal):
    """The particles of volume result ``a`` are those of ``b``, at the same positions.

    Peaks dimmer than a quarter of the median (fragments a threshold splits off, which the
    noise may leave below the threshold) are left out. A position is the point nearest the
    rays of the ~100 or more pixels that saw the particle; the noise (3 counts on 50 to 3000)
    moves each ray's weight by 0.1-6 %, the point by about that over sqrt(100) of the bundle's
    spread, a hundredth of a cell or less, and the lit/dark call of a few pixels at the
    threshold moves a near-focus depth (the least determined) by a few hundredths: within
    0.02 footprint laterally and 0.1 depth cell.
    """
    lat, dep = resolution_cell(cal.effective_camera)

    def genuine(r):
        keep = r.particle_intensity >= 0.25 * np.median(r.particle_intensity)
        return r.particle_position[keep]

    pa, pb = genuine(a), genuine(b)
    assert len(pa) >= 10 and len(pb) == len(pa)
    _, j = cKDTree(pb).query(pa)
    assert len(set(j)) == len(pa)
    err = np.abs(pb[j] - pa) / [lat, lat, dep]
    assert (err[:, :2] < 0.02).all() and (err[:, 2] < 0.1).all(), err


def grid():
    return VolumeGrid.from_bounds((-1.0e-3, 1.0e-3), (-1.0e-3, 1.0e-3), (-1.5e-3, 1.5e-3),
                                  voxel=0.125e-3)


# ---- kernels and their twins ------------------------------------------------------------------


@pytest.mark.parametrize("radius", [1, 2])
def test_neighbour_kernel_equals_its_numpy_twin(rng, radius):
    shape = (23, 31)
    img = rng.normal(100.0, 20.0, shape)
    labels = rng.integers(-1, 3, shape).astype(np.int32)
    use, which = rng.random(shape) > 0.2, rng.random(shape) > 0.3
    numba = neighbour_stats(img, labels, use=use, which=which, radius=radius)
    twin = neighbour_stats(img, labels, use=use, which=which, radius=radius, engine="numpy")
    for a, b in zip(numba, twin, strict=True):
        np.testing.assert_array_equal(a, b)
    assert (numba[2][which] > 0).any() and (numba[2][~which] == 0).all()


def test_label_kernel_equals_its_numpy_twin(rng):
    # a jittered square lattice of pitch 7 px over a 40 x 50 sensor, some centres off it
    r, c = np.meshgrid(np.arange(-3, 45, 7.0), np.arange(-3, 55, 7.0), indexing="ij")
    centres = np.c_[r.ravel(), c.ravel()] + rng.normal(0, 0.8, (r.size, 2))
    a = micro_images_from_centres(centres, (40, 50), 7.0, 3.0)
    b = micro_images_from_centres(centres, (40, 50), 7.0, 3.0, engine="numpy")
    np.testing.assert_array_equal(a.label, b.label)
    np.testing.assert_array_equal(a.distance_px, b.distance_px)


def test_repairs_and_hot_pixels_are_the_same_with_either_engine(rng, micro):
    img = rng.normal(50.0, 3.0, micro.shape)
    bad = rng.random(micro.shape) < 1e-3
    img[bad] += 3000.0
    fixed = [repair_pixels(img, bad, micro.label, engine=e) for e in ("numba", "numpy")]
    np.testing.assert_array_equal(fixed[0][0], fixed[1][0])
    found = [isolated_pixels(img, micro.label, noise=3.0, engine=e) for e in ("numba", "numpy")]
    np.testing.assert_array_equal(*found)
    # all but the few that touch another (each has a bright neighbour) or lie outside a cell
    assert not (found[0] & ~bad).any() and found[0].sum() >= 0.97 * bad.sum()


def test_every_pixel_belongs_to_its_nearest_focal_spot(cal, micro):
    rows, cols = np.indices(micro.shape)
    dist, nearest = cKDTree(cal.focal_spot_px).query(np.c_[rows.ravel(), cols.ravel()], k=2)
    labelled = micro.label.ravel() >= 0
    clear = labelled & (dist[:, 1] - dist[:, 0] > 1e-6)       # not equidistant from two
    assert (micro.label.ravel()[clear] == nearest[clear, 0]).all()
    np.testing.assert_allclose(micro.distance_px.ravel()[labelled], dist[labelled, 0],
                               rtol=1e-6)
    # a cell is about a pitch wide: no labelled pixel is farther than 0.75 pitch
    assert micro.distance_px[micro.label >= 0].max() <= 0.75 * micro.pitch_px


# ---- dark, white ------------------------------------------------------------------------------


def test_master_dark_is_the_mean_and_its_noise_the_stacks_spread(rng):
    stack = rng.normal(100.0, SIGMA, (6, 20, 30)).round().astype(np.uint16)
    d = master_dark(stack)
    np.testing.assert_allclose(d.mean, stack.mean(axis=0))
    np.testing.assert_allclose(d.frame_variance, stack.astype(float).var(axis=0, ddof=1))
    np.testing.assert_allclose(d.variance, d.frame_variance / 6)
    assert d.n_frames == 6 and d.noise == pytest.approx(SIGMA, rel=0.15)
    one = master_dark(stack[0])
    assert one.frame_variance is None and one.variance is None and one.noise is None
    with pytest.raises(ImageError, match="expected one frame"):
        master_dark(np.zeros((2, 3, 4, 5)))


def test_dark_defects_are_the_hot_pixels_and_not_the_fixed_pattern(sensor, frames_of):
    darks, _ = frames_of
    hot, cold = dark_defects(master_dark(darks).mean)
    assert (hot == sensor.hot).all() and not cold.any()


def test_flat_field_divides_out_each_lenslets_throughput(sensor, coverage, micro, frames):
    flat = frames.flat
    # the white's noise (3 counts over 8 frames of 2500) and the vignetting's curvature
    # across a micro-image (1e-4) leave the fitted throughput within 0.2 %
    ok = ~flat.mask
    assert np.abs(flat.gain[ok] / sensor.gain[ok] - 1).max() < 2e-3
    assert flat.spread == pytest.approx(np.std(sensor.gain[ok]), rel=0.5)
    # masked: outside the micro-images and the rim below 0.2 of the plateau, not more
    inside = micro.label >= 0
    assert not (ok & (coverage < 0.15)).any()
    assert not (flat.mask & inside & (coverage > 0.25)).any()
    assert flat.reference == pytest.approx(WHITE, rel=0.01)


def test_a_white_that_is_no_white_is_refused(micro, light, rng):
    uniform = rng.normal(1000.0, SIGMA, micro.shape)
    with pytest.raises(ImageError, match=r"'w.tif' shows no micro-image structure"):
        flat_field(uniform, micro, name="'w.tif'")
    with pytest.raises(ImageError, match="no lit micro-images|is not a white"):
        flat_field(light, micro, name="'w.tif'")
    with pytest.raises(ImageError, match=r"'w.tif' is 10 × 10 pixels: expected the sensor's "
                                         r"700 × 1040"):
        flat_field(np.ones((10, 10)), micro, name="'w.tif'")


def test_dead_and_stuck_pixels_of_the_white(micro, coverage, frames_of):
    darks, white = frames_of
    dark = master_dark(darks)
    w = white.copy()
    plateau = np.argwhere((micro.label >= 0) & (micro.distance_px < micro.radius_px - 3))
    dead, stuck = plateau[100], plateau[5000]
    w[tuple(dead)] = dark.mean[tuple(dead)]           # reads no light
    w[tuple(stuck)] += 3 * WHITE
    f = prepare_frames(micro, dark=dark, white=w)
    assert f.flat.dead[tuple(dead)] and f.flat.mask[tuple(dead)]
    assert f.flat.stuck[tuple(stuck)] and not f.flat.mask[tuple(stuck)]
    assert f.bad[tuple(dead)] and f.bad[tuple(stuck)]
    assert f.counts["white_dead"] == 1 and f.counts["white_stuck"] == 1


# ---- invariance: the defects undone -----------------------------------------------------------


@pytest.fixture(scope="module")
def realistic(sensor, light):
    return sensor.frame(light, np.random.default_rng(9))


def test_preprocessing_gives_back_the_ideal_render(sensor, light, micro, frames, realistic):
    p = prepare_image(realistic, frames)
    assert (frames.bad == sensor.hot).all()                 # every hot pixel, nothing else
    assert p.figures["hot_pixels_in_image"] == 0
    compare = (micro.label >= 0) & ~p.mask & ~frames.bad
    # the image's noise and the master dark's, and the quantisation, through the gain
    sigma = np.sqrt(SIGMA ** 2 * (1 + 1 / N_DARK) + 1 / 12) / sensor.gain
    z = (p.image - light) / sigma
    lit = compare & (light > 10 * SIGMA)
    assert lit.sum() > 2000
    assert 0.85 < np.sqrt(np.mean(z[lit] ** 2)) < 1.15
    assert np.abs(z[compare]).max() < 6.0
    # the variance image holds that noise (each pixel's from 8 dark frames: 7 degrees of
    # freedom, so per pixel within a factor of two; in the median within 10 %)
    ratio = np.sqrt(p.variance[lit]) / sigma[lit]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)


def test_the_preprocessed_frame_reconstructs_the_ideal_particles(cal, light, frames, realistic):
    from plenopiv.reconstruction.build import weights_for
    from plenopiv.reconstruction.settings import ReconstructionSettings
    from plenopiv.workflow.volume import reconstruct_volume

    settings = ReconstructionSettings(lateral_subdivision=1)
    g = grid()
    weights, _ = weights_for(cal, g, settings)
    ideal = reconstruct_volume(cal, light, g, settings=settings, weights=weights)
    p = prepare_image(realistic, frames)
    real = reconstruct_volume(cal, p.image, g, settings=settings, weights=weights,
                              image_mask=p.mask, checked=True)
    assert_same_particles(ideal, real, cal)


# ---- hot pixels at a micro-image border -------------------------------------------------------


def test_a_hot_pixel_at_a_border_is_repaired_from_its_own_micro_image(micro):
    img = np.zeros(micro.shape)
    k = micro.label[350, 520]
    img[micro.label == k] = 1000.0                          # one bright micro-image
    # a pixel of k that touches another micro-image
    rows, cols = np.nonzero(micro.label == k)
    border = [(r, c) for r, c in zip(rows, cols, strict=True)
              if (micro.label[r - 1:r + 2, c - 1:c + 2] != k).any()]
    # the pixel with the most neighbours in other micro-images (a corner of the cell)
    r, c = max(border, key=lambda p: (micro.label[p[0] - 1:p[0] + 2, p[1] - 1:p[1] + 2]
                                      != k).sum())
    img[r, c] = 6000.0
    assert (micro.label[r - 1:r + 2, c - 1:c + 2] != k).sum() >= 4
    bad = np.zeros(micro.shape, bool)
    bad[r, c] = True
    fixed, left = repair_pixels(img, bad, micro.label)
    assert fixed[r, c] == 1000.0 and not left.any()
    # across the border the dark neighbours would have pulled it down
    across, _ = repair_pixels(img, bad)
    assert across[r, c] < 1000.0
    # found: a hot pixel at the rim of a lit micro-image (a disc), and one in the gap of the
    # dark micro-image beside it, next to the border
    img = np.where((micro.label == k) & (micro.distance_px <= micro.radius_px), 1000.0, 0.0)
    rim = np.argwhere((micro.label == k) & (micro.distance_px <= micro.radius_px)
                      & (micro.distance_px > micro.radius_px - 1))[0]
    q = next((rr, cc) for rr, cc in [(r + a, c + b) for a in (-1, 0, 1) for b in (-1, 0, 1)]
             if micro.label[rr, cc] != k)
    img[tuple(rim)] = img[q] = 6000.0
    found = isolated_pixels(img, micro.label)
    assert found[tuple(rim)] and found[q] and found.sum() == 2
    # a lit pixel whose light spills over the border into the next cell is no hot pixel
    spill = img.copy()
    spill[tuple(rim)] = 1000.0
    spill[q] = 300.0
    spill[r, c] = 1000.0
    assert not isolated_pixels(spill, micro.label)[q]


# ---- background ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def batch(camera, sensor):
    """Four frames of other particles with a static glow (a reflection), and the light."""
    rng = np.random.default_rng(21)
    shape = camera.sensor.shape
    cols = np.arange(shape[1])
    reflection = 300.0 * np.exp(-0.5 * ((cols - 400) / 60.0) ** 2)[None, :] * np.ones(shape)
    lights, raws = [], []
    for i in range(4):
        pos = np.c_[rng.uniform(-0.8e-3, 0.8e-3, (8, 2)), rng.uniform(-1e-3, 1e-3, 8)]
        img = particle_image(camera, pos, rays_per_particle=512, seed=i)
        img *= PEAK / img.max()
        lights.append(img)
        raws.append(sensor.frame(img + reflection / sensor.gain, rng))
    return lights, raws, reflection


@pytest.mark.parametrize("kind", ["minimum", "mean"])
def test_a_batch_background_removes_a_static_glow(kind, micro, sensor, frames_of, batch):
    darks, _ = frames_of
    lights, raws, reflection = batch
    bg, n = batch_background(raws, kind)
    assert n == 4
    dark = master_dark(darks)
    # without a dark, the hot pixels are those bright in every image: isolated in the
    # background; none else, and most of them (not the dimmest, 200 counts, where they
    # must double the 300-count reflection or stand 57 noise levels out)
    alone = prepare_frames(micro, background=bg)
    assert not (alone.bad & ~sensor.hot).any()
    assert alone.counts["background_hot"] >= 0.75 * sensor.hot.sum()
    with_bg = prepare_frames(micro, dark=dark, background=bg)
    without = prepare_frames(micro, dark=dark)
    glow = reflection > 200                                  # the reflection's band
    for light, raw in zip(lights, raws, strict=True):
        free = glow & (np.max(lights, axis=0) < 1.0)         # no particle there in any image
        kept = prepare_image(raw, without).image
        assert np.median(kept[free]) > 200                   # the glow, left in
        out = prepare_image(raw, with_bg).image
        # the minimum of 4 noisy frames sits ~1 sigma low: 2 sigma is what may remain
        assert np.median(out[free]) < 2 * SIGMA
        # the particles' light stays (less the batch's minimum or mean of it), through the
        # throughput (no white here)
        lit = glow & (light > 20 * SIGMA)
        expected = sensor.gain * (light - (np.min(lights, axis=0) if kind == "minimum"
                                           else np.mean(lights, axis=0)))
        assert np.median(np.abs(out[lit] - expected[lit])) < 3 * SIGMA


def test_a_batch_background_is_refused_for_a_single_pair(tmp_path, cal):
    from plenopiv.config.experiment import experiment_from_dict
    from plenopiv.workflow.preprocess import ImagePreparation

    exp = experiment_from_dict({"camera": "small_m1", "volume": {
        "x_mm": [-1, 1], "y_mm": [-1, 1], "z_mm": [-1, 1], "voxel_mm": 0.125},
        "preprocess": {"background": "minimum"}}, base_dir=tmp_path)
    with pytest.raises(ConfigError, match=r'\[preprocess\] background = "minimum" is the '
                                          r"per-pixel minimum.*background image.*plenopiv run"):
        ImagePreparation(exp, cal)
    assert PreprocessSettings(background="bg.tif").background_kind == "image"
    with pytest.raises(ValueError, match="hot_pixels"):
        PreprocessSettings(hot_pixels="some")


# ---- the two exposures of a pair --------------------------------------------------------------


def test_a_weaker_second_pulse_reconstructs_the_same_particles(cal, sensor, light, micro,
                                                                 frames):
    from plenopiv.products.images import saturation
    from plenopiv.reconstruction.build import weights_for
    from plenopiv.reconstruction.settings import ReconstructionSettings
    from plenopiv.workflow.volume import reconstruct_volume

    # bright enough that the brightest particles clip at 4095 in the full pulse
    bright = light * 1.6
    noise = np.random.default_rng(31)
    a = sensor.frame(bright, np.random.default_rng(30))
    state = noise.bit_generator.state
    b1 = sensor.frame(bright, noise)
    noise.bit_generator.state = state                        # the same noise, pulse 0.85
    b85 = sensor.frame(0.85 * bright, noise)
    sat = [saturation(x) for x in (a, b1, b85)]
    assert sat[0][0] > 0 and sat[1][0] > 0                   # the full pulses clip
    masks = [x >= s[1] if s[0] > 0 else None for x, s in zip((a, b1, b85), sat, strict=True)]
    _, p1, n1 = prepare_pair(a, b1, frames, saturated=(masks[0], masks[1]))
    _, p85, n85 = prepare_pair(a, b85, frames, saturated=(masks[0], masks[2]))
    assert n85["scale_b"] == pytest.approx(n1["scale_b"] / 0.85, rel=0.01)
    # the same pixels are dark: the threshold (0.3 % of the brightest) falls alike
    tau = 0.003
    ok = ~p1.mask
    dark1 = p1.image <= tau * p1.image[ok].max()
    dark85 = p85.image <= tau * p85.image[ok].max()
    # they may differ only where the noise (3 counts, over 0.85 in B) straddles the threshold
    near = np.abs(p1.image - tau * p1.image[ok].max()) < 6 * SIGMA / 0.85
    assert not ((dark1 != dark85) & ok & ~near).any()
    assert exposure_level(p85.image, p1.mask) == pytest.approx(exposure_level(p1.image,
                                                                              p1.mask),
                                                               rel=0.01)
    settings = ReconstructionSettings(lateral_subdivision=1)
    g = grid()
    weights, _ = weights_for(cal, g, settings)
    v1, v85 = (reconstruct_volume(cal, p.image, g, settings=settings, weights=weights,
                                  image_mask=p.mask, checked=True) for p in (p1, p85))
    assert_same_particles(v1, v85, cal)


# ---- images as they come ----------------------------------------------------------------------


def _experiment(tmp_path, preprocess=None):
    from plenopiv.config.experiment import experiment_from_dict

    cfg = {"camera": "small_m1", "volume": {"x_mm": [-1, 1], "y_mm": [-1, 1], "z_mm": [-1, 1],
                                            "voxel_mm": 0.125}}
    if preprocess is not None:
        cfg["preprocess"] = preprocess
    return experiment_from_dict(cfg, base_dir=tmp_path)


def test_a_realistic_frame_without_preprocessing_gets_one_warning(tmp_path, cal, light,
                                                                  realistic, frames_of):
    from plenopiv.workflow.preprocess import ImagePreparation

    plain = ImagePreparation(_experiment(tmp_path), cal)
    with pytest.warns(PlenopivWarning) as caught:
        out = plain.image(realistic, name="image 'a.tif'")
    assert len(caught) == 1
    msg = str(caught[0].message)
    assert re.match(r"image 'a.tif': black level (9\d|10\d) counts", msg)   # ~100
    assert "0.00% of the pixels saturated" in msg and " hot pixels" in msg
    assert '[preprocess] dark = "DARK.tif"' in msg
    assert out.figures["black_level_counts"] == pytest.approx(100, abs=5)
    assert out.figures["hot_pixels"] > 0
    plain.image(light, name="ideal")                             # no warning: all well
    darks, _ = frames_of
    tifffile.imwrite(tmp_path / "dark.tif", darks, photometric="minisblack")
    fixed = ImagePreparation(_experiment(tmp_path, {"dark": "dark.tif"}), cal)
    p = fixed.image(realistic, name="image 'a.tif'")             # no warning
    assert p.figures["black_level_counts"] < 1.0 and p.figures["hot_pixels"] > 0


def test_missing_or_misshapen_frames_name_the_key_and_the_file(tmp_path, cal):
    from plenopiv.workflow.preprocess import ImagePreparation

    with pytest.raises(ImageError, match=r"\[preprocess\] dark = 'none.tif': file .*none.tif' "
                                         r"not found: expected a dark frame or stack"):
        ImagePreparation(_experiment(tmp_path, {"dark": "none.tif"}), cal)
    tifffile.imwrite(tmp_path / "small.tif", np.ones((3, 10, 10), np.uint16),
                     photometric="minisblack")
    with pytest.raises(ImageError, match=r"\[preprocess\] white 'small.tif' is 10 × 10 pixels: "
                                         r"expected the sensor's 700 × 1040"):
        ImagePreparation(_experiment(tmp_path, {"white": "small.tif"}), cal)
    with pytest.raises(ConfigError, match=r"unknown key \[preprocess\] flat"):
        _experiment(tmp_path, {"flat": "x.tif"})


# ---- the contract at the command line ---------------------------------------------------------


def sha256(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_calibrate_with_a_dark_stack(tmp_path, capsys, camera, sensor, frames_of):
    from plenopiv.calibration.calibrate import calibrate
    from plenopiv.synthetic.images import focal_point_image

    fp = focal_point_image(camera, f_number=16)
    fp *= PEAK / fp.max()
    tifffile.imwrite(tmp_path / "fp.tif", sensor.frame(fp, np.random.default_rng(41)))
    # what a perfect dark would leave: the spots' light through the throughput, with the
    # same read noise (as recorded, this frame loses 11 % of its spots to the black level
    # and the hot pixels)
    noise = np.random.default_rng(41).normal(0.0, SIGMA, fp.shape)
    light_only = np.clip(np.rint(sensor.gain * fp + noise), 0, None)
    reference = calibrate(camera, light_only, focal_point_f_number=16).calibration
    darks, _ = frames_of
    tifffile.imwrite(tmp_path / "dark.tif", darks,          # a multi-page TIFF: a stack
                     photometric="minisblack")
    code = main(["calibrate", "small_m1", "--focal-point", str(tmp_path / "fp.tif"),
                 "--focal-point-f-number", "16", "--dark", str(tmp_path / "dark.tif"),
                 "--no-report", "--out", str(tmp_path / "cal.h5"), "--json", "--quiet"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0, out
    dark = out["dark"]
    assert dark["frames"] == N_DARK and dark["hot_pixels"] == int(sensor.hot.sum())
    assert dark["sha256"] == sha256(tmp_path / "dark.tif")
    assert dark["level_counts"] == pytest.approx(np.median(sensor.offset), abs=1)
    # the S_i of the light alone, within the master dark's own noise (3/sqrt(8) counts):
    # a fifth of the fit's uncertainty (which the vignetting's pull on the spots exceeds)
    assert out["image_distance_mm"] == pytest.approx(reference.image_distance * 1e3,
                                                     abs=out["focal_point"]["sigma_mm"])
    with h5py.File(tmp_path / "cal.h5") as fh:
        assert json.loads(fh.attrs["config"])["inputs"]["dark"] == str(tmp_path / "dark.tif")


@pytest.fixture(scope="module")
def contract(tmp_path_factory, cal, sensor, camera, frames_of, coverage, positions):
    """A folder with a calibration, a dark and a white stack, two pairs of realistic frames."""
    d = tmp_path_factory.mktemp("contract")
    cal.save(d / "cal.h5")
    darks, _ = frames_of
    rng = np.random.default_rng(51)
    tifffile.imwrite(d / "dark.tif", darks, photometric="minisblack")
    tifffile.imwrite(d / "white.tif", np.stack([sensor.frame(coverage * WHITE, rng)
                                                for _ in range(4)]), photometric="minisblack")
    (d / "pairs").mkdir()
    shift = np.array([0.1e-3, 0.0, 0.0])
    for i in (1, 2):
        pos = positions + rng.normal(0, 0.1e-3, positions.shape)
        for tag, p in (("A", pos), ("B", pos + shift)):
            img = particle_image(camera, p, rays_per_particle=1024, seed=i)
            tifffile.imwrite(d / "pairs" / f"p{i}_{tag}.tif",
                             sensor.frame(img * (PEAK / img.max()), rng))
    base = ('camera = "small_m1"\n[volume]\nx_mm = [-1.0, 1.0]\ny_mm = [-1.0, 1.0]\n'
            'z_mm = [-1.5, 1.5]\nvoxel_mm = 0.125\n[reconstruction]\nlateral_subdivision = 1\n'
            '[piv]\nwindows = [[12, 12, 12]]\npasses = 2\nuncertainty = "correlation"\n'
            '[images]\ndt_s = 1e-3\n[output]\npng = false\nvtk = false\nweights_cache = ""\n')
    (d / "raw.toml").write_text(base)
    (d / "pre.toml").write_text(base + '[preprocess]\ndark = "dark.tif"\nwhite = "white.tif"\n')
    return d


def _attr(path) -> dict:
    with h5py.File(path, "r") as fh:
        return json.loads(fh.attrs["preprocess"])


def _image_warnings(warnings, judged=()) -> list[str]:
    """The warnings about the images: not those of the settings' and the seeding's judgement
    (this cheap experiment has footprint voxels without subdivision and few particles)."""
    said = {f["text"] for f in judged}
    return [w for w in warnings if w not in said and "particles per lenslet" not in w]


def test_reconstruct_honours_preprocess_and_records_it(contract, capsys):
    d = contract
    code = main(["reconstruct", str(d / "cal.h5"), str(d / "pairs" / "p1_A.tif"), "--config",
                 str(d / "pre.toml"), "--out", str(d / "vol.h5"), "--json", "--quiet"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert not _image_warnings(out.get("warnings", ()), out["judgement"]["findings"])
    rec = _attr(d / "vol.h5")
    assert rec == out["preprocess"] and rec["applied"]
    assert rec["dark"]["sha256"] == sha256(d / "dark.tif") and rec["dark"]["frames"] == N_DARK
    assert rec["white"]["sha256"] == sha256(d / "white.tif")
    assert rec["white"]["reference_counts"] == pytest.approx(WHITE, rel=0.01)
    assert rec["background"] == {"kind": "none"} and rec["hot_pixels"] == "auto"
    assert rec["exposures"]["image"]["hot_pixels"] >= 0.9 * 5e-4 * 700 * 1040
    assert rec["exposures"]["image"]["black_level_counts"] < 1.0
    # the same frame without [preprocess]: one warning, and the product says nothing applied
    code = main(["reconstruct", str(d / "cal.h5"), str(d / "pairs" / "p1_A.tif"), "--config",
                 str(d / "raw.toml"), "--out", str(d / "vol_raw.h5"), "--json", "--quiet"])
    out, err = capsys.readouterr()
    out = json.loads(out)
    images = _image_warnings(out["warnings"], out["judgement"]["findings"])
    assert code == 0 and len(images) == 1
    assert "black level" in images[0] and "[preprocess] dark" in images[0]
    assert err.count("warning: ") == len(out["warnings"])
    assert _attr(d / "vol_raw.h5")["applied"] is False


def test_track_honours_preprocess_and_records_it(contract, capsys):
    d = contract
    code = main(["track", str(d / "cal.h5"), str(d / "pairs" / "p1_A.tif"),
                 str(d / "pairs" / "p1_B.tif"), "--config", str(d / "pre.toml"), "--out",
                 str(d / "tracks.h5"), "--json", "--quiet"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert not _image_warnings(out.get("warnings", ()), out["judgement"]["findings"])
    rec = _attr(d / "tracks.h5")
    assert rec["dark"]["sha256"] == sha256(d / "dark.tif")
    assert set(rec["exposures"]) == {"A", "B"} and "scale_b" in rec["normalisation"]
    assert _attr(d / "tracks_binned.h5") == rec


@pytest.mark.slow
def test_run_forms_the_batch_background_once_and_records_it(contract, capsys):
    d = contract
    (d / "dark_run.tif").write_bytes((d / "dark.tif").read_bytes())
    text = (d / "pre.toml").read_text().replace(
        "[images]\n", '[images]\na = "pairs/*_A.tif"\nb = "pairs/*_B.tif"\n'
        'calibration = "cal.h5"\n').replace('dark = "dark.tif"', 'dark = "dark_run.tif"')
    (d / "run.toml").write_text(text + 'background = "minimum"\n[batch]\nworkers = 1\n')
    code = main(["run", str(d / "run.toml"), "--json", "--quiet"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0 and sorted(out["done"]) == ["p1", "p2"], out
    bg = d / "out" / "background_minimum.tif"
    for name in ("p1_vectors.h5", "p1_volume_A.h5", "p2_volume_B.h5"):
        rec = _attr(d / "out" / name)
        assert rec["background"]["kind"] == "minimum" and rec["background"]["images"] == 4
        assert rec["background"]["sha256"] == sha256(bg)
        assert rec["dark"]["sha256"] == sha256(d / "dark_run.tif")
    # the background is the pixel-wise minimum of the four images
    from plenopiv.products.images import read_image

    images = [read_image(d / "pairs" / f"p{i}_{t}.tif") for i in (1, 2) for t in "AB"]
    np.testing.assert_array_equal(read_image(bg), np.min(images, axis=0).astype(np.float32))
    # the same batch again: every pair skipped; another dark: every pair recomputed
    assert main(["run", str(d / "run.toml"), "--json", "--quiet"]) == 0
    assert sorted(json.loads(capsys.readouterr().out)["skipped"]) == ["p1", "p2"]
    tifffile.imwrite(d / "dark_run.tif", tifffile.imread(d / "dark.tif")[:5],
                     photometric="minisblack")
    assert main(["run", str(d / "run.toml"), "--json", "--quiet"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["n_recomputed"] == 2
    assert {r["reason"] for r in s["recomputed"]} == {"made with other preprocessing frames"}


def test_a_batch_pair_returns_the_warnings_its_images_got(contract, tmp_path):
    """In a batch the warnings arise in the workers: each pair returns its images' own."""
    from plenopiv.batch.jobs import PairJob
    from plenopiv.workflow.worker import ExperimentPairProcess, drop_worker_processor

    d = contract
    job = PairJob("p1", str(d / "pairs" / "p1_A.tif"), str(d / "pairs" / "p1_B.tif"),
                  tmp_path / "p1_vectors.h5")
    try:
        out = ExperimentPairProcess(str(d / "raw.toml"), str(d / "cal.h5"), str(tmp_path))(job)
    finally:
        drop_worker_processor()
    images = _image_warnings(out["warnings"])
    assert len(images) == 2
    assert all("black level" in w and "[preprocess] dark" in w for w in images)
    assert images[0].startswith(f"image {str(d / 'pairs' / 'p1_A.tif')!r}: ")
    assert _attr(tmp_path / "p1_vectors.h5")["applied"] is False
