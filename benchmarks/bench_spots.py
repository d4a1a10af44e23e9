"""Benchmark: lenslet spot detection and lattice fit on a full-size focal-point image.

Synthesises a 3280 x 4904 px focal-point-like image of the Auburn camera (193 x 287 lenslets
at 16.89 px pitch, Gaussian spots of about 3 px FWHM, Poisson and read noise), then times
:func:`plenopiv.calibration.spots.detect_spots` + :func:`fit_lattice` and a simple baseline
(``scipy.ndimage.label`` + ``center_of_mass`` on a thresholded image) in the same process.

Prints wall time, spots per second, peak traced memory and the centre error against the
known positions. Target: detect + fit in at most 10 s on 2 cores. Not a unit test.

Usage::

    python benchmarks/bench_spots.py [--cores 2] [--repeat 3] [--seed 0]
"""

from __future__ import annotations

import argparse
import os
import resource
import time
import tracemalloc

import numpy as np
from scipy import ndimage as ndi
from scipy.spatial import cKDTree

from plenopiv.calibration.spots import detect_spots, fit_lattice

SHAPE = (3280, 4904)  # sensor rows, cols (px)
LENSLETS = (193, 287)  # lattice rows, cols
PITCH_PX = 16.89
SPOT_SIGMA_PX = 1.3  # FWHM = 2.355 * sigma, about 3 px
ROTATION_RAD = 1.5e-3
PEAK_PHOTONS = 2000.0
READ_NOISE = 5.0
DARK = 100.0


def synthesise(rng):
    """Focal-point image (uint16) and the true spot centres ``(row, col)`` px."""
    i, j = np.meshgrid(np.arange(LENSLETS[0]), np.arange(LENSLETS[1]), indexing="ij")
    c, s = np.cos(ROTATION_RAD), np.sin(ROTATION_RAD)
    e_col = PITCH_PX * np.array([s, c])  # (d_row, d_col) of one column step
    e_row = PITCH_PX * np.array([c, -s])
    extent = (LENSLETS[0] - 1) * e_row + (LENSLETS[1] - 1) * e_col
    origin = (np.array(SHAPE) - 1 - extent) / 2.0 + rng.uniform(-0.5, 0.5, 2)
    centres = origin + i.reshape(-1, 1) * e_row + j.reshape(-1, 1) * e_col
    centres += rng.normal(0.0, 0.05, centres.shape)  # lenslet placement scatter
    # render each spot in an 11 x 11 patch, integrated over the pixel area
    half = 5
    base = np.rint(centres).astype(np.int64)
    off = np.arange(-half, half + 1)
    from scipy.special import erf

    def pixel_integral(d):  # d: pixel centre minus spot centre, (N, 11)
        a = (d + 0.5) / (np.sqrt(2.0) * SPOT_SIGMA_PX)
        b = (d - 0.5) / (np.sqrt(2.0) * SPOT_SIGMA_PX)
        return 0.5 * (erf(a) - erf(b))

    pr = pixel_integral(base[:, 0, None] + off[None, :] - centres[:, 0, None])
    pc = pixel_integral(base[:, 1, None] + off[None, :] - centres[:, 1, None])
    flux = PEAK_PHOTONS * 2.0 * np.pi * SPOT_SIGMA_PX**2
    patch = flux * pr[:, :, None] * pc[:, None, :]
    rows = base[:, 0, None, None] + off[None, :, None]
    cols = base[:, 1, None, None] + off[None, None, :]
    rows, cols = np.broadcast_arrays(rows, cols)
    inside = (rows >= 0) & (rows < SHAPE[0]) & (cols >= 0) & (cols < SHAPE[1])
    expected = np.zeros(SHAPE)
    np.add.at(expected, (rows[inside], cols[inside]), patch[inside])
    image = rng.poisson(expected) + DARK + rng.normal(0.0, READ_NOISE, SHAPE)
    return np.clip(np.rint(image), 0, 65535).astype(np.uint16), centres


