"""Throughput of plenopiv.piv against a plain batched-FFT cross-correlation baseline.

Run: ``python benchmarks/bench_piv.py [--size 128] [--window 32] [--overlap 0.5] [--repeat 5]``

Both run in this process on the same two synthetic particle volumes (Gaussian blobs moved by
a known uniform shift). Figures are vectors per second per pass (best of ``--repeat``):

- baseline: cut every window pair out (float64, means removed), ``scipy.fft.fftn`` of both,
  complex multiply, ``ifftn``, ``argmax`` of the real part: an integer peak, no sub-voxel fit,
  no signal-to-noise ratio, no validation, one thread. This is the straightforward code.
- baseline (float32): the same in single precision (complex64), to separate the gain of the
  precision from the rest.
- plenopiv pass: one pass of ``correlate_volumes`` (window cutting, rfftn on all cores, peak
  search with 3-point Gaussian fit and peak ratio, median test and replacement, VectorField).
- plenopiv WIDIM pass: the mean time of a pass of a 3-pass run with window deformation (cubic
  B-spline deformation of both volumes included).

Wall-clock figures on a machine shared with other work vary a lot; the CPU time of the
single-threaded runs (``cpu s``) is the steadier comparison there. Nothing here is asserted;
the numbers are printed.
"""

from __future__ import annotations

import argparse
import os
import time
from types import SimpleNamespace

import numpy as np
import scipy.fft

from plenopiv.piv import PIVSettings, correlate_volumes
from plenopiv.piv.windows import _window_layout


def render(shape, positions, sigma, rng):
    """Sum of Gaussian blobs (peak 0.5..1) at ``positions`` (N, 3) ``(z, y, x)`` voxels."""
    vol = np.zeros(shape)
    sigma = np.asarray(sigma, dtype=float)
    reach = np.ceil(4 * sigma).astype(int)
    peaks = rng.uniform(0.5, 1.0, len(positions))
    for p, peak in zip(positions, peaks, strict=True):
        c = np.rint(p).astype(int)
        lo = np.maximum(c - reach, 0)
        hi = np.minimum(c + reach + 1, shape)
        if np.any(hi <= lo):
            continue
        g = [np.exp(-0.5 * ((np.arange(lo[a], hi[a]) - p[a]) / sigma[a]) ** 2) for a in range(3)]
        vol[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] += (
            peak * g[0][:, None, None] * g[1][None, :, None] * g[2][None, None, :]
        )
    return vol.astype(np.float32)


def volumes(size, shift, seed=0, density=0.01):
    rng = np.random.default_rng(seed)
    shape = (size,) * 3
    margin = 10
    n = int(density * (size + 2 * margin) ** 3)
    pos = rng.uniform(-margin, size - 1 + margin, size=(n, 3))
    state = rng.bit_generator.state
    a = render(shape, pos, (1.0, 1.0, 1.0), rng)
    rng.bit_generator.state = state  # the same peak intensities for the moved particles
    b = render(shape, pos + np.asarray(shift), (1.0, 1.0, 1.0), rng)
    return a, b


