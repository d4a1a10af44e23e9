"""Bad input and faults at the command line (issue #14): one error path for every failure.

A table of bad ``plenopiv`` invocations, each run in-process through ``main(argv)``: every one
must end with a non-zero exit status (2 for bad input), one ``error:`` line on stderr naming
the thing and the value, no traceback, a JSON object with ``"error"`` when ``--json`` is
given, and the folder of inputs exactly as it was (no input overwritten, nothing written).
A few run as real processes (``python -m plenopiv.cli``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import tifffile

from plenopiv.calibration.model import Calibration
from plenopiv.camera.corrections import DepthCorrection
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.model import load_camera
from plenopiv.cli import main
from plenopiv.products.volume import VolumeResult

REPO = Path(__file__).resolve().parents[2]
SHAPE = (700, 1040)          # the small cameras' sensor

EXPERIMENT = """camera = "small_m1"
[volume]
x_mm = [-1.0625, 1.0625]
y_mm = [-1.0625, 1.0625]
z_mm = [-1.5, 1.5]
{volume}
{extra}
"""


def experiment(volume="voxel_mm = 0.125", extra="[output]\npng = false\nvtk = false\n"
               "weights_cache = \"\""):
    return EXPERIMENT.format(volume=volume, extra=extra)


def particle_like(rng) -> np.ndarray:
    """A sparse image of bright spots on a dark background (no ray tracing: these cases are
    refused before any reconstruction)."""
    img = np.zeros(SHAPE, np.float64)
    r = rng.integers(5, SHAPE[0] - 5, 400)
    c = rng.integers(5, SHAPE[1] - 5, 400)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            img[r + dr, c + dc] += 1.0 if dr == dc == 0 else 0.4
    return img


def tiny_volume(path: Path, shape=(8, 10, 12), seed=0):
    """A noise volume whose particle table holds one particle in every fourth voxel (a PIV
    window needs [piv] min_particles_per_window of them)."""
    grid = VolumeGrid((0.0, 0.0, 0.0), (1e-4, 1e-4, 1e-4), shape)
    rng = np.random.default_rng(seed)
    vol = rng.random(shape).astype(np.float32)
    n = int(np.prod(shape)) // 4
    xyz = rng.uniform(-0.5, np.array(shape[::-1]) - 0.5, size=(n, 3)) * 1e-4
    VolumeResult(vol, grid, DepthCorrection(1.0, 1.0), xyz, xyz, np.ones(n),
                 np.full((n, 3), 1e-4)).save(path)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A folder of inputs, good and bad, shared by every case of the table."""
    d = tmp_path_factory.mktemp("inputs")
    rng = np.random.default_rng(14)
    Calibration.from_camera(load_camera("small_m1")).save(d / "cal.h5")
    Calibration.from_camera(load_camera("small_test")).save(d / "cal_135.h5")
    good = particle_like(rng)
    tifffile.imwrite(d / "a.tif", (good / good.max() * 3000).astype(np.uint16))
    tifffile.imwrite(d / "noise.tif", rng.integers(0, 65535, SHAPE).astype(np.uint16))
    sat12 = (good / good.max() * 3000).astype(np.uint16)
    sat12[rng.random(SHAPE) < 0.12] = 4095                       # 12-bit data, clipped
    tifffile.imwrite(d / "sat12.tif", sat12)
    clip = (good / good.max() * 0.7).astype(np.float32)
    clip[rng.random(SHAPE) < 0.12] = 1.0                         # floats clipped at 1.0
    tifffile.imwrite(d / "clipped.tif", clip)
    tifffile.imwrite(d / "negative.tif", (good / good.max() - 0.05).astype(np.float32))
    tifffile.imwrite(d / "small.tif", np.ones((10, 10), np.uint16))
    tifffile.imwrite(d / "uniform.tif", rng.normal(1000, 3, SHAPE).astype(np.uint16))
    with h5py.File(d / "complex.h5", "w") as fh:
        fh["image"] = good + 1j * good
    with h5py.File(d / "img.h5", "w") as fh:
        fh["image"] = good
    tiny_volume(d / "va.h5", seed=1)
    tiny_volume(d / "vb.h5", seed=2)
    tiny_volume(d / "vc.h5", shape=(8, 10, 14), seed=3)
    (d / "exp.toml").write_text(experiment())
    (d / "bad_utf8.toml").write_bytes(b"\xff\xfe[volume]\nx_mm = [0, 1]\n")
    (d / "huge_cam.toml").write_text(
        (REPO / "src/plenopiv/presets/small_test.toml").read_text()
        .replace("rows = 700", "rows = 1000000").replace("cols = 1040", "cols = 1000000"))
    variants = {
        "big_voxel": experiment("voxel_mm = 50"),
        "inf_z": experiment("voxel_mm = 0.125").replace("z_mm = [-1.5, 1.5]", "z_mm = [-inf, 3]"),
        "two_voxel": experiment("voxel_mm = [0.1, 0.1]"),
        "tiny_voxel": experiment("voxel_mm = 0.0006"),
        "huge_shape": experiment("shape = [10000, 10000, 10000]"),
        "iterations": experiment(extra="[reconstruction]\niterations = 1000000000"),
        "nan_relax": experiment(extra="[reconstruction]\nrelaxation = nan"),
        "small_windows": experiment(extra="[piv]\nwindows = [[2, 2, 2]]"),
        "no_cal": experiment(extra="[images]\na = \"*_A.tif\"\nb = \"*_B.tif\""),
        "no_match": experiment(extra="[images]\na = \"nothing_*_A.tif\"\nb = \"*_B.tif\"\n"
                               "calibration = \"cal.h5\""),
        "bad_cluster": experiment(extra="[batch]\ncluster = \"pbs\"\n[images]\npairs = "
                                  "\"img.h5\"\ncalibration = \"cal.h5\""),
        "out_is_file": experiment(extra="[images]\npairs = \"img.h5\"\ncalibration = "
                                  "\"cal.h5\"\n[output]\ndirectory = \"a.tif\""),
        "count": experiment(extra="[images]\na = \"cnt/*_A.tif\"\nb = \"cnt/*_B.tif\"\n"
                            "calibration = \"cal.h5\"\npair_by = \"order\""),
        "wrong_cal": experiment(extra="[images]\npairs = \"img.h5\"\ncalibration = "
                                "\"cal_135.h5\""),
        "dt_inf": experiment(extra="[images]\ndt_s = inf"),
        "clash": experiment(extra="[images]\npairs = \"clash/*.h5\"\ncalibration = "
                            "\"cal.h5\"\n[output]\ndirectory = \"clash\""),
        "unknown_key": experiment(extra="[piv]\nwindow = [[16, 16, 16]]"),
        "pre_missing": experiment(extra='[preprocess]\ndark = "none.tif"'),
        "pre_small": experiment(extra='[preprocess]\ndark = "small.tif"'),
        "pre_uniform": experiment(extra='[preprocess]\nwhite = "uniform.tif"'),
        "pre_minimum": experiment(extra='[preprocess]\nbackground = "minimum"'),
        "pre_unknown": experiment(extra='[preprocess]\nflat = "uniform.tif"'),
        "pre_hot": experiment(extra='[preprocess]\nhot_pixels = "some"'),
        "run_pre_missing": experiment(extra='[images]\npairs = "img.h5"\ncalibration = '
                                      '"cal.h5"\n[preprocess]\nwhite = "none.tif"'),
    }
    for name, text in variants.items():
        (d / f"{name}.toml").write_text(text)
    (d / "cnt").mkdir()
    for n in ("1_A", "2_A", "1_B"):
        tifffile.imwrite(d / "cnt" / f"{n}.tif", np.ones((4, 4), np.uint16))
    (d / "clash").mkdir()
    for n in ("p", "p_volume_A"):
        (d / "clash" / f"{n}.h5").write_bytes((d / "img.h5").read_bytes())
    (d / "folder.h5").mkdir()
    (d / "folder.tif").mkdir()
    (d / "existing_dir").mkdir()
    return d


