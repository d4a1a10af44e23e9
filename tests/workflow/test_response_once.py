"""The chain's response is measured once per experiment: its key holds what the experiment
fixes, never a pair's particle count, and ``plenopiv run`` measures it before the pairs."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.camera.model import load_camera
from plenopiv.cli import main
from plenopiv.config.experiment import Experiment, ImagesConfig, OutputConfig
from plenopiv.piv.settings import PIVSettings
from plenopiv.synthetic.flows import Uniform
from plenopiv.synthetic.seeding import SeedingBox, simulate_pair
from plenopiv.workflow import response as response_module
from plenopiv.workflow.pair import PairProcessor
from plenopiv.workflow.response import (
    experiment_response_key,
    response_counts,
    response_particle_count,
)
from plenopiv.workflow.vortex_case import VortexCase, aligned_grid


@pytest.fixture
def counted(monkeypatch):
    """Calls of the response measurement (the real one, counted)."""
    calls = []
    real = response_module.measure_response

    def measure(*args, **kwargs):
        calls.append(kwargs["n_particles"])
        return real(*args, **kwargs)

    monkeypatch.setattr(response_module, "measure_response", measure)
    return calls


def test_pairs_with_different_counts_share_one_response(tmp_path, counted):
    """Two pairs of one experiment, 30 and 90 particles (found counts that the old key
    rounded to 32 and 64 or 128): one key, one measurement; the second processor (another
    worker) reads it from the cache, and its pair says how long that took."""
    cam = load_camera("small_m1")
    cal = Calibration.from_camera(cam)
    grid = aligned_grid(cam, VortexCase(depth=2e-3, lateral_fill=0.5))
    box = SeedingBox(tuple(grid.bounds[0]), tuple(grid.bounds[1]), (-2e-3, 2e-3))
    exp = Experiment(camera=cam, volume=grid,
                     piv=PIVSettings(windows=((16, 16, 16),), passes=2, response_displacements=1),
                     images=ImagesConfig(dt_s=1e-3),
                     output=OutputConfig(directory=str(tmp_path), weights_cache="cache"),
                     base_dir=tmp_path)
    rng = np.random.default_rng(5)
    found, keys, timings = [], [], []
    for n in (30, 90):
        pair = simulate_pair(cam, Uniform((0.25, 0.0, 0.0)), dt=1e-3, box=box, n_particles=n,
                             rng=rng, rays_per_particle=512)
        processor = PairProcessor(exp, cal)          # a fresh worker for each pair
        res = processor(pair.image_a, pair.image_b)
        found.append(len(res.volume_a.particle_position))
        keys.append(processor.response().key)
        timings.append(res.timings)
        assert res.vectors.uncertainty_method == "response"
    assert found[1] > 2 * found[0]
    assert keys[0] == keys[1]
    n = response_particle_count(cal, grid, exp.piv.response_particles_per_lenslet)
    assert counted == [n]                            # measured once, at the experiment's density
    assert len(list((tmp_path / "cache").glob("response-*.json"))) == 1
    assert "response_s" in timings[0] and "response_s" in timings[1]
    # the key changes with what the experiment fixes
    w = PairProcessor(exp, cal).weights().key
    denser = dataclasses.replace(exp, piv=dataclasses.replace(
        exp.piv, response_particles_per_lenslet=0.3))
    assert experiment_response_key(denser, cal, w) != keys[0]
    assert experiment_response_key(exp, cal, w) == keys[0]
    assert experiment_response_key(exp, cal, w, volume_mask=np.zeros(grid.shape, bool)) != keys[0]


def test_response_seeding_follows_the_box():
    """Particles per test pair: the density times the lenslets the box covers."""
    cam = load_camera("small_m1")
    cal = Calibration.from_camera(cam)
    grid = aligned_grid(cam, VortexCase(depth=2e-3, lateral_fill=0.5))
    n = response_particle_count(cal, grid, 0.15)
    assert response_particle_count(cal, grid, 0.3) == pytest.approx(2 * n, abs=1)
    from plenopiv.synthetic.images import field_of_view

    fx, fy = field_of_view(cam, 0.0)
    b = grid.bounds
    share = (b[0, 1] - b[0, 0]) * (b[1, 1] - b[1, 0]) / (4 * fx * fy)
    assert n == round(0.15 * cam.microlens_array.count * share)
    assert response_counts(3) == (16, 13) and response_counts(1) == (2, 2)


def test_plenopiv_run_measures_the_response_once_before_the_pairs(tmp_path, capsys, counted):
    """Three pairs of 20, 40 and 80 particles on a LocalCluster of two workers: the response
    is measured once, in the run, before the pairs; the pairs use it (no worker measures or
    reads it); the summary and the progress say so; a rerun with new pairs takes it from the
    cache."""
    cam = load_camera("small_m1")
    Calibration.from_camera(cam).save(tmp_path / "cal.h5")
    (tmp_path / "pairs").mkdir()
    for i, n in enumerate((20, 40, 80), start=1):
        assert main(["simulate", "pair", "small_m1", "--n-particles", str(n),
                     "--rays-per-particle", "256", "--depth-mm", "-1.5", "1.5", "--fill", "0.4",
                     "--seed", str(i), "--no-tiff", "--quiet",
                     "--out", str(tmp_path / "pairs" / f"p_{i}.h5")]) == 0
    exp = tmp_path / "exp.toml"
    exp.write_text(
        'camera = "small_m1"\n[volume]\nx_mm = [-1.0625, 1.0625]\ny_mm = [-1.0625, 1.0625]\n'
        'z_mm = [-1.5, 1.5]\nvoxel_mm = 0.125\n'
        '[piv]\nwindows = [[12, 12, 12]]\npasses = 2\nresponse_displacements = 1\n'
        '[images]\npairs = "pairs/*.h5"\ncalibration = "cal.h5"\ndt_s = 1e-3\n'
        '[output]\ndirectory = "out"\npng = false\nvtk = false\n')
    capsys.readouterr()
    assert main(["run", str(exp)]) == 0
    out, err = capsys.readouterr()
    assert err.count("measuring the chain's response: once per experiment, about ") == 1
    assert "response: measured once in" in out
    assert len(counted) == 1
    assert main(["run", str(exp), "--json", "--no-resume"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert sorted(s["done"]) == ["p_1", "p_2", "p_3"]
    assert s["response"]["from_cache"] and s["response"]["n_particles"] == counted[0]
    assert len(counted) == 1
    # no pair measured it, nor read it: they were handed the run's
    assert all("response_s" not in r["result"] for r in s["results"])
    assert len(list((tmp_path / ".plenopiv-cache").glob("response-*.json"))) == 1
    # everything complete: nothing to measure for
    assert main(["run", str(exp), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["n_skipped"] == 3 and s["response"] is None
