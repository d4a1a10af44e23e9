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