def tree(folder: Path) -> dict[str, str]:
    """Every file and folder under ``folder`` with the hash of its bytes."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder))
        out[rel] = "dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
    return out


# (case id, argv with {d} for the inputs folder, exit status, words the error line must hold)
CASES = [
    # ---- simulate ----
    ("toml-not-utf8", "simulate alignment {d}/bad_utf8.toml --out {d}/x.tif", 2, "not UTF-8"),
    ("sensor-1e6-square", "simulate alignment {d}/huge_cam.toml --out {d}/x.tif", 2,
     "needs about"),
    ("unknown-preset", "simulate alignment no_such_camera --out {d}/x.tif", 2, "presets"),
    ("pair-dt-0", "simulate pair small_m1 --dt 0 --out {d}/p.h5", 2, "--dt 0"),
    ("pair-dt-negative", "simulate pair small_m1 --dt -1e-3 --out {d}/p.h5", 2, "--dt -0.001"),
    ("pair-dt-nan", "simulate pair small_m1 --dt nan --out {d}/p.h5", 2, "--dt nan"),
    ("seed-negative", "simulate alignment small_m1 --seed -1 --out {d}/x.tif", 2, "--seed -1"),
    ("seed-huge", "simulate alignment small_m1 --seed 1099511627776 --out {d}/x.tif", 2,
     "--seed"),
    ("f-number-0", "simulate focal-point small_m1 --f-number 0 --out {d}/x.tif", 2,
     "--f-number 0"),
    ("f-number-negative", "simulate particles small_m1 --f-number -2 --out {d}/x.tif", 2,
     "--f-number -2"),
    ("f-number-inf", "simulate focal-point small_m1 --f-number inf --out {d}/x.tif", 2,
     "--f-number inf"),
    ("blur-negative", "simulate particles small_m1 --blur-px -1 --out {d}/x.tif", 2,
     "--blur-px -1"),
    ("blur-nan", "simulate particles small_m1 --blur-px nan --out {d}/x.tif", 2, "--blur-px"),
    ("rays-per-particle-0", "simulate particles small_m1 --rays-per-particle 0 --out {d}/x.tif",
     2, "--rays-per-particle 0"),
    ("full-well-0", "simulate particles small_m1 --full-well 0 --out {d}/x.tif", 2,
     "--full-well 0"),
    ("read-noise-negative", "simulate particles small_m1 --read-noise -1 --out {d}/x.tif", 2,
     "--read-noise"),
    ("n-particles-0", "simulate particles small_m1 --n-particles 0 --out {d}/x.tif", 2,
     "--n-particles 0"),
    ("density-0", "simulate particles small_m1 --particles-per-lenslet 0 --out {d}/x.tif", 2,
     "--particles-per-lenslet"),
    ("density-mm3-negative", "simulate pair small_m1 --particles-per-mm3 -1 --out {d}/p.h5", 2,
     "--particles-per-mm3"),
    ("fill-0", "simulate particles small_m1 --fill 0 --out {d}/x.tif", 2, "--fill 0"),
    ("fill-above-1", "simulate particles small_m1 --fill 1.5 --out {d}/x.tif", 2, "--fill 1.5"),
    ("depth-reversed", "simulate particles small_m1 --depth-mm 5 -5 --out {d}/x.tif", 2,
     "--depth-mm ZMAX"),
    ("ruler-spacing-0", "simulate ruler small_m1 --spacing-mm 0 --out {d}/x.tif", 2,
     "--spacing-mm 0"),
    ("ruler-tick-wider", "simulate ruler small_m1 --spacing-mm 1 --tick-width-mm 2 --out "
     "{d}/x.tif", 2, "--tick-width-mm"),
    ("ruler-rays-0", "simulate ruler small_m1 --rays-per-lenslet 0 --out {d}/x.tif", 2,
     "--rays-per-lenslet"),
    ("image-distance-0", "simulate alignment small_m1 --image-distance-mm 0 --out {d}/x.tif", 2,
     "--image-distance-mm"),
    ("image-distance-virtual", "simulate alignment small_m1 --image-distance-mm 10 --out "
     "{d}/x.tif", 2, "--image-distance-mm 10: expected > [main_lens] focal_length_mm = 50"),
    ("max-displacement-0", "simulate pair small_m1 --max-displacement-mm 0 --out {d}/p.h5", 2,
     "--max-displacement-mm"),
    ("out-suffix", "simulate alignment small_m1 --out {d}/x.txt", 2, ".tif"),
    ("out-folder", "simulate alignment small_m1 --out {d}/folder.tif", 2, "is a folder"),
    ("out-proc", "simulate alignment small_m1 --out /proc/x.tif", 2, "cannot create files"),
    ("bit-depth-12", "simulate alignment small_m1 --bit-depth 12 --out {d}/x.tif", 2,
     "--bit-depth"),
    ("noise-unknown", "simulate alignment small_m1 --noise gaussian --out {d}/x.tif", 2,
     "--noise"),
    ("out-missing", "simulate alignment small_m1", 2, "--out"),
    ("simulate-unknown-kind", "simulate volume small_m1 --out {d}/x.tif", 2, "invalid choice"),
    # ---- calibrate ----
    ("missing-fraction-negative", "calibrate small_m1 --focal-point {d}/a.tif "
     "--max-missing-fraction -1 --out {d}/c.h5", 2, "--max-missing-fraction -1"),
    ("missing-fraction-above-1", "calibrate small_m1 --focal-point {d}/a.tif "
     "--max-missing-fraction 1.5 --out {d}/c.h5", 2, "--max-missing-fraction 1.5"),
    ("ruler-spacing-mm-0", "calibrate small_m1 --focal-point {d}/a.tif --ruler {d}/a.tif "
     "--ruler-spacing-mm 0 --method both --out {d}/c.h5", 2, "--ruler-spacing-mm 0"),
    ("ruler-spacing-mm-negative", "calibrate small_m1 --focal-point {d}/a.tif --ruler {d}/a.tif "
     "--ruler-spacing-mm -1 --method both --out {d}/c.h5", 2, "--ruler-spacing-mm -1"),
    ("ruler-spacing-mm-nan-json", "calibrate small_m1 --focal-point {d}/a.tif --ruler {d}/a.tif "
     "--ruler-spacing-mm nan --method both --out {d}/c.h5 --json", 2, "--ruler-spacing-mm nan"),
    ("method-needs-ruler", "calibrate small_m1 --focal-point {d}/a.tif --method both --out "
     "{d}/c.h5", 2, "needs --ruler"),
    ("calibrate-out-is-input", "calibrate small_m1 --focal-point {d}/img.h5:/image --out "
     "{d}/img.h5", 2, "is the input"),
    ("calibrate-image-missing", "calibrate small_m1 --focal-point {d}/none.tif --out {d}/c.h5",
     2, "not found"),
    ("calibrate-complex", "calibrate small_m1 --focal-point {d}/complex.h5:/image --out "
     "{d}/c.h5", 2, "complex"),
    ("calibrate-out-sys", "calibrate small_m1 --focal-point {d}/a.tif --out /sys/c.h5", 2,
     "cannot create files"),
    # ---- reconstruct ----
    ("reconstruct-out-is-calibration", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/exp.toml "
     "--out {d}/cal.h5", 2, "is the input"),
    ("reconstruct-out-is-image", "reconstruct {d}/cal.h5 {d}/img.h5:/image --config "
     "{d}/exp.toml --out {d}/img.h5", 2, "is the input"),
    ("calibration-of-135mm-lens", "reconstruct {d}/cal_135.h5 {d}/a.tif --config {d}/exp.toml "
     "--out {d}/v.h5", 2, "main lens focal length 135 mm ≠ 50 mm"),
    ("config-not-utf8", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/bad_utf8.toml --out "
     "{d}/v.h5", 2, "not UTF-8"),
    ("voxel-larger-than-box", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/big_voxel.toml "
     "--out {d}/v.h5", 2, "voxel_mm = 50 is larger than the box"),
    ("z-minus-inf", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/inf_z.toml --out {d}/v.h5",
     2, "z_mm = [-inf, 3.0]: expected finite"),
    ("voxel-two-values", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/two_voxel.toml --out "
     "{d}/v.h5", 2, "voxel_mm = [0.1, 0.1]: expected one number"),
    ("voxel-0.6-um", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/tiny_voxel.toml --out "
     "{d}/v.h5", 2, "voxels: expected at most"),
    ("shape-1e4-cubed", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/huge_shape.toml --out "
     "{d}/v.h5", 2, "1e+12 voxels"),
    ("iterations-1e9", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/iterations.toml --out "
     "{d}/v.h5", 2, "iterations"),
    ("relaxation-nan", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/nan_relax.toml --out "
     "{d}/v.h5", 2, "relaxation"),
    ("unknown-key", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/unknown_key.toml --out "
     "{d}/v.h5", 2, "unknown key [piv] window"),
    ("dt-s-inf", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/dt_inf.toml --out {d}/v.h5", 2,
     "dt_s"),
    ("uniform-noise-image", "reconstruct {d}/cal.h5 {d}/noise.tif --config {d}/exp.toml --out "
     "{d}/v.h5 --json", 2, "looks like pure noise"),
    ("complex-image", "reconstruct {d}/cal.h5 {d}/complex.h5:/image --config {d}/exp.toml --out "
     "{d}/v.h5", 2, "complex values"),
    ("negative-background", "reconstruct {d}/cal.h5 {d}/negative.tif --config {d}/exp.toml "
     "--out {d}/v.h5", 2, "negative background"),
    ("12-bit-saturated", "reconstruct {d}/cal.h5 {d}/sat12.tif --config {d}/exp.toml --out "
     "{d}/v.h5", 2, "at 4095 (12-bit data in uint16)"),
    ("float-clipped", "reconstruct {d}/cal.h5 {d}/clipped.tif --config {d}/exp.toml --out "
     "{d}/v.h5", 2, "at 1 (clipped floats)"),
    ("image-wrong-size", "reconstruct {d}/cal.h5 {d}/small.tif --config {d}/exp.toml --out "
     "{d}/v.h5", 2, "camera's sensor is 700 × 1040"),
    ("calibration-missing", "reconstruct {d}/none.h5 {d}/a.tif --config {d}/exp.toml --out "
     "{d}/v.h5", 2, "not found"),
    ("calibration-is-volume", "reconstruct {d}/va.h5 {d}/a.tif --config {d}/exp.toml --out "
     "{d}/v.h5", 2, "not a plenopiv calibration"),
    ("reconstruct-out-folder", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/exp.toml --out "
     "{d}/folder.h5", 2, "is a folder"),
    # ---- preprocessing ----
    ("preprocess-dark-missing", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/pre_missing.toml "
     "--out {d}/v.h5", 2, "[preprocess] dark = 'none.tif': file"),
    ("preprocess-dark-wrong-shape", "reconstruct {d}/cal.h5 {d}/a.tif --config "
     "{d}/pre_small.toml --out {d}/v.h5 --json", 2,
     "[preprocess] dark 'small.tif' is 10 × 10 pixels: expected the sensor's 700 × 1040"),
    ("preprocess-white-not-a-white", "reconstruct {d}/cal.h5 {d}/a.tif --config "
     "{d}/pre_uniform.toml --out {d}/v.h5", 2, "'uniform.tif' shows no micro-image structure"),
    ("preprocess-minimum-for-one-image", "reconstruct {d}/cal.h5 {d}/a.tif --config "
     "{d}/pre_minimum.toml --out {d}/v.h5", 2, '[preprocess] background = "minimum" is the'),
    ("track-out-is-image", "track {d}/cal.h5 {d}/img.h5:/image {d}/a.tif --config "
     "{d}/exp.toml --out {d}/img.h5", 2, "is the input"),
    ("track-out-is-volume-a", "track {d}/cal.h5 {d}/a.tif {d}/a.tif --config {d}/exp.toml "
     "--volume-a {d}/va.h5 --out {d}/va.h5", 2, "is the input"),
    ("preprocess-minimum-for-one-pair", "track {d}/cal.h5 {d}/a.tif {d}/a.tif --config "
     "{d}/pre_minimum.toml --out {d}/t.h5 --json", 2, "give the path of a background image"),
    ("preprocess-unknown-key", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/pre_unknown.toml "
     "--out {d}/v.h5", 2, "unknown key [preprocess] flat"),
    ("preprocess-hot-pixels-word", "reconstruct {d}/cal.h5 {d}/a.tif --config {d}/pre_hot.toml "
     "--out {d}/v.h5", 2, "hot_pixels = 'some'"),
    ("run-preprocess-white-missing", "run {d}/run_pre_missing.toml", 2,
     "[preprocess] white = 'none.tif': file"),
    ("calibrate-dark-missing", "calibrate small_m1 --focal-point {d}/a.tif --dark {d}/none.tif "
     "--out {d}/c.h5", 2, "none.tif': file not found: expected a dark frame"),
    ("calibrate-dark-wrong-shape", "calibrate small_m1 --focal-point {d}/a.tif --dark "
     "{d}/small.tif --out {d}/c.h5", 2, "small.tif' is 10 × 10 pixels: expected the sensor's"),
    # ---- piv ----
    ("windows-0", "piv {d}/va.h5 {d}/vb.h5 --windows 0 0 0 --out {d}/w.h5 --json", 2,
     "--windows 0 0 0"),
    ("windows-1", "piv {d}/va.h5 {d}/vb.h5 --windows 1 1 1 --out {d}/w.h5", 2,
     "--windows 1 1 1"),
    ("windows-negative", "piv {d}/va.h5 {d}/vb.h5 --windows -8 8 8 --out {d}/w.h5 --json", 2,
     "--windows -8 8 8"),
    ("piv-config-windows", "piv {d}/va.h5 {d}/vb.h5 --config {d}/small_windows.toml --out "
     "{d}/w.h5", 2, "windows"),
    ("piv-out-is-volume-a", "piv {d}/va.h5 {d}/vb.h5 --out {d}/va.h5", 2, "is the input"),
    ("piv-out-folder", "piv {d}/va.h5 {d}/vb.h5 --out {d}/folder.h5", 2, "is a folder"),
    ("piv-out-proc", "piv {d}/va.h5 {d}/vb.h5 --out /proc/w.h5", 2, "cannot create files"),
    ("piv-out-sys", "piv {d}/va.h5 {d}/vb.h5 --out /sys/w.h5", 2, "cannot create files"),
    ("piv-dt-inf", "piv {d}/va.h5 {d}/vb.h5 --dt inf --out {d}/w.h5", 2, "--dt inf"),
    ("piv-dt-negative-json", "piv {d}/va.h5 {d}/vb.h5 --dt -1e-3 --out {d}/w.h5 --json", 2,
     "--dt -0.001"),
    ("piv-dt-0", "piv {d}/va.h5 {d}/vb.h5 --dt 0 --out {d}/w.h5", 2, "--dt 0"),
    ("piv-dt-nan", "piv {d}/va.h5 {d}/vb.h5 --dt nan --out {d}/w.h5", 2, "--dt nan"),
    ("piv-dt-no-value", "piv {d}/va.h5 {d}/vb.h5 --dt --out {d}/w.h5", 2, "--dt"),
    ("piv-different-grids", "piv {d}/va.h5 {d}/vc.h5 --out {d}/w.h5", 2, "different grids"),
    ("piv-volume-missing", "piv {d}/va.h5 {d}/none.h5 --out {d}/w.h5", 2, "not found"),
    ("piv-volume-is-calibration", "piv {d}/va.h5 {d}/cal.h5 --out {d}/w.h5", 2,
     "not a plenopiv volume"),
    # ---- compare ----
    ("compare-vectors-missing", "compare {d}/none.h5 {d}/va.h5", 2, "VECTORS file"),
    ("compare-vectors-is-volume", "compare {d}/va.h5 {d}/vb.h5 --json", 2,
     "is a plenopiv volume file: expected a vectors product"),
    ("compare-bands-0", "compare {d}/va.h5 {d}/vb.h5 --bands 0", 2, "--bands 0"),
    # ---- validate, demo ----
    ("lateral-oversampling-0", "validate oseen --lateral-oversampling 0 --out {d}/val", 2,
     "--lateral-oversampling 0"),
    ("validate-out-file", "validate oseen --out {d}/a.tif", 2, "is an existing file"),
    ("validate-density-0", "validate oseen --particles-per-lenslet 0 --out {d}/val", 2,
     "--particles-per-lenslet"),
    ("validate-seed-negative", "validate hill --seed -1 --out {d}/val", 2, "--seed -1"),
    ("validate-lenslets-0", "validate oseen --lenslets 0 5 --out {d}/val", 2, "--lenslets"),
    ("demo-out-existing-file", "demo --out {d}/exp.toml", 2, "is an existing file"),
    ("demo-seed-negative", "demo --seed -5 --out {d}/demo", 2, "--seed -5"),
    # ---- run ----
    ("run-workers-0", "run {d}/exp.toml --workers 0", 2, "--workers 0"),
    ("run-no-calibration", "run {d}/no_cal.toml", 2, "calibration is not set"),
    ("run-pattern-matches-nothing", "run {d}/no_match.toml", 2, "matches no file"),
    ("run-bad-cluster", "run {d}/bad_cluster.toml", 2, "cluster 'pbs'"),
    ("run-output-dir-is-file", "run {d}/out_is_file.toml", 2, "is an existing file"),
    ("run-a-b-counts", "run {d}/count.toml", 2, "matches 2 files but pattern_b"),
    ("run-calibration-of-other-camera", "run {d}/wrong_cal.toml --json", 2, "was made for"),
    ("run-cluster-flag", "run {d}/bad_cluster.toml --cluster slurm://x", 2, "slurm://x"),
    ("run-product-overwrites-input", "run {d}/clash.toml", 2,
     "clash/p_volume_A.h5', which is one of the batch's inputs"),
    # ---- the command line itself ----
    ("no-command", "", 2, "required"),
    ("unknown-command", "fly", 2, "invalid choice"),
    ("unknown-option", "piv {d}/va.h5 {d}/vb.h5 --out {d}/w.h5 --bogus", 2, "--bogus"),
]


def test_the_table_is_long_enough():
    assert len(CASES) >= 60
    assert len({c[0] for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_invocation_is_one_clear_error(case, inputs, capsys):
    _, argv, status, words = case
    args = [a.replace("{d}", str(inputs)) for a in argv.split()]
    before = tree(inputs)
    code = main(args)
    out, err = capsys.readouterr()
    assert code == status, (code, out, err)
    assert "Traceback" not in out + err
    lines = [ln for ln in err.splitlines() if ln.startswith("error: ")]
    assert len(lines) == 1, err
    assert words in lines[0], lines[0]
    if "--json" in args:
        obj = json.loads(out)             # valid JSON: no bare NaN
        assert obj["error"] == lines[0][len("error: "):] and obj["exit_status"] == status
    assert tree(inputs) == before         # no input changed, nothing written, no temporary


def test_json_never_holds_bare_nan(tmp_path, capsys):
    from plenopiv.products.jsonio import to_json

    text = to_json({"a": float("nan"), "b": [np.inf, 1.0], "c": np.float32("-inf")})
    assert json.loads(text) == {"a": None, "b": [None, 1.0], "c": None}


def test_warnings_are_lines_and_json_entries(inputs, monkeypatch, capsys):
    """Saturation below the refusal limit is a warning with the fraction: a ``warning:`` line
    and, with --json, an entry of "warnings" in the summary."""
    from plenopiv.products.images import check_image

    rng = np.random.default_rng(3)
    img = particle_like(rng)
    sat = (img / img.max() * 3000).astype(np.uint16)
    sat[rng.random(SHAPE) < 0.01] = 4095

    def checks(args):
        check_image(sat, name="particle image", particles=True)
        return {"command": "piv"}

    code = _piv_running(checks, inputs, monkeypatch, as_json=True)
    out, err = capsys.readouterr()
    assert code == 0
    assert err.startswith("warning: particle image is saturated: 0.9")
    assert "of the pixels are at 4095 (12-bit data in uint16)" in err
    assert json.loads(out)["warnings"] == [err.strip()[len("warning: "):]]


def test_a_warning_said_twice_by_one_command_is_one_line(inputs, monkeypatch, capsys):
    """A command that meets the same finding twice (its weights built for the response and
    again for the batch) says it once, in its lines and in its JSON."""
    import warnings

    from plenopiv.errors import PlenopivWarning

    def twice(args):
        for _ in range(2):
            warnings.warn("lateral_subdivision = \"auto\": taking 1 x 1", PlenopivWarning,
                          stacklevel=2)
        warnings.warn("another finding", PlenopivWarning, stacklevel=2)
        return {"command": "piv"}

    code = _piv_running(twice, inputs, monkeypatch, as_json=True)
    out, err = capsys.readouterr()
    assert code == 0
    assert err.splitlines() == ['warning: lateral_subdivision = "auto": taking 1 x 1',
                                "warning: another finding"]
    assert json.loads(out)["warnings"] == ['lateral_subdivision = "auto": taking 1 x 1',
                                           "another finding"]


def test_unexpected_exception_is_one_line_exit_1(monkeypatch, capsys, inputs):

    def broken(args):
        raise ZeroDivisionError("float division by zero")

    code = _piv_running(broken, inputs, monkeypatch, as_json=True)
    out, err = capsys.readouterr()
    assert code == 1 and "Traceback" not in err
    assert err.startswith("error: unexpected ZeroDivisionError: float division by zero")
    assert json.loads(out)["exit_status"] == 1


def _piv_running(func, inputs, monkeypatch, *, as_json: bool = False) -> int:
    """``plenopiv piv`` on the fixture's volumes with ``func`` as its command: the exit status."""
    import plenopiv.cli as cli

    parser = cli.build_parser
    monkeypatch.setattr(cli, "build_parser", lambda: _with_func(parser(), func))
    return main(["piv", str(inputs / "va.h5"), str(inputs / "vb.h5"), "--out",
                 str(inputs / "w.h5"), *(["--json"] if as_json else [])])


