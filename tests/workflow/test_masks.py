"""Masks: an image mask in the reconstruction (a reflection), volume masks from [mask] (boxes,
cylinders, arrays) applied in the PIV of the pair pipeline."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.config.experiment import experiment_from_dict
from plenopiv.errors import ConfigError, ReconstructionError
from plenopiv.reconstruction.build import weights_for
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.synthetic.images import particle_image
from plenopiv.synthetic.seeding import SeedingBox, random_particles
from plenopiv.workflow.masks import cylinder_mask, image_mask, read_mask, volume_mask
from plenopiv.workflow.volume import reconstruct_volume
from plenopiv.workflow.vortex_case import VortexCase, aligned_grid


def _matched(found, true, lateral=0.15e-3, depth=0.6e-3):
    """Which true particles have a found one within ``lateral`` and ``depth`` (metres)."""
    d = found[None, :, :] - true[:, None, :]
    near = (np.hypot(d[..., 0], d[..., 1]) < lateral) & (np.abs(d[..., 2]) < depth)
    return near.any(axis=1)


@pytest.fixture(scope="module")
def reflection_scene():
    """30 particles on the CI camera and a disk of pixels over about half of one particle's
    light (out of focus, Z = 0.67 mm)."""
    cam = load_camera("small_m1")
    cal = Calibration.from_camera(cam)
    grid = aligned_grid(cam, VortexCase(depth=1.5e-3, lateral_fill=0.6))
    rng = np.random.default_rng(3)
    box = SeedingBox(tuple(grid.bounds[0] * 0.9), tuple(grid.bounds[1] * 0.9), (-1.4e-3, 1.4e-3))
    pos = random_particles(box, 30, rng)
    image = particle_image(cam, pos, rays_per_particle=1024, seed=1)
    target = 4
    alone = particle_image(cam, pos[target][None], rays_per_particle=1024, seed=1)
    lit = alone > 0.02 * alone.max()
    rows, cols = np.nonzero(lit)
    rc = np.average(rows, weights=alone[lit])
    cc = np.average(cols, weights=alone[lit])
    rr, cg = np.ogrid[: image.shape[0], : image.shape[1]]
    d2 = (rr - rc) ** 2 + (cg - cc) ** 2
    disk = d2 <= np.percentile(np.sqrt(d2[lit]), 45) ** 2
    weights, _ = weights_for(cal, grid, ReconstructionSettings())

    def particles(img, mask=None):
        return reconstruct_volume(cal, img, grid, weights=weights,
                                  image_mask=mask).particle_position

    return {"pos": pos, "image": image, "disk": disk, "target": target,
            "share": alone[disk].sum() / alone.sum(), "particles": particles}


@pytest.mark.xfail(strict=True, reason=(
    "with half of the target's light masked, SMART with dark-pixel ceilings finds the target "
    "(Z = +0.67 mm) at Z = -0.05 mm, 0.72 mm (1.3 depth cells) towards focus: no particle is "
    "made by the reflection, but the target falls outside the 0.6 mm match; the same "
    "pull towards focus as the depth study's ±6 mm case (tests/studies/test_depth.py)"))
def test_masked_reflection_creates_no_particles(reflection_scene):
    s = reflection_scene
    pos, disk, target = s["pos"], s["disk"], s["pos"][s["target"]]
    assert 0.4 < s["share"] < 0.6
    reflection = np.where(disk, 4 * s["image"].max(), s["image"])
    clean = s["particles"](s["image"])
    bright = s["particles"](reflection)
    masked = s["particles"](reflection, disk)

    def fakes(found):   # found particles under the reflection that match no true particle
        lateral = np.hypot(*(found[:, :2] - target[:2]).T) < 0.3e-3
        return int((lateral & ~_matched(pos, found)).sum())

    n_clean = _matched(clean, pos).sum()
    # unmasked, the reflection is the brightest thing in the volume: it makes a particle where
    # there is none and the threshold (relative to the brightest voxels) loses the others
    assert fakes(bright) >= 1 and _matched(bright, pos).sum() < 0.5 * n_clean
    # masked, the reflection is gone: no particle under it, the others found as without it
    assert fakes(masked) == 0
    assert _matched(masked, pos).sum() >= n_clean
    assert _matched(masked, target[None])[0]


@pytest.mark.xfail(strict=True, reason=(
    "the half-masked target (Z = +0.67 mm) is found 0.72 mm towards focus under the sub-cell "
    "mask and SMART ceilings, outside the 0.6 mm match (see the reflection test)"))
def test_masked_pixels_are_dropped_not_dark(reflection_scene):
    """Half of the target's light under the mask: with the rows dropped the rest of its light
    reconstructs it; taken as dark pixels, they empty its voxels (line-of-sight rule)."""
    s = reflection_scene
    target = s["pos"][s["target"]][None]
    dark = s["particles"](np.where(s["disk"], 0.0, s["image"]))
    assert not _matched(dark, target)[0]
    masked = s["particles"](s["image"], s["disk"])
    assert _matched(masked, target)[0]


def test_what_lies_under_the_mask_does_not_matter(reflection_scene):
    """Masked pixels are dropped from the system: any content under the mask gives the same
    particles."""
    s = reflection_scene
    masked = s["particles"](s["image"], s["disk"])
    other = np.where(s["disk"], np.random.default_rng(1).random(s["image"].shape), s["image"])
    np.testing.assert_array_equal(s["particles"](other, s["disk"]), masked)


def test_image_mask_errors(reflection_scene, tmp_path):
    s = reflection_scene
    with pytest.raises(ReconstructionError, match="image mask has shape"):
        s["particles"](s["image"], s["disk"][1:])
    with pytest.raises(ReconstructionError, match="masks every pixel"):
        s["particles"](s["image"], np.ones_like(s["disk"]))


# --------------------------------------------------------------------------------------------
# [mask] in the experiment config
# --------------------------------------------------------------------------------------------

VOLUME = {"x_mm": [-2, 2], "y_mm": [-1, 1], "z_mm": [-1.5, 1.5], "voxel_mm": 0.25}


def _experiment(tmp_path, mask):
    return experiment_from_dict({"camera": "small_m1", "volume": VOLUME, "mask": mask},
                                base_dir=tmp_path)


def test_box_and_cylinder_masks_from_config(tmp_path):
    exp = _experiment(tmp_path, {
        "box": [{"x_mm": [1, 2], "y_mm": [-1, 1], "z_mm": [-1.5, 1.5]}],
        "cylinder": [{"axis": "y", "centre_mm": [-1.0, 0.0], "radius_mm": 0.5}]})
    grid = exp.volume
    m = volume_mask(exp.mask, grid, exp.base_dir)
    zz, yy, xx = np.meshgrid(grid.z, grid.y, grid.x, indexing="ij")
    in_box = xx >= 1e-3
    in_cyl = (xx + 1e-3) ** 2 + zz**2 <= (0.5e-3) ** 2
    np.testing.assert_array_equal(m, in_box | in_cyl)
    pipe = _experiment(tmp_path, {"cylinder": [{"axis": "x", "centre_mm": [0, 0],
                                                "radius_mm": 0.8, "masked": "outside"}]})
    m = volume_mask(pipe.mask, grid, pipe.base_dir)
    np.testing.assert_array_equal(m, yy**2 + zz**2 > (0.8e-3) ** 2)
    assert volume_mask(_experiment(tmp_path, {}).mask, grid) is None


def test_mask_arrays_from_npy_and_h5(tmp_path):
    grid = VolumeGrid.from_bounds((-2e-3, 2e-3), (-1e-3, 1e-3), (-1.5e-3, 1.5e-3),
                                  voxel=0.25e-3)
    arr = np.zeros(grid.shape, bool)
    arr[:, :2] = True
    np.save(tmp_path / "flow.npy", arr)
    with h5py.File(tmp_path / "flow.h5", "w") as fh:
        fh["masks/flow"] = arr.astype(np.uint8)
    for spec in ("flow.npy", "flow.h5:/masks/flow"):
        exp = _experiment(tmp_path, {"volume": spec})
        np.testing.assert_array_equal(volume_mask(exp.mask, exp.volume, tmp_path), arr)
    np.save(tmp_path / "wrong.npy", arr[1:])
    with pytest.raises(ConfigError, match=r"shape .* expected the \[volume\] grid"):
        volume_mask(_experiment(tmp_path, {"volume": "wrong.npy"}).mask, grid, tmp_path)
    with pytest.raises(ConfigError, match="not found"):
        read_mask(tmp_path / "missing.npy")
    with pytest.raises(ConfigError, match="no dataset"):
        read_mask(tmp_path / "flow.h5:/nothing")
    cam = load_camera("small_m1")
    np.save(tmp_path / "img.npy", np.zeros(cam.sensor.shape, bool))
    exp = _experiment(tmp_path, {"image": "img.npy"})
    assert image_mask(exp.mask, cam.sensor.shape, tmp_path).shape == cam.sensor.shape
    with pytest.raises(ConfigError, match="expected the sensor's"):
        image_mask(exp.mask, (10, 10), tmp_path)


def test_mask_config_errors_name_the_key(tmp_path):
    with pytest.raises(ConfigError, match="radius_mm"):
        _experiment(tmp_path, {"cylinder": [{"axis": "y", "centre_mm": [0, 0],
                                             "radius_mm": -1}]})
    with pytest.raises(ConfigError, match="colour"):
        _experiment(tmp_path, {"colour": "red"})
    with pytest.raises(ConfigError, match="axis"):
        cylinder_mask(VolumeGrid((0, 0, 0), (1, 1, 1), (2, 2, 2)), "w", (0, 0), 1.0)
