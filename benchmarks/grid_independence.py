"""Particle-field quality on the grid a user types against the footprint-aligned grid.

Not a unit test. Run ``python benchmarks/grid_independence.py [--density 0.3 --json]``.

The field-quality camera (Auburn 16 MP optics, 50 mm lens at M = -1, 61 × 91-lenslet patch,
f/2.2) records one particle field; it is reconstructed with the library's defaults
(``ReconstructionSettings()``, matrix-free lattice projector) on two grids of the same voxels
(0.125 × 0.125 × 0.25 mm):

- ``aligned``: :func:`plenopiv.validation.field_quality.study_grid`, voxel edges on the
  lenslet boundaries (each voxel column is one lenslet's footprint);
- ``typed``: ``x_mm = [-5.5, 5.5]``, ``y_mm = [-3.75, 3.75]``, ``z_mm = [-6, 6]``: with an
  odd lenslet count a lenslet sits on the axis, so these voxel edges run through the lenslet
  centres and every voxel straddles four lenslets.

Per grid it prints Q (against Gaussian blobs of the resolution cell), the detection and ghost
rates (matches inside the resolution cell, :func:`field_quality.score`) and the time, inside
each grid's interior (the blur radius of the deepest particle from its lateral edges).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.config import ReconstructionSettings
from plenopiv.pipeline import reconstruct_volume, resolution_cell
from plenopiv.validation import field_quality as fq
from plenopiv.volume import VolumeGrid
from plenopiv.weights import cached_weights


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--density", type=float, default=0.3, help="particles per lenslet")
    ap.add_argument("--seed", type=int, default=20261122)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    cam = fq.study_camera()
    cal = Calibration.from_camera(cam)
    aligned = fq.study_grid(cam)
    typed = VolumeGrid.from_bounds((-5.5e-3, 5.5e-3), (-3.75e-3, 3.75e-3), (-6e-3, 6e-3),
                                   voxel=(0.125e-3, 0.125e-3, 0.25e-3))
    rng = np.random.default_rng(a.seed)
    pos = fq.seed_field(typed, cam, a.density, rng)
    img = fq.render(cam, pos, seed=a.seed)
    lat, dep = resolution_cell(cam)
    settings = ReconstructionSettings()
    out = {"density_ppl": a.density, "n_particles": int(len(pos))}
    for name, grid in (("aligned", aligned), ("typed", typed)):
        t0 = time.perf_counter()
        w, _ = cached_weights(cal, grid, cache_dir=None, projector="lattice")
        res = reconstruct_volume(cal, img, grid, settings=settings,
                                 particles=fq.particle_settings(grid, cam), weights=w)
        row = fq.score(res, pos, tolerance=(lat, lat, dep),
                       sigmas={"cell": fq.cell_sigma(grid, cam)},
                       region=fq.Region(grid, fq.interior_margin(cam)))
        out[name] = {"q_cell": row["q"]["cell"], "detection": row["detection_rate"],
                     "ghosts": row["ghost_rate"], "n_true": row["n_true"],
                     "n_found": row["n_found"]}
        out[name]["seconds"] = round(time.perf_counter() - t0, 1)
        print(f"{name}: {grid.shape} " + ", ".join(
            f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
            for k, v in out[name].items()), flush=True)
    if a.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