def _with_func(parser, func):
    parse = parser.parse_args

    def parse_args(argv):
        args = parse(argv)
        args.func = func
        return args

    parser.parse_args = parse_args
    return parser


def test_interrupt_is_exit_130(monkeypatch, capsys, inputs):

    def interrupted(args):
        raise KeyboardInterrupt

    code = _piv_running(interrupted, inputs, monkeypatch)
    assert code == 130 and capsys.readouterr().err.startswith("error: interrupted")


def test_help_and_version_exit_0(capsys):
    assert main(["--version"]) == 0
    assert capsys.readouterr().out.startswith("plenopiv ")
    assert main(["piv", "--help"]) == 0


def env_with_src():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO / "src") + os.pathsep + env.get("PYTHONPATH", "")
    return env


@pytest.mark.parametrize("argv, words", [
    (["simulate", "alignment", "{d}/bad_utf8.toml", "--out", "{d}/x.tif"], "not UTF-8"),
    (["piv", "{d}/va.h5", "{d}/vb.h5", "--dt", "-1e-3", "--out", "{d}/w.h5", "--json"],
     "--dt -0.001"),
    (["piv", "{d}/va.h5", "{d}/vb.h5", "--windows", "0", "0", "0", "--out", "{d}/w.h5",
      "--json"], "--windows 0 0 0"),
])
def test_bad_invocations_as_real_processes(argv, words, inputs):
    before = tree(inputs)
    args = [a.replace("{d}", str(inputs)) for a in argv]
    res = subprocess.run([sys.executable, "-m", "plenopiv.cli", *args], capture_output=True,
                         text=True, env=env_with_src(), timeout=120)
    assert res.returncode == 2
    assert "Traceback" not in res.stderr and res.stderr.startswith("error: ")
    assert words in res.stderr
    if "--json" in args:
        assert "error" in json.loads(res.stdout)
    assert tree(inputs) == before