def baseline_pass(vol_a, vol_b, window, overlap, dtype):
    """Straightforward batched FFT correlation: integer displacement per window (voxels)."""
    layout = _window_layout(vol_a.shape, window, overlap)
    starts = layout.all_starts()
    wz, wy, wx = window
    wa = np.stack([vol_a[z : z + wz, y : y + wy, x : x + wx] for z, y, x in starts]).astype(dtype)
    wb = np.stack([vol_b[z : z + wz, y : y + wy, x : x + wx] for z, y, x in starts]).astype(dtype)
    wa -= wa.mean(axis=(1, 2, 3), keepdims=True)
    wb -= wb.mean(axis=(1, 2, 3), keepdims=True)
    fa = scipy.fft.fftn(wa, axes=(1, 2, 3))
    fb = scipy.fft.fftn(wb, axes=(1, 2, 3))
    corr = scipy.fft.ifftn(np.conj(fa) * fb, axes=(1, 2, 3)).real
    peak = np.argmax(corr.reshape(len(starts), -1), axis=1)
    idx = np.stack(np.unravel_index(peak, window), axis=1)
    w = np.asarray(window)
    return np.where(2 * idx >= w, idx - w, idx)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128, help="volume edge, voxels")
    parser.add_argument("--window", type=int, default=32, help="window edge, voxels")
    parser.add_argument("--overlap", type=float, default=0.5)
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()

    shift = np.array([2.3, -1.7, 3.1])
    vol_a, vol_b = volumes(args.size, shift)
    grid = SimpleNamespace(origin=(0.0, 0.0, 0.0), voxel_size=1.0)
    window = (args.window,) * 3
    n_vec = int(np.prod(_window_layout(vol_a.shape, window, args.overlap).shape))
    one_pass = PIVSettings(windows=window, overlap=args.overlap, passes=1)
    widim = PIVSettings(windows=window, overlap=args.overlap, passes=3)

    # warm-up: numba compilation and FFT plans are not what we measure
    correlate_volumes(vol_a, vol_b, grid, settings=widim)
    baseline_pass(vol_a, vol_b, window, args.overlap, np.float64)

    # interleaved repeats, best of each: on a shared machine every method sees the same load
    runs = {
        "base64": lambda: baseline_pass(vol_a, vol_b, window, args.overlap, np.float64),
        "base32": lambda: baseline_pass(vol_a, vol_b, window, args.overlap, np.float32),
        "one": lambda: correlate_volumes(vol_a, vol_b, grid, settings=one_pass),
        "one_1": lambda: correlate_volumes(vol_a, vol_b, grid, settings=one_pass, workers=1),
        "widim": lambda: correlate_volumes(vol_a, vol_b, grid, settings=widim),
    }
    times = {name: [] for name in runs}
    cpu = {name: [] for name in runs}
    results = {}
    load_before = os.getloadavg()[0]
    for _ in range(args.repeat):
        for name, fn in runs.items():
            t0, c0 = time.perf_counter(), time.process_time()
            results[name] = fn()
            times[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)
    load_after = os.getloadavg()[0]
    t_base, t_base32, t_one, t_one_1, t_widim = (min(times[k]) for k in runs)
    d_base, f_one, f_widim = results["base64"], results["one"], results["widim"]
    t_widim_pass = t_widim / widim.passes

    def interior_error(field):
        est = np.stack([field.w, field.v, field.u])[:, 1:-1, 1:-1, 1:-1].reshape(3, -1)
        return np.abs(est - shift[:, None]).mean(axis=1)

    err_base = np.abs(d_base - shift).mean(axis=0)
    print(
        f"volume {vol_a.shape} float32, windows {window}, overlap {args.overlap}, "
        f"{n_vec} vectors per pass, true shift (z, y, x) {shift}"
    )
    print(
        f"{os.cpu_count()} cores, 1-min load average {load_before:.2f} before, "
        f"{load_after:.2f} after; best of {args.repeat} interleaved repeats"
    )
    header = f"{'method':<34}{'s/pass':>10}{'vectors/s':>12}{'x baseline':>12}{'cpu s':>10}"
    print(f"{header}   mean |error| (z, y, x) vox")
    rows = [
        ("baseline fftn float64, 1 thread", t_base, min(cpu["base64"]), err_base),
        ("baseline fftn float32, 1 thread", t_base32, min(cpu["base32"]), None),
        ("plenopiv pass, workers=1", t_one_1, min(cpu["one_1"]), None),
        ("plenopiv pass, all cores", t_one, None, interior_error(f_one)),
        ("plenopiv WIDIM pass (3 passes)", t_widim_pass, None, interior_error(f_widim)),
    ]
    for name, t, c, err in rows:
        err_s = "" if err is None else np.array2string(err, precision=3)
        c_s = f"{c:>10.4f}" if c is not None else f"{'':>10}"
        print(f"{name:<34}{t:>10.4f}{n_vec / t:>12.0f}{t_base / t:>12.2f}{c_s}   {err_s}")
    print(
        f"speed-up of one plenopiv pass over the float64 baseline: {t_base / t_one:.2f}x wall, "
        f"all cores ({t_base32 / t_one:.2f}x over the float32 baseline); single-threaded: "
        f"{t_base / t_one_1:.2f}x wall, {min(cpu['base64']) / min(cpu['one_1']):.2f}x CPU time"
    )


if __name__ == "__main__":
    main()
