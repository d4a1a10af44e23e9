"""``plenopiv run``'s resume: a pair is kept only when nothing that made it changed.

One batch of one pair is run once (the module fixture); each case copies its folder, changes
one thing that made the pair's products (a file, a setting, a product) and asserts the resume
decision: recomputed with the reason, or kept. One case runs the batch again and reads the
reason in its summary.
"""

from __future__ import annotations

import json
import shutil

import h5py
import numpy as np
import pytest
import tifffile

from plenopiv.batch import SUMMARY_NAME, _jobs_to_run
from plenopiv.batch.jobs import finished_before
from plenopiv.calibration.model import Calibration
from plenopiv.camera.model import load_camera
from plenopiv.cli import main
from plenopiv.cli.run import batch_jobs, with_identities
from plenopiv.config.experiment import load_experiment
from plenopiv.products.files import PACKAGE_DIR
from small_case import VOLUME, simulate_pair_argv

EXPERIMENT = """camera = "camera.toml"
""" + VOLUME + """[reconstruction]
lateral_subdivision = 1
[piv]
windows = [[12, 12, 12]]
passes = 2
[mask]
image = "mask.npy"
[preprocess]
dark = "dark.tif"
[images]
pairs = "pairs/*.h5"
calibration = "cal.h5"
dt_s = 1e-3
[output]
directory = "out"
png = false
vtk = false
weights_cache = "cache"
"""


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A folder whose batch (one pair) has run."""
    d = tmp_path_factory.mktemp("batch")
    shutil.copyfile(PACKAGE_DIR / "presets" / "small_m1.toml", d / "camera.toml")
    cam = load_camera(d / "camera.toml")
    Calibration.from_camera(cam).save(d / "cal.h5")
    (d / "pairs").mkdir()
    assert main(simulate_pair_argv(d / "pairs" / "p.h5", seed=3) + ["--quiet"]) == 0
    tifffile.imwrite(d / "dark.tif", np.full(cam.sensor.shape, 2, np.uint16))
    np.save(d / "mask.npy", np.zeros(cam.sensor.shape, bool))
    (d / "exp.toml").write_text(EXPERIMENT)
    assert main(["run", str(d / "exp.toml"), "--workers", "1", "--quiet"]) == 0
    return d


def _replace_text(path, old, new):
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))


def _edit_dataset(path, name, edit):
    with h5py.File(path, "r+") as fh:
        fh[name][...] = edit(fh[name][()])


def _other_calibration(d):
    cal = Calibration.load(d / "cal.h5")
    centre = cal.centre_px.copy()
    centre[3, 1] += 1e-3
    import dataclasses

    dataclasses.replace(cal, centre_px=centre).save(d / "cal.h5")


#: Each change: what it does to the copied folder, and the reason the resume must give
#: (None: the pair is kept).
CHANGES = {
    "nothing": (lambda d: None, None),
    "a comment in the camera file": (lambda d: _replace_text(
        d / "camera.toml", "[sensor]", "# the same camera\n[sensor]"), None),
    "the camera": (lambda d: _replace_text(d / "camera.toml", "f_number = 2.2",
                                           "f_number = 2.8"), "made with other settings"),
    "a setting": (lambda d: _replace_text(d / "exp.toml", "passes = 2", "passes = 3"),
                  "made with other settings"),
    "a mask added": (lambda d: _replace_text(
        d / "exp.toml", "[preprocess]",
        "[[mask.box]]\nx_mm = [0, 1]\ny_mm = [0, 1]\nz_mm = [0, 1]\n[preprocess]"),
        "made with other settings"),
    "the mask file": (lambda d: np.save(d / "mask.npy", np.eye(700, 1040, dtype=bool)),
                      "made with other mask files"),
    "the dark frame": (lambda d: tifffile.imwrite(d / "dark.tif",
                                                  np.full((700, 1040), 3, np.uint16)),
                       "made with other preprocessing frames"),
    "the calibration": (_other_calibration, "made with other calibration"),
    "an image": (lambda d: _edit_dataset(d / "pairs" / "p.h5", "/image_a", lambda a: a + 1),
                 "made with other first image, second image"),
    "the vectors deleted": (lambda d: (d / "out" / "p_vectors.h5").unlink(),
                            "its product p_vectors.h5 was deleted since the last run"),
    "the vectors damaged": (lambda d: (d / "out" / "p_vectors.h5").write_bytes(b"damaged"),
                            "is no longer complete"),
    "a volume deleted": (lambda d: (d / "out" / "p_volume_A.h5").unlink(),
                         "its p_volume_A.h5 is missing"),
    "the product of a newer plenopiv": (lambda d: _newer(d / "out" / "p_vectors.h5"),
                                        "this plenopiv cannot read it"),
}


def _newer(path):
    with h5py.File(path, "r+") as fh:
        fh.attrs["schema_version"] = 3


@pytest.mark.parametrize("change", CHANGES)
def test_resume_recomputes_a_pair_when_what_made_it_changed(finished, tmp_path, change):
    d = tmp_path / "copy"
    shutil.copytree(finished, d)
    apply, reason = CHANGES[change]
    apply(d)
    exp = load_experiment(d / "exp.toml")
    jobs = with_identities(batch_jobs(exp), exp, exp.path(exp.images.calibration))
    kept, recomputed, todo = _jobs_to_run(jobs, True, finished_before(d / "out" / SUMMARY_NAME))
    if reason is None:
        assert list(kept) == ["p"] and not todo
        return
    assert [j.name for j in todo] == ["p"] and not kept
    assert len(recomputed) == 1 and reason in recomputed[0][1], recomputed


def test_a_rerun_says_why_it_recomputes_a_pair(finished, tmp_path, capsys):
    d = tmp_path / "copy"
    shutil.copytree(finished, d)
    (d / "out" / "p_volume_B.h5").unlink()
    capsys.readouterr()
    assert main(["run", str(d / "exp.toml"), "--workers", "1", "--json", "--quiet"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["done"] == ["p"] and s["recomputed"] == [
        {"name": "p", "reason": "its p_volume_B.h5 is missing (deleted since it was made)"}]
    assert json.loads((d / "out" / SUMMARY_NAME).read_text())["recomputed"] == s["recomputed"]
    assert (d / "out" / "p_volume_B.h5").exists()


@pytest.mark.parametrize("user_env", [{}, {"MALLOC_TRIM_THRESHOLD_": "131072"}])
def test_the_workers_get_the_allocator_settings_of_the_command(finished, tmp_path, monkeypatch,
                                                               user_env):
    """A dask nanny starts its workers with its own ``MALLOC_TRIM_THRESHOLD_``; what the
    user set where ``plenopiv run`` runs is handed to the pairs' process instead."""
    import plenopiv.batch

    for key in ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_MAX_"):
        monkeypatch.delenv(key, raising=False)
    for key, value in user_env.items():
        monkeypatch.setenv(key, value)
    d = tmp_path / "copy"
    shutil.copytree(finished, d)
    handed, real = [], plenopiv.batch.run_batch
    monkeypatch.setattr(plenopiv.batch, "run_batch",
                        lambda jobs, process, **kw: handed.append(process) or real(jobs, process,
                                                                                   **kw))
    assert main(["run", str(d / "exp.toml"), "--workers", "1", "--quiet"]) == 0   # resumed
    assert [p.allocator for p in handed] == [tuple(user_env.items())]