# ---- validate: the studies kept in the repository's pipelines/ ------------------------------

STUDY_CASES = ("vortex", "calibration", "depth", "fields", "letters", "uncertainty")


@pytest.mark.parametrize("case", STUDY_CASES)
def test_validate_a_study_without_the_repository_is_one_clear_error(case, tmp_path, monkeypatch,
                                                                     capsys):
    """An installed package does not carry pipelines/: exit 2, the script to run instead."""
    from plenopiv.cli import validate

    monkeypatch.setattr(validate, "studies_root", lambda: None)
    code = main(["validate", case, "--out", str(tmp_path / "val"), "--json"])
    out, err = capsys.readouterr()
    assert code == 2 and "Traceback" not in out + err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: validate {case} runs a study kept ")
    assert f"python pipelines/{validate.STUDIES[case][1]} --out DIR" in lines[0]
    assert json.loads(out)["exit_status"] == 2
    assert not (tmp_path / "val").exists()


def test_studies_are_found_under_plenopiv_repo_or_beside_the_source_tree(tmp_path, monkeypatch):
    import plenopiv
    from plenopiv.cli import validate

    monkeypatch.delenv("PLENOPIV_REPO", raising=False)
    # an installed package: site-packages/plenopiv/, no pipelines/ two folders up
    monkeypatch.setattr(plenopiv, "__file__", str(tmp_path / "lib" / "plenopiv" / "__init__.py"))
    assert validate.studies_root() is None
    monkeypatch.setenv("PLENOPIV_REPO", str(tmp_path))              # not a clone: still none
    assert validate.studies_root() is None
    monkeypatch.setenv("PLENOPIV_REPO", str(REPO))
    assert validate.studies_root() == REPO
    # a clone's source tree: src/plenopiv/ beside pipelines/
    monkeypatch.delenv("PLENOPIV_REPO")
    monkeypatch.setattr(plenopiv, "__file__", str(REPO / "src" / "plenopiv" / "__init__.py"))
    assert validate.studies_root() == REPO


