"""Real lenslet arrays as they are: a white frame like a light-field microscope's.

A square array of 27.5 px pitch, about 7,700 lenslets on a 2400 × 2440 sensor, micro-images
that fill their cells (discs one pitch across, soft edges), lenslet centres scattered by
0.55 px rms (2 % of the pitch), rotated by 1 mrad, cut by the sensor's edges, with photon and
read noise and ±5 % throughput. The calibration must find at least 95 % of the complete
lenslets, the pitches within 0.03 px and the rotation within 0.6 mrad (the bars of a real
frame), keep each lenslet's measured centre where it beats the lattice, and refuse what is no
lenslet lattice (a particle image, a ruler, a smooth scene), naming what it found.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.special import erfc

from plenopiv.calibration.calibrate import calibrate
from plenopiv.calibration.lattice_fit import fit_lattice
from plenopiv.calibration.lattice_quality import check_lattice
from plenopiv.calibration.lenslets import spot_lattice
from plenopiv.calibration.spot_detection import detect_spots
from plenopiv.camera.model import camera_from_dict, load_camera
from plenopiv.camera.optics import focal_spot_exact
from plenopiv.conventions import sensor_to_pixel
from plenopiv.errors import CalibrationError
from plenopiv.synthetic.images import Ruler, finish_image, particle_image, ruler_image
from plenopiv.synthetic.seeding import SeedingBox, random_particles

PITCH_PX = 27.5             # the micro-images' pitch on the sensor
ROTATION = 1e-3
SCATTER_PX = 0.55           # rms of the 2-D displacement of each lenslet from its node
PIXEL_UM = 6.5
IMAGE_DISTANCE = 0.2
FBAR = 2.5e-3               # lenslet focal length (sensor distance), m


def microscope_camera(rows=2400, cols=2440, n_lenslets=(86, 87), rotation=0.0):
    """A light-field-microscope-like camera: a square array whose micro-images lie 27.5 px
    apart at S_i = 0.2 m (lenslets of f = 2.5 mm), nearly as wide as the sensor."""
    k = 1.0 + FBAR / IMAGE_DISTANCE
    return camera_from_dict({
        "name": "light-field microscope (synthetic)",
        "sensor": {"rows": rows, "cols": cols, "pixel_pitch_um": PIXEL_UM},
        "microlens_array": {"rows": n_lenslets[0], "cols": n_lenslets[1],
                            "pitch_um": PITCH_PX * PIXEL_UM / k, "focal_length_um": FBAR * 1e6,
                            "sensor_distance_um": FBAR * 1e6, "grid": "square",
                            "rotation_rad": rotation},
        "main_lens": {"focal_length_mm": 100.0, "f_number": 4.0,
                      "image_distance_mm": IMAGE_DISTANCE * 1e3},
    })


def lattice_centres(shape, rng, *, origin=(-9.3, -4.6), rotation=ROTATION,
                    scatter_px=SCATTER_PX):
    """Micro-image centres ``(row, col)`` px of a square array larger than the sensor (its
    first node at ``origin``, off the sensor): the sensor cuts it on every side."""
    c, s = math.cos(rotation), math.sin(rotation)
    e_col, e_row = PITCH_PX * np.array([s, c]), PITCH_PX * np.array([c, -s])
    n = int(max(shape) / PITCH_PX) + 3
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    nodes = np.asarray(origin) + i.reshape(-1, 1) * e_row + j.reshape(-1, 1) * e_col
    nodes = nodes[np.all((nodes > -PITCH_PX) & (nodes < np.array(shape) + PITCH_PX), axis=1)]
    return nodes + rng.normal(0.0, scatter_px / math.sqrt(2), nodes.shape)


def white_frame(shape, centres, rng, *, edge_px=1.2, throughput=0.05):
    """The white frame (uint16, 12-bit counts on a black level of 100) of micro-images at
    ``centres``: discs one pitch across with an erfc edge of ``edge_px``, so that they touch
    their neighbours, no dark gap between them; photon and read noise."""
    level = 1.0 + rng.uniform(-throughput, throughput, len(centres))
    pad = 40
    img = np.zeros((shape[0] + 2 * pad, shape[1] + 2 * pad))
    h = int(PITCH_PX / 2 + 5 * edge_px) + 1
    dr, dc = np.mgrid[-h:h + 1, -h:h + 1]
    base = np.rint(centres).astype(int) + pad
    frac = centres + pad - base
    inside = np.all((base - h >= 0) & (base + h < np.array(img.shape)), axis=1)
    base, frac, level = base[inside], frac[inside], level[inside]
    for a, b in zip(dr.ravel(), dc.ravel(), strict=True):
        r = np.hypot(a - frac[:, 0], b - frac[:, 1])
        img[base[:, 0] + a, base[:, 1] + b] += level * 0.5 * erfc(
            (r - PITCH_PX / 2) / (math.sqrt(2) * edge_px))
    img = img[pad:-pad, pad:-pad]
    counts = finish_image(img, noise="poisson", bit_depth=None, full_well=20000.0,
                          peak_fraction=0.7, rng=rng)
    counts = counts * 4095 + 100.0 + rng.normal(0.0, 3.0, shape)
    return np.clip(np.rint(counts), 0, 4095).astype(np.uint16)


@pytest.fixture(scope="module")
def frame():
    rng = np.random.default_rng(27)
    shape = (2400, 2440)
    truth = lattice_centres(shape, rng)
    image = white_frame(shape, truth, rng)
    spots = detect_spots(image, grid="square")
    lattice = fit_lattice(spots, grid="square", image_shape=image.shape)
    return image, truth, spots, lattice


def _complete(truth, shape, radius=PITCH_PX / 2):
    return np.all((truth - radius >= -0.5) & (truth + radius <= np.array(shape) - 0.5), axis=1)


def test_the_real_frame_bars(frame):
    """>= 95 % of the complete lenslets found, <= 5 % missing, the pitches within 0.03 px
    and the rotation within 0.6 mrad; to within 5 standard errors, which are far smaller."""
    image, truth, spots, lattice = frame
    complete = _complete(truth, image.shape)
    assert complete.sum() >= 7000
    q = check_lattice(lattice)                         # the defaults accept it
    found = lattice.inlier & ((lattice.flags & 1) == 0)
    dist, k = cKDTree(truth[complete]).query(lattice.centres_px[found])
    assert len(np.unique(k[dist < 0.25 * PITCH_PX])) >= 0.95 * complete.sum()
    assert q["missing_fraction"] <= 0.05
    assert np.all(np.abs(lattice.pitch_px - PITCH_PX) < 0.03)
    assert abs(lattice.rotation_rad - ROTATION) < 0.6e-3
    assert np.all(np.abs(lattice.pitch_px - PITCH_PX) < 5 * lattice.pitch_std_px + 1e-3)
    assert abs(lattice.rotation_rad - ROTATION) < 5 * lattice.rotation_std_rad + 1e-5
    assert spots.method == "shape"
    # the partial lenslets at the edges are flagged, not counted missing
    assert q["n_edge"] > 0 and q["n_missing"] < 0.01 * complete.sum()


def test_each_lenslet_keeps_its_measured_centre(frame):
    """The lattice's nodes miss the scattered lenslets by 0.39 px per axis; their measured
    centres, kept with their standard errors, by a tenth of that, and the best centres (the
    inverse-variance mean of node and measurement) as well."""
    _, truth, _, lattice = frame
    use = lattice.inlier
    _, k = cKDTree(truth).query(lattice.centres_px[use])
    true = truth[k]
    node = lattice.predict(lattice.grid_index[use])
    rms = {name: float(np.sqrt(np.mean((x - true) ** 2)))
           for name, x in (("node", node), ("measured", lattice.corrected_centres_px[use]),
                           ("best", lattice.best_centres_px[use]))}
    assert rms["node"] == pytest.approx(SCATTER_PX / math.sqrt(2), rel=0.1)
    assert rms["measured"] < 0.1 * rms["node"]
    assert rms["best"] <= rms["measured"] * 1.01
    scatter = float(np.hypot(*lattice.scatter_px))
    assert scatter == pytest.approx(SCATTER_PX, rel=0.1)
    std = lattice.centre_std_px[use]
    assert np.all(np.isfinite(std)) and np.median(std) < 0.05
    assert lattice.quality["on_lattice_fraction"] > 0.99


def test_calibrate_takes_a_scattered_white_frame_with_its_defaults():
    """A white frame as the calibration's image, of a camera whose file knows neither S_i nor
    the rotation: every lenslet paired with its micro-image, S_i from their pitch."""
    rng = np.random.default_rng(28)
    camera = microscope_camera(rotation=ROTATION)
    mla, shape = camera.microlens_array, camera.sensor.shape
    spots = focal_spot_exact(mla.centres(), IMAGE_DISTANCE, mla.sensor_distance)
    centres = sensor_to_pixel(spots, shape, camera.sensor.pixel_pitch)
    centres = centres + rng.normal(0.0, SCATTER_PX / math.sqrt(2), centres.shape)
    image = white_frame(shape, centres, rng)
    rep = calibrate(microscope_camera().with_image_distance(0.19), image)
    q = rep.summary()["lattice"]["focal_point"]
    assert q["spot_method"] == "shape" and q["missing_fraction"] <= 0.05
    assert rep.calibration.n_lenslets == mla.count >= 7000
    assert rep.n_missing <= 0.05 * mla.count
    assert abs(rep.focal_fit.rotation - ROTATION) < 0.6e-3
    # S_i from the pitch: 0.55 px of scatter over 86 lenslets, sigma ~ 0.03 mm
    assert abs(rep.focal_fit.image_distance - IMAGE_DISTANCE) <= \
        4 * rep.focal_fit.sigma_image_distance
    assert rep.focal_fit.sigma_image_distance < 0.1e-3


@pytest.fixture(scope="module")
def scenes():
    """A particle image, a ruler image and a smooth scene on a 21 x 31-lenslet camera."""
    cam = load_camera("small_test").patch(21, 31, margin_px=12)
    rng = np.random.default_rng(3)
    box = SeedingBox.field_of_view(cam, (-5e-3, 5e-3))
    particles = particle_image(cam, random_particles(box, 400, rng), rays_per_particle=256)
    ruler = ruler_image(load_camera("small_test"), Ruler(1e-3), rays_per_lenslet=300)
    rr, cc = np.indices(cam.sensor.shape)
    smooth = sum(rng.uniform(0.5, 1.0) * np.exp(
        -((rr - rng.uniform(0, rr.max())) ** 2 + (cc - rng.uniform(0, cc.max())) ** 2)
        / (2 * rng.uniform(30, 120) ** 2)) for _ in range(6))
    smooth = finish_image(smooth, noise="poisson", rng=rng)
    return cam, {"particles": particles, "ruler": ruler, "smooth": smooth}


def test_what_is_no_lenslet_lattice_is_refused_saying_what_was_found(scenes):
    cam, images = scenes
    with pytest.raises(CalibrationError, match=r"\d+ spots, where this camera's \d+ lenslets "
                                               r"make one each.*a particle image or a scene "
                                               r"given as the focal-point image"):
        calibrate(cam, images["particles"])
    with pytest.raises(CalibrationError, match=r"(hold no spot, \d+\.\d % .*max_missing_fraction"
                                               r"|unevenly lit.*max_lenslet_contrast)"):
        spot_lattice(images["ruler"], load_camera("small_test"), "the ruler image",
                     max_missing_fraction=0.05)
    with pytest.raises(CalibrationError, match=r"the focal-point image: \d spots, where this "
                                               r"camera's 651 lenslets make one each"):
        calibrate(cam, images["smooth"])


def test_a_ruler_is_refused_even_with_every_lenslet_allowed_missing(scenes):
    """Its micro-images form a lattice, but the ticks light them unevenly."""
    _, images = scenes
    with pytest.raises(CalibrationError, match=r"unevenly lit: one in ten differs from its "
                                               r"neighbours by more than \d+ %"):
        spot_lattice(images["ruler"], load_camera("small_test"), "the ruler image",
                     max_missing_fraction=1.0)
