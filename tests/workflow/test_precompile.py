"""Background compilation (plenopiv.workflow.precompile): the rehearsals compile what the run needs.

The rehearsals only save time: the test that matters is that their kernels are the run's
(same kernels, same argument types), so that a first run finds them in numba's cache. It
runs the demo's case in a fresh interpreter after the rehearsals and lists every kernel that
gained a signature there; only the renderer's (the run compiles those while the rehearsals
work) may. The rest checks the pieces: the rehearsal's grid and images, and that a
rehearsal that fails or is stopped leaves nothing behind.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from plenopiv.calibration.model import Calibration
from plenopiv.calibration.spot_detection import detect_spots
from plenopiv.camera.grid import VolumeGrid
from plenopiv.workflow.precompile import (
    DEFAULT_CHILDREN,
    REHEARSALS,
    SPOT_LENSLETS,
    Rehearsals,
    blob_volume,
    rehearsal_grid,
    spot_image,
)
from plenopiv.workflow.vortex_case import VortexCase, case_camera

#: In a fresh interpreter: the rehearsals of the demo's case, then the case itself (a
#: smaller patch and depth of the same camera and settings); prints the kernels that gained
#: a signature during the case.
_AFTER_REHEARSALS = r"""
import json, sys, tempfile
from pathlib import Path

import numba
import plenopiv.workflow.precompile as P
from plenopiv.calibration.model import Calibration
from plenopiv.cli.demo import DEMO_RESPONSE_DISPLACEMENTS
from plenopiv.workflow.vortex_case import VortexCase, case_camera, case_experiment, run_case

case = VortexCase(flow="oseen", seed=3, response_displacements=DEMO_RESPONSE_DISPLACEMENTS,
                  depth=2e-3, lateral_fill=0.6)
out = Path(tempfile.mkdtemp())
model = Calibration.from_camera(case_camera(case))
for group in P.DEFAULT_CHILDREN:
    for stage in group:
        getattr(P, P.REHEARSALS[stage])(model, case_experiment(case, model, out))


def kernels():
    for name, module in list(sys.modules.items()):
        if name.startswith("plenopiv"):
            for value in vars(module).values():
                if isinstance(value, numba.core.registry.CPUDispatcher):
                    yield f"{value.py_func.__module__}.{value.__name__}", value


before = {name: set(k.signatures) for name, k in kernels()}
run_case(case, out)
gained = sorted({name for name, k in kernels() if set(k.signatures) - before.get(name, set())})
print(json.dumps(gained))
"""


def test_the_rehearsals_compile_every_kernel_of_the_run_but_the_renderer():
    """After the rehearsals, the demo's chain compiles only the renderer's kernels.

    The rehearsals run on the exact calibration, a 16-voxel volume and blobs; the case on a
    measured calibration, its own grid and rendered particles: the same kernels must come out
    with the same argument types, or a first run would compile them again.
    """
    res = subprocess.run([sys.executable, "-c", _AFTER_REHEARSALS], capture_output=True,
                         text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    gained = json.loads(res.stdout.strip().splitlines()[-1])
    assert gained, "the case called no kernel: the check saw nothing"
    assert all(name.startswith("plenopiv.synthetic.") for name in gained), gained


def test_every_stage_of_the_default_children_is_rehearsed_once():
    stages = [s for group in DEFAULT_CHILDREN for s in group]
    assert sorted(stages) == sorted(REHEARSALS)


def test_the_rehearsal_grid_keeps_the_voxels_and_the_centre():
    rng = np.random.default_rng(5)
    for _ in range(20):
        voxel = tuple(rng.uniform(0.05e-3, 0.3e-3, 3))
        shape = tuple(int(n) for n in rng.integers(3, 60, 3))
        grid = VolumeGrid(tuple(rng.uniform(-5e-3, 5e-3, 3)), voxel, shape)
        small = rehearsal_grid(grid, (16, 16, 16))
        assert small.voxel == grid.voxel
        assert small.shape == tuple(min(n, 16) for n in shape)
        np.testing.assert_allclose(small.bounds.mean(axis=1), grid.bounds.mean(axis=1),
                                   atol=1e-12)


def test_blob_volumes_are_float32_blobs_moved_by_the_shift():
    """The second volume is the first moved by the shift, voxel for voxel."""
    a = blob_volume((20, 24, 28), np.random.default_rng(1))
    b = blob_volume((20, 24, 28), np.random.default_rng(1), shift_vox=(1.0, -2.0, 3.0))
    assert a.dtype == np.float32 and 0.9 < a.max() < 3.0
    np.testing.assert_allclose(b[1:, :-2, 3:], a[:-1, 2:, :-3], atol=1e-5)


@pytest.mark.parametrize("grid", ["square", "hexagonal"])
def test_the_spot_image_shows_one_spot_per_lenslet_at_the_camera_pitch(grid):
    """The calibration rehearsal's image is found as the camera would show its lenslets."""
    cam = case_camera(VortexCase())
    cam = cam.replace(microlens_array=replace(cam.microlens_array, grid=grid))
    spots = detect_spots(spot_image(cam), grid=grid)
    pitch = cam.microlens_array.pitch / cam.sensor.pixel_pitch
    assert len(spots.centres_px) >= SPOT_LENSLETS ** 2 - 2 * SPOT_LENSLETS
    nearest = np.sort(np.hypot(*(spots.centres_px[:, None] - spots.centres_px[None]).T), axis=0)[1]
    np.testing.assert_allclose(np.median(nearest), pitch, rtol=0.02)


@pytest.mark.parametrize("fork", [True, False])
def test_a_failed_rehearsal_only_returns_its_exit_status(fork):
    """A child that cannot rehearse exits 1; the run goes on (it compiles what it needs)."""
    cal = Calibration.from_camera(case_camera(VortexCase()))
    with Rehearsals.start(cal, "not an experiment", children=(("piv",),), force=True,
                          fork=fork) as r:
        assert not r.ready("piv", timeout=120)
        assert r.wait(timeout=120) == [1]


@pytest.mark.parametrize("fork", [True, False])
def test_a_stage_is_ready_when_its_rehearsal_is_done_and_the_run_is_paced_by_it(fork):
    """The run waits at the stage's progress report until the child has rehearsed it."""
    cal = Calibration.from_camera(case_camera(VortexCase()))
    seen = []
    with Rehearsals.start(cal, None, children=(("calibration",),), force=True,
                          fork=fork) as r:
        report = r.paced(lambda stage, fraction: seen.append((stage,
                                                              r.rehearsed("calibration"))))
        report("calibration images", 0.5)
        report("calibrate")
        assert not r.ready("piv", timeout=0)            # no child rehearses it
        assert r.wait(timeout=120) == [0]
    assert seen[1] == ("calibrate", True)


@pytest.mark.parametrize("fork", [True, False])
def test_rehearsals_still_running_are_stopped_at_the_end_of_the_block(fork):
    cal = Calibration.from_camera(case_camera(VortexCase()))
    with pytest.raises(RuntimeError), Rehearsals.start(
            cal, "not an experiment", children=(("piv",),), force=True, fork=fork) as r:
        raise RuntimeError("the run failed")
    assert all(p.poll() is not None for p in r.processes)


def test_an_unknown_stage_is_named():
    with pytest.raises(ValueError, match="stage = 'mart'"):
        Rehearsals.start(None, None, children=(("mart",),), force=True)