@pytest.mark.study
def test_validate_a_study_from_a_clone_runs_it(tmp_path, monkeypatch, capsys):
    """Found under $PLENOPIV_REPO, the study is imported by file location (sys.path unchanged)
    and its ``run`` called with the output folder."""
    from pipelines.studies import depth_report

    calls = []

    def run(out, **kw):
        calls.append((out, kw))
        return {"slopes_10mm": {"none corrected": 1.0}}

    monkeypatch.setenv("PLENOPIV_REPO", str(REPO))
    monkeypatch.setattr(depth_report, "run", run)
    path = list(sys.path)
    code = main(["validate", "depth", "--out", str(tmp_path / "val"), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert calls == [(str(tmp_path / "val"), {})]
    summary = json.loads(out)
    assert summary["command"] == "validate depth" and summary["slopes_10mm"]
    assert sys.path == path


@pytest.mark.study
def test_a_study_loads_by_file_location_in_a_fresh_process(tmp_path):
    """Without the repository on sys.path: pipelines.studies comes from $PLENOPIV_REPO."""
    code = ("import importlib.util, sys; from plenopiv.cli.validate import load_study, "
            "studies_root; path = list(sys.path); "
            "print(importlib.util.find_spec('pipelines') is None); "
            "print(load_study(studies_root(), 'letters_data').__file__); print(sys.path == path)")
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"), PLENOPIV_REPO=str(REPO))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=tmp_path, check=True, timeout=120)
    not_on_path, file, path_kept = res.stdout.split()
    assert not_on_path == "True" and path_kept == "True"
    assert Path(file) == REPO / "pipelines" / "studies" / "letters_data.py"


def test_validate_a_study_from_an_installed_package_as_a_real_process(tmp_path):
    """The package copied out of the clone, as a wheel installs it: validate depth refuses
    with the script to run; validate oseen's parser still answers."""
    shutil.copytree(REPO / "src" / "plenopiv", tmp_path / "site" / "plenopiv",
                    ignore=shutil.ignore_patterns("__pycache__"))
    env = {k: v for k, v in os.environ.items() if k != "PLENOPIV_REPO"}
    env["PYTHONPATH"] = str(tmp_path / "site")
    res = subprocess.run([sys.executable, "-m", "plenopiv.cli", "validate", "depth", "--out",
                          str(tmp_path / "val")], capture_output=True, text=True, env=env,
                         cwd=tmp_path, timeout=120)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.startswith("error: validate depth runs a study kept in the repository's "
                                 "pipelines/ folder")
    assert "python pipelines/validate_depth.py --out DIR" in res.stderr
    assert not (tmp_path / "val").exists()


def test_a_rerun_removes_the_temporaries_of_a_killed_write(inputs, tmp_path, capsys):
    """`plenopiv piv` killed while writing left hidden temporaries: the next run of the same
    command removes them and writes its products."""
    out = tmp_path / "w.h5"
    stale = [tmp_path / ".w.h5.k1ll3d00.part", tmp_path / ".w.vti.k1ll3d01.part.vti",
             tmp_path / ".w.vti.k1ll3d02.part"]
    for p in stale:
        p.write_bytes(b"half")
    other = tmp_path / ".x.h5.k1ll3d03.part"             # another output's: left alone
    other.write_bytes(b"")
    code = main(["piv", str(inputs / "va.h5"), str(inputs / "vb.h5"), "--out", str(out),
                 "--windows", "4", "4", "4", "--no-png", "--quiet"])
    capsys.readouterr()
    assert code == 0 and out.exists() and (tmp_path / "w.vti").exists()
    assert not any(p.exists() for p in stale) and other.exists()
