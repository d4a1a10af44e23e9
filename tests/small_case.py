"""The small case the CLI, provenance and lock tests share: a box of the small_m1 camera and
a sparse simulated pair in it (seconds to reconstruct and correlate)."""

from __future__ import annotations

#: The ``[volume]`` table: ±1.06 mm laterally, ±1.5 mm in depth, footprint voxels.
VOLUME = """[volume]
x_mm = [-1.0625, 1.0625]
y_mm = [-1.0625, 1.0625]
z_mm = [-1.5, 1.5]
voxel_mm = 0.125
"""


def simulate_pair_argv(out, *, seed: int, n_particles: int = 30) -> list[str]:
    """``plenopiv simulate pair`` arguments of a sparse pair inside :data:`VOLUME` (no TIFFs)."""
    return ["simulate", "pair", "small_m1", "--n-particles", str(n_particles),
            "--rays-per-particle", "256", "--depth-mm", "-1.5", "1.5", "--fill", "0.4",
            "--seed", str(seed), "--no-tiff", "--out", str(out)]


def volume_script(*, n_particles: int, seed: int) -> str:
    """Python source that renders a still pair of ``n_particles`` in the demo's box of the
    small_m1 camera and reconstructs exposure A as ``r`` (a VolumeResult), for the tests that
    run it in a process of their own (memory is per process). ``np`` and ``sys`` are
    imported."""
    return f"""
import sys
import numpy as np
from plenopiv.calibration.model import Calibration
from plenopiv.camera.model import load_camera
from plenopiv.synthetic.flows import Uniform
from plenopiv.synthetic.seeding import SeedingBox, simulate_pair
from plenopiv.workflow.volume import reconstruct_volume
from plenopiv.workflow.vortex_case import VortexCase, aligned_grid
cam = load_camera("small_m1")
grid = aligned_grid(cam, VortexCase())
b = grid.bounds
pair = simulate_pair(cam, Uniform((0.0, 0.0, 0.0)), dt=1e-3,
                     box=SeedingBox(tuple(b[0]), tuple(b[1]), tuple(b[2])),
                     n_particles={n_particles}, rng=np.random.default_rng({seed}),
                     rays_per_particle=256)
r = reconstruct_volume(Calibration.from_camera(cam), np.asarray(pair.image_a, float), grid)
"""
