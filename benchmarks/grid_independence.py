"""Particle-field quality on the grid a user types against the footprint-aligned grid.

Not a unit test. Run ``python benchmarks/grid_independence.py [--density 0.3 --json]``;
``--spread`` for how far single particles move over random sub-voxel grids
(:func:`spread_study`); ``--single`` for the single-particle table: the thesis §5.1 camera
cut to 61 × 61 lenslets (one on the axis), one on-axis particle at Z = -5 … +3 mm (Poisson
noise, 50 counts peak), on the grid a user types (``x_mm = y_mm = [-3, 3]``,
``z_mm = [-7.5, 7.5]``, ``voxel_mm = 0.125``: voxel edges through the lenslet centres) and on
the same grid moved by half a voxel.

The field-quality camera (Auburn 16 MP optics, 50 mm lens at M = -1, 61 × 91-lenslet patch,
f/2.2) records one particle field; it is reconstructed with the library's defaults
(``ReconstructionSettings()``, matrix-free lattice projector) on two grids of the same voxels
(0.125 × 0.125 × 0.25 mm):

- ``aligned``: :func:`pipelines.studies.field_quality.study_grid`, voxel edges on the
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
import sys
import time
from pathlib import Path

import numpy as np

# the repository root, so that pipelines.studies imports from a clone without installing it
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.studies import field_quality as fq
from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.resolution import resolution_cell
from plenopiv.products.jsonio import dumps
from plenopiv.reconstruction.build import cached_weights
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.workflow.volume import reconstruct_volume


def single_particles() -> dict:
    from pipelines.studies.depth import STUDY_PARTICLES, thesis_camera
    from plenopiv.synthetic.images import particle_image

    cam = thesis_camera(lenslets=61, sensor_px=1040)
    cal = Calibration.from_camera(cam)
    out = {}
    for name, h in (("typed ±3 mm", 3.0e-3), ("moved ±3.0625 mm", 3.0625e-3)):
        grid = VolumeGrid.from_bounds((-h, h), (-h, h), (-7.5e-3, 7.5e-3), voxel=0.125e-3)
        w, _ = cached_weights(cal, grid, cache_dir=None, projector="lattice")
        rows = []
        for z in (-5, -3, -2, -1, 0, 1, 2, 3):
            img = particle_image(cam, [(0.0, 0.0, z * 1e-3)], rays_per_particle=20000, seed=0)
            img = np.random.default_rng(1).poisson(img * 50 / img.max()).astype(np.float32)
            r = reconstruct_volume(cal, img, grid, weights=w, particles=STUDY_PARTICLES)
            p = r.particle_position_effective[int(np.argmax(r.particle_intensity))]
            rows.append({"z_mm": z, "found_z_mm": round(p[2] * 1e3, 3),
                         "lateral_vox": round(float(np.abs(p[:2]).max() / grid.voxel[0]), 3),
                         "n_particles": len(r.particle_intensity)})
        out[name] = rows
        print(name, " ".join(f"{q['z_mm']:+d}:{q['found_z_mm']:+.3f}" for q in rows),
              flush=True)
    return out


#: Single particles of the spread study: (lenslets, (x, y, z) metres). 15 lenslets put one on
#: the axis, 16 put lenslet edges there; 0.125 mm is the footprint of the thesis camera.
SPREAD_CASES = ((15, (0.0, 0.0, 0.0)), (15, (0.0, 0.0, 0.4e-3)), (15, (0.0, 0.0, -0.8e-3)),
                (16, (0.3 * 0.125e-3 + 62.5e-6, -0.2 * 0.125e-3 - 62.5e-6, 0.0)),
                (16, (62.5e-6, 62.5e-6, 0.4e-3)),
                (16, (0.3 * 0.125e-3 + 62.5e-6, 62.5e-6, 0.4e-3)),
                (15, (0.2 * 0.125e-3, -0.35 * 0.125e-3, 1.5e-3)))


def spread_study(grids_per_size: int = 4, seed: int = 20261202) -> list[dict]:
    """How far one particle's position moves when only the voxel grid moves.

    Each case's image (thesis §5.1 camera cut to 15 or 16 lenslets, Poisson noise) is
    reconstructed on ``grids_per_size`` grids with random sub-voxel origins for each voxel
    size of 0.5, 1 and 1.5 footprints; spread = largest minus smallest over all those grids of
    the brightest particle's position (light field, the default) and of the volume's
    centroid, laterally in footprints (per voxel size, in voxels) and in depth cells.
    """
    import math

    from pipelines.studies.depth import thesis_camera
    from plenopiv.camera.resolution import footprint
    from plenopiv.synthetic.images import particle_image

    rng = np.random.default_rng(seed)
    rows = []
    for lenslets, truth in SPREAD_CASES:
        cam = thesis_camera(lenslets=lenslets,
                            sensor_px=int(math.ceil(lenslets * 125 / 7.4)) + 4)
        cal = Calibration.from_camera(cam)
        b = footprint(cal.effective_camera)
        _, cell = resolution_cell(cal.effective_camera)
        img = particle_image(cam, [truth], rays_per_particle=20000, seed=3)
        img = np.random.default_rng(4).poisson(img * 50 / img.max()).astype(np.float32)
        found = {"position": [], "centroid": []}
        per_size = {}
        for size in (0.5, 1.0, 1.5):
            v = size * b
            start = len(found["position"])
            for _ in range(grids_per_size):
                s = rng.uniform(-0.5, 0.5, 3) * v
                grid = VolumeGrid.from_bounds(*[(t - h + o, t + h + o) for t, h, o in zip(
                    truth, (5 * b, 5 * b, 2.5e-3), s, strict=True)], voxel=v)
                w, _ = cached_weights(cal, grid, cache_dir=None, projector="lattice")
                r = reconstruct_volume(cal, img, grid, weights=w)
                k = int(np.argmax(r.particle_intensity))
                found["position"].append(r.particle_position_effective[k])
                found["centroid"].append(r.particle_centroid_effective[k])
            per_size[size] = slice(start, len(found["position"]))
        row = {"lenslets": lenslets, "truth_mm": [round(t * 1e3, 4) for t in truth]}
        for label, ps in found.items():
            ps = np.array(ps)
            spread = ps.max(0) - ps.min(0)
            err = ps - np.array(truth)
            row[label] = {
                "lateral_spread_fp": float(spread[:2].max() / b),
                "lateral_spread_vox": {str(sz): float(np.ptp(ps[sl, :2], axis=0).max()
                                                      / (sz * b))
                                       for sz, sl in per_size.items()},
                "depth_spread_cells": float(spread[2] / cell),
                "mean_error_fp": [float(e) for e in err.mean(0)[:2] / b],
                "mean_error_cells": float(err.mean(0)[2] / cell)}
        rows.append(row)
        print(f"{lenslets} lenslets, particle at {row['truth_mm']} mm: " + "; ".join(
            f"{k} spread {row[k]['lateral_spread_fp']:.3f} fp, "
            f"{row[k]['depth_spread_cells']:.3f} cells, error "
            f"{row[k]['mean_error_cells']:+.2f} cells" for k in found), flush=True)
    return rows


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--density", type=float, default=0.3, help="particles per lenslet")
    ap.add_argument("--seed", type=int, default=20261122)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--single", action="store_true", help="the single-particle table instead")
    ap.add_argument("--spread", action="store_true",
                    help="how far single particles move over random sub-voxel grids instead")
    a = ap.parse_args(argv)
    if a.spread:
        rows = spread_study()
        if a.json:
            print(dumps(rows))
        return {"spread": rows}
    if a.single:
        out = single_particles()
        if a.json:
            print(dumps(out))
        return out
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
    found = {}
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
        found[name] = res
        print(f"{name}: {grid.shape} " + ", ".join(
            f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
            for k, v in out[name].items()), flush=True)
    out["moved"] = moved_between(found["aligned"], found["typed"], (lat, lat, dep))
    print("the same particles on the two grids, |position difference| median / 90th "
          "percentile (lateral in footprints, depth in cells): " + "; ".join(
              f"{k}: {v['lateral_median']:.3f} / {v['lateral_p90']:.3f} fp, "
              f"{v['depth_median']:.3f} / {v['depth_p90']:.3f} cells ({v['n']} pairs)"
              for k, v in out["moved"].items()), flush=True)
    if a.json:
        print(dumps(out))
    return out


def moved_between(first, second, cell) -> dict:
    """How far the particles found in both of two reconstructions of one image moved.

    Particles are paired when they lie within half a resolution cell of each other (mutual
    nearest neighbours); lateral distances in footprints (``cell[0]``), depth in depth cells.
    Both the reported positions and the volume centroids (where the positions came from the
    light field).
    """
    from scipy.spatial import cKDTree

    scale = np.asarray(cell, float)
    out = {}
    for label in ("position", "centroid"):
        p = [getattr(r, "particle_centroid_effective" if label == "centroid"
                     else "particle_position_effective") for r in (first, second)]
        if p[0] is None or p[1] is None:
            continue
        a, b = p[0] / scale, p[1] / scale
        d_ab, i_ab = cKDTree(b).query(a)
        _, i_ba = cKDTree(a).query(b)
        pair = (d_ab < 0.5) & (i_ba[i_ab] == np.arange(len(a)))
        diff = np.abs(a[pair] - b[i_ab[pair]])
        lateral, depth = diff[:, :2].max(axis=1), diff[:, 2]
        out[label] = {"n": int(pair.sum()),
                      "lateral_median": float(np.median(lateral)),
                      "lateral_p90": float(np.percentile(lateral, 90)),
                      "depth_median": float(np.median(depth)),
                      "depth_p90": float(np.percentile(depth, 90))}
    return out


if __name__ == "__main__":
    main()