def baseline(image):
    """Threshold at half the robust maximum, label, centre of mass of each label."""
    img = image.astype(np.float32) - np.median(image)
    level = 0.5 * np.percentile(img, 99.9)
    labels, n = ndi.label(img > level)
    return np.array(ndi.center_of_mass(img, labels, np.arange(1, n + 1)))


def timed(fn, *args, **kwargs):
    """Run ``fn`` under tracemalloc; return its result, seconds and peak traced bytes."""
    tracemalloc.start()
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    dt = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return out, dt, peak


def errors(found, truth, pitch):
    d, i = cKDTree(found).query(truth)
    ok = d < pitch / 4
    e = found[i[ok]] - truth[ok]
    return int(ok.sum()), np.sqrt(np.mean(e**2, axis=0)), e.mean(axis=0)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--cores", type=int, default=2, help="pin the process to this many cores (Linux)"
    )
    ap.add_argument("--repeat", type=int, default=3, help="timed repetitions (best is reported)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.cores and hasattr(os, "sched_setaffinity"):
        avail = sorted(os.sched_getaffinity(0))
        os.sched_setaffinity(0, set(avail[: args.cores]))
    ncores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()

    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    image, truth = synthesise(rng)
    print(
        f"synthesised {image.shape[0]} x {image.shape[1]} uint16 image, {len(truth)} spots "
        f"in {time.perf_counter() - t0:.1f} s; running on {ncores} core(s)"
    )

    # compile / load the numba kernels outside the timing
    t0 = time.perf_counter()
    detect_spots(image[:400, :400], expected_pitch_px=PITCH_PX)
    print(f"numba warm-up (small image): {time.perf_counter() - t0:.2f} s")

    best = None
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        spots = detect_spots(image)
        t1 = time.perf_counter()
        lattice = fit_lattice(spots)
        t2 = time.perf_counter()
        if best is None or t2 - t0 < best[0]:
            best = (t2 - t0, t1 - t0, t2 - t1, spots, lattice)
    total, t_detect, t_fit, spots, lattice = best
    # memory in a separate run: tracemalloc slows every allocation down
    _, _, mem_detect = timed(detect_spots, image)
    _, _, mem_fit = timed(fit_lattice, spots)
    n = len(spots)
    print(f"detect_spots:  {t_detect:6.2f} s   peak traced memory {mem_detect / 2**20:7.1f} MiB")
    print(f"fit_lattice:   {t_fit:6.2f} s   peak traced memory {mem_fit / 2**20:7.1f} MiB")
    print(f"total:         {total:6.2f} s   {n / total:,.0f} spots/s   (target <= 10 s on 2 cores)")
    print(
        f"found {n} spots ({np.count_nonzero(spots.complete)} complete), lattice "
        f"{lattice.shape[0]} x {lattice.shape[1]} {lattice.grid}, pitch "
        f"{lattice.pitch_px[0]:.4f} / {lattice.pitch_px[1]:.4f} px (true {PITCH_PX}), rotation "
        f"{lattice.rotation_rad * 1e3:.4f} mrad (true {ROTATION_RAD * 1e3}), "
        f"rms residual {lattice.rms_residual_px:.4f} px, missing {lattice.n_missing}"
    )
    m, rms, bias = errors(spots.centres_px[lattice.inlier], truth, PITCH_PX)
    print(
        f"centre error vs truth ({m} matched): rms {rms[0]:.4f} / {rms[1]:.4f} px, "
        f"bias {bias[0]:+.4f} / {bias[1]:+.4f} px"
    )

    t0 = time.perf_counter()
    base = baseline(image)
    t_base = time.perf_counter() - t0
    _, _, mem_base = timed(baseline, image)
    mb, rms_b, bias_b = errors(base, truth, PITCH_PX)
    print(
        f"baseline label + center_of_mass: {t_base:6.2f} s, {len(base)} labels, peak traced memory "
        f"{mem_base / 2**20:.1f} MiB; error ({mb} matched) rms {rms_b[0]:.4f} / {rms_b[1]:.4f} px"
    )
    print(f"ratio detect+fit / baseline: {total / t_base:.2f}")
    print(f"process max RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10:.0f} MiB")


if __name__ == "__main__":
    main()
