"""Voxel-pixel weights on a real plenoptic geometry: build rate, memory, and one MART / block
pass next to scipy's CSR ``W @ x`` + ``W.T @ y`` on the same matrix in the same run.

    python benchmarks/bench_weights.py [--camera small_m1] [--depth-mm 3] [--json]

Prints figures; not a test.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera import load_camera
from plenopiv.lightfield import light_field
from plenopiv.reconstruction.mart import reconstruct
from plenopiv.reconstruction.weights import build_weights
from plenopiv.validation.vortex import VortexCase, aligned_grid


def best_of(fn, n=3):
    times = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--camera", default="small_m1")
    ap.add_argument("--depth-mm", type=float, default=3.0)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    cam = load_camera(a.camera)
    cal = Calibration.from_camera(cam)
    grid = aligned_grid(cam, VortexCase(depth=a.depth_mm * 1e-3, lateral_fill=0.85))
    lf = light_field(cal)
    build_weights(lf, aligned_grid(cam, VortexCase(depth=0.3e-3, lateral_fill=0.1)))  # compile
    t = time.perf_counter()
    w = build_weights(lf, grid)
    t_build = time.perf_counter() - t
    p = w.projector
    res = {"camera": cam.name, "grid_shape": list(grid.shape), "n_rows": p.n_pixels,
           "nnz": p.nnz, "build_s": t_build, "build_mnnz_per_s": p.nnz / t_build / 1e6,
           "bytes_per_mnnz": p.nbytes / p.nnz * 1e6 if hasattr(p, "nbytes") else None}
    m = p.to_scipy().tocsr()
    rng = np.random.default_rng(0)
    x = rng.random(p.n_voxels).astype(np.float32)
    y = rng.random(p.n_pixels).astype(np.float32)
    t_scipy = best_of(lambda: (m @ x, m.T @ y))
    norm, scale = w.normalised
    # a sparse particle-like volume (0.2 % of the voxels lit) projected to an image
    truth = (rng.random(p.n_voxels) < 0.002).astype(np.float32)
    img = ((m @ truth) / scale).astype(np.float32)
    blocks = (np.arange(p.n_pixels) % 64).astype(np.int64)
    reconstruct(img, norm, method="block", iterations=1, blocks=blocks)  # compile, schedules
    reconstruct(img, norm, method="mart", iterations=1)
    t_block = best_of(lambda: reconstruct(img, norm, method="block", iterations=1,
                                          blocks=blocks), 2)
    t_mart = best_of(lambda: reconstruct(img, norm, method="mart", iterations=1), 2)
    t_first = best_of(lambda: reconstruct(img, norm, method="mart", iterations=0), 2)
    mnnz = p.nnz / 1e6
    res.update({"scipy_forward_back_ms_per_mnnz": t_scipy * 1e3 / mnnz,
                "block_pass_ms_per_mnnz": (t_block - t_first) * 1e3 / mnnz,
                "mart_pass_ms_per_mnnz": (t_mart - t_first) * 1e3 / mnnz,
                "first_guess_ms_per_mnnz": t_first * 1e3 / mnnz})
    res["block_over_scipy"] = res["block_pass_ms_per_mnnz"] / res["scipy_forward_back_ms_per_mnnz"]
    res["mart_over_scipy"] = res["mart_pass_ms_per_mnnz"] / res["scipy_forward_back_ms_per_mnnz"]
    if a.json:
        print(json.dumps(res))
    else:
        for k, v in res.items():
            print(f"{k:34s} {v:.4g}" if isinstance(v, float) else f"{k:34s} {v}")


if __name__ == "__main__":
    main()
