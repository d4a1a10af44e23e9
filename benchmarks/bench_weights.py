"""Voxel-pixel weights on a real plenoptic geometry: build rate, memory, and one MART / block
pass next to scipy's CSR ``W @ x`` + ``W.T @ y`` on the same matrix in the same run.

    python benchmarks/bench_weights.py [--camera small_m1] [--depth-mm 3] [--json]
    python benchmarks/bench_weights.py --reconstruct smart mart --depth-mm 1

``--reconstruct`` instead prints the bytes held per explicit non-zero during whole
reconstructions (``pipeline.reconstruct_volume``; traced peak, and after loading the weights)
and their CPU time; with ``--peak-site`` also the calls that were running when the traced
peak was reached (where a copy that sets the peak was made).

Prints figures; not a test.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera.model import load_camera
from plenopiv.lightfield import light_field
from plenopiv.products.jsonio import dumps
from plenopiv.reconstruction.mart import reconstruct
from plenopiv.reconstruction.weights import build_weights
from plenopiv.workflow.vortex_case import VortexCase, aligned_grid


def best_of(fn, n=3):
    times = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def _peak_site(fn) -> tuple[float, list[str]]:
    """Run ``fn()`` traced; the traced peak (bytes) and the call stack that reached it.

    ``sys.setprofile`` reads the traced peak at every call and return (Python and C) and
    resets it, so the stack of the event that closes the interval holding the peak is where
    the memory was allocated (innermost first; a temporary inside a C function shows as the
    Python function that called it).
    """
    import sys
    import tracemalloc

    best, last = [0, []], [[]]

    def profile(frame, event, arg):
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        stack, f = [], frame
        while f is not None and len(stack) < 8:
            stack.append(f"{f.f_globals.get('__name__', '?')}.{f.f_code.co_name}:{f.f_lineno}")
            f = f.f_back
        if frame.f_back is None:        # a numba kernel's frame: the Python caller's stack
            stack = stack + last[0]
        else:
            last[0] = stack
        if peak > best[0]:
            best[:] = [peak, stack]

    sys.setprofile(profile)
    try:
        fn()
    finally:
        sys.setprofile(None)
    return best[0], best[1]


def reconstruction_footprint(camera: str, depth_mm: float, method: str, repeats: int = 2,
                             peak_site: bool = False) -> dict:
    """Bytes held per explicit non-zero while a volume is reconstructed, and its CPU time.

    The weights are built once into a temporary cache; then, under ``tracemalloc``, they are
    loaded from it and one image is reconstructed
    (:func:`plenopiv.workflow.volume.reconstruct_volume`, ``method``, no lateral subdivision,
    explicit weights). The traced peak is everything held by NumPy at once: W, any scaled or
    row-selected copies of it, volumes and images (arrays allocated inside numba kernels are not
    traced: the colouring of MART's row schedule, a few bytes per voxel). The CPU time is the best
    of ``repeats`` reconstructions with the weights already loaded.
    """
    import tempfile
    import tracemalloc

    from plenopiv.reconstruction.build import weights_for
    from plenopiv.reconstruction.settings import ReconstructionSettings
    from plenopiv.workflow.volume import reconstruct_volume

    cam = load_camera(camera)
    cal = Calibration.from_camera(cam)
    grid = aligned_grid(cam, VortexCase(depth=depth_mm * 1e-3, lateral_fill=0.85))
    settings = ReconstructionSettings(method=method, lateral_subdivision=1,
                                      projector="sparse", iterations=10)
    rng = np.random.default_rng(1)
    with tempfile.TemporaryDirectory(prefix="bench_weights_") as cache:
        w, _ = weights_for(cal, grid, settings, cache_dir=cache)
        truth = (rng.random(grid.n_voxels) < 0.002).astype(np.float32)
        image = w.forward_image(truth, cam.sensor.shape).astype(np.float64)
        image += 0.01 * float(image.max()) * rng.random(image.shape)
        nnz = w.nnz
        reconstruct_volume(cal, image, grid, settings=settings, weights=w)   # compile
        times = []
        for _ in range(repeats):
            t = time.process_time()
            reconstruct_volume(cal, image, grid, settings=settings, weights=w)
            times.append(time.process_time() - t)
        del w
        tracemalloc.start()
        w, hit = weights_for(cal, grid, settings, cache_dir=cache)
        assert hit
        loaded = tracemalloc.get_traced_memory()[0]
        reconstruct_volume(cal, image, grid, settings=settings, weights=w)
        held_after = tracemalloc.get_traced_memory()[0]
        peak = tracemalloc.get_traced_memory()[1]
        site = None
        if peak_site:
            tracemalloc.reset_peak()
            _, site = _peak_site(lambda: reconstruct_volume(cal, image, grid, settings=settings,
                                                            weights=w))
        tracemalloc.stop()
    out = {"method": method, "grid_shape": list(grid.shape), "nnz": nnz,
           "bytes_per_nnz_loaded": loaded / nnz, "bytes_per_nnz_peak": peak / nnz,
           "bytes_per_nnz_held_after": held_after / nnz,
           "reconstruct_cpu_s": min(times)}
    if site is not None:
        out["peak_site"] = site
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--camera", default="small_m1")
    ap.add_argument("--depth-mm", type=float, default=3.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--reconstruct", nargs="*", metavar="METHOD",
                    help="instead: bytes held per non-zero and CPU time of whole "
                         "reconstructions (pipeline.reconstruct_volume) with these methods "
                         "(default smart mart)")
    ap.add_argument("--peak-site", action="store_true",
                    help="with --reconstruct: also the call stack at the traced peak")
    a = ap.parse_args(argv)
    if a.reconstruct is not None:
        for method in a.reconstruct or ["smart", "mart"]:
            r = reconstruction_footprint(a.camera, a.depth_mm, method,
                                         peak_site=a.peak_site)
            print(dumps(r) if a.json else
                  "  ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                            for k, v in r.items()), flush=True)
        return
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
    reconstruct(img, norm, method="block", iterations=1, relaxation=1.0,
                blocks=blocks)  # compile, schedules
    reconstruct(img, norm, method="mart", iterations=1, relaxation=1.0)
    t_block = best_of(lambda: reconstruct(img, norm, method="block", iterations=1, relaxation=1.0,
                                          blocks=blocks), 2)
    t_mart = best_of(lambda: reconstruct(img, norm, method="mart", iterations=1,
                                         relaxation=1.0), 2)
    t_first = best_of(lambda: reconstruct(img, norm, method="mart", iterations=0,
                                           relaxation=1.0), 2)
    mnnz = p.nnz / 1e6
    res.update({"scipy_forward_back_ms_per_mnnz": t_scipy * 1e3 / mnnz,
                "block_pass_ms_per_mnnz": (t_block - t_first) * 1e3 / mnnz,
                "mart_pass_ms_per_mnnz": (t_mart - t_first) * 1e3 / mnnz,
                "first_guess_ms_per_mnnz": t_first * 1e3 / mnnz})
    res["block_over_scipy"] = res["block_pass_ms_per_mnnz"] / res["scipy_forward_back_ms_per_mnnz"]
    res["mart_over_scipy"] = res["mart_pass_ms_per_mnnz"] / res["scipy_forward_back_ms_per_mnnz"]
    if a.json:
        print(dumps(res))
    else:
        for k, v in res.items():
            print(f"{k:34s} {v:.4g}" if isinstance(v, float) else f"{k:34s} {v}")


if __name__ == "__main__":
    main()
