"""Simulator benchmark: tracer rays/s, and full-size focal-point and particle images.

Prints figures; it is not a test. Ratios are against the plain-NumPy twin of the tracer run
on the same rays in the same process.

    python benchmarks/bench_simulator.py [--particles 10000] [--rays-per-particle 4096] [--json]
"""

from __future__ import annotations

import argparse
import resource
import sys
import time

import numpy as np

from plenopiv.camera.model import load_camera
from plenopiv.products.jsonio import dumps
from plenopiv.synthetic import _kernels as K
from plenopiv.synthetic.images import focal_point_image, particle_image
from plenopiv.synthetic.tracer import geometry_vector


def peak_rss_gb() -> float:
    """Peak resident memory of this process so far, GB (Linux ru_maxrss is in kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def timed(fn, *args, **kw):
    t = time.perf_counter()
    out = fn(*args, **kw)
    return out, time.perf_counter() - t


def random_image_rays(cam, n, rng):
    r = 0.5 * cam.main_lens.aperture_diameter * np.sqrt(rng.random(n))
    phi = 2 * np.pi * rng.random(n)
    x0, y0 = r * np.cos(phi), r * np.sin(phi)
    w, h = cam.microlens_array.extent
    tx, ty = rng.uniform(-w / 2, w / 2, n), rng.uniform(-h / 2, h / 2, n)
    return x0, y0, np.zeros(n), (tx - x0) / cam.mla_z, (ty - y0) / cam.mla_z


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=10000)
    ap.add_argument("--rays-per-particle", type=int, default=4096)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    cam = load_camera("auburn_135mm")               # full size, 10.4 mm substrate
    rng = np.random.default_rng(0)
    res = {"threads": K.n_threads(), "camera": cam.name}

    # 1. tracer core: numba kernel vs the NumPy twin on the same rays
    g = geometry_vector(cam)
    rays = random_image_rays(cam, 2_000_000, rng)
    K.trace_image_rays(*(a[:10] for a in rays), g)                   # compile / load cache
    _, t_nb = timed(K.trace_image_rays, *rays, g)
    small = tuple(a[:1000] for a in rays)      # the brute-force twin needs N × lenslets memory
    _, t_np = timed(K.trace_image_rays_numpy, *small, g)
    res["trace_mrays_per_s"] = 2e6 / t_nb / 1e6
    res["trace_numpy_mrays_per_s"] = 1e3 / t_np / 1e6
    res["trace_speedup_vs_numpy"] = res["trace_mrays_per_s"] / res["trace_numpy_mrays_per_s"]

    # 2. full-size focal-point image (f/16, default sampling)
    focal_point_image(cam, f_number=16, pupil_across=3, cell_across=1)  # warm-up
    img, t = timed(focal_point_image, cam, f_number=16)
    n_pupil = 177   # symmetric 15-across grid clipped to the disc
    n_rays = cam.microlens_array.count * n_pupil * 4   # 2 × 2 cell samples
    res["focal_point_seconds"] = t
    res["focal_point_mrays_per_s"] = n_rays / t / 1e6
    res["focal_point_peak_rss_gb"] = peak_rss_gb()
    del img

    # 3. full-size particle image
    pts = np.c_[rng.uniform(-35e-3, 35e-3, args.particles), rng.uniform(-24e-3, 24e-3,
                args.particles), rng.uniform(-10e-3, 10e-3, args.particles)]
    particle_image(cam, pts[:20], rays_per_particle=64)               # warm-up
    img, t = timed(particle_image, cam, pts, rays_per_particle=args.rays_per_particle)
    q = int(np.ceil(np.sqrt(args.rays_per_particle)))
    res["particles"] = args.particles
    res["rays_per_particle"] = q * q
    res["particle_image_seconds"] = t
    res["particle_mrays_per_s"] = args.particles * q * q / t / 1e6
    res["particle_image_peak_rss_gb"] = peak_rss_gb()
    res["particle_image_shape"] = list(img.shape)

    if args.json:
        print(dumps(res))
    else:
        for k, v in res.items():
            print(f"{k:32s} {v:.4g}" if isinstance(v, float) else f"{k:32s} {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
