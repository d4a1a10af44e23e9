"""Time MART passes on a plenoptic-like sparse weight matrix, next to scipy's CSR products.

Not a unit test. Run ``python benchmarks/bench_mart.py [--lenslets 35 --directions 10
--nz 64 --voxels-per-lenslet 2 --particles 0.002 --repeat 5]``; ``NUMBA_NUM_THREADS`` sets the
threads.

The matrix imitates a plenoptic 1.0 camera: a square grid of lenslets, ``directions**2``
pixels under each (one per perspective view), pixels ordered as the sensor reads out
(row-major over the whole sensor, so the lenslets interleave). A pixel's beam is a straight
line through its lenslet's footprint on the nominal focal plane (the middle depth slice) with
a slope set by its direction, up to +-``max_slope`` voxels per slice; at each of the ``nz``
depth slices it deposits bilinear weights on the 2 x 2 voxels around the line and keeps the
largest 3, i.e. ``~3 nz`` non-zeros per row, like a one-voxel-wide beam crossing every slice.

Printed, in ms and ms per million non-zeros (``ms/Mnnz``):

- scipy: ``W @ x`` plus ``W.T @ y`` (CSR matvec and its CSC view), single-threaded C;
- projector forward / back (numba, all threads);
- back projection with ``transpose=True`` (gather from a transposed copy) and a
  colour-ordered scatter, for comparison;
- one MART sweep (row action, parallel over voxel-disjoint chunks; and in plain pixel order
  on one thread), one block sweep (one block per perspective view, parallel), one SMART
  iteration (forward + back through the Projector protocol), in two scenes: every pixel lit
  from ones (worst case), and a sparse particle volume from its MLOS first guess;
- the ratio block sweep / scipy (the goal is <= 0.5);
- memory per million non-zeros: CSR, scratch, row and block schedules, the alternatives.
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np
import scipy.sparse

from plenopiv.reconstruction._kernels import mart as mk
from plenopiv.reconstruction.mart import mlos
from plenopiv.reconstruction.projector import SparseProjector


def plenoptic_like_matrix(lenslets, directions, nz, voxels_per_lenslet, max_slope, rng):
    """Return ``(csr, view_labels, shape)`` for a plenoptic-like random weight matrix."""
    n_side = lenslets * directions
    ny = nx = lenslets * voxels_per_lenslet
    rows, cols = np.meshgrid(np.arange(n_side), np.arange(n_side), indexing="ij")
    rows, cols = rows.ravel(), cols.ravel()
    ly, lx = rows // directions, cols // directions
    a, b = rows % directions, cols % directions
    half = (directions - 1) / 2.0
    slope_y = (a - half) / max(half, 1.0) * max_slope
    slope_x = (b - half) / max(half, 1.0) * max_slope
    y0 = (ly + rng.uniform(0, 1, ly.shape)) * voxels_per_lenslet - 0.5
    x0 = (lx + rng.uniform(0, 1, lx.shape)) * voxels_per_lenslet - 0.5
    z = np.arange(nz)
    zc = (nz - 1) / 2.0
    y = y0[:, None] + slope_y[:, None] * (z - zc)
    x = x0[:, None] + slope_x[:, None] * (z - zc)
    iy, ix = np.floor(y).astype(np.int64), np.floor(x).astype(np.int64)
    fy, fx = y - iy, x - ix
    w = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], axis=-1)
    dy = np.array([0, 0, 1, 1])
    dx = np.array([0, 1, 0, 1])
    vy = iy[..., None] + dy
    vx = ix[..., None] + dx
    drop = np.argmin(w, axis=-1)  # keep the 3 largest of the 4 bilinear weights
    keep = np.ones(w.shape, bool)
    np.put_along_axis(keep, drop[..., None], False, axis=-1)
    keep &= (vy >= 0) & (vy < ny) & (vx >= 0) & (vx < nx) & (w > 0)
    vz = np.broadcast_to(z[None, :, None], w.shape)
    vox = (vz * ny + vy) * nx + vx
    n_rows = rows.shape[0]
    r = np.broadcast_to(np.arange(n_rows)[:, None, None], w.shape)
    csr = scipy.sparse.csr_array(
        (w[keep].astype(np.float32), (r[keep], vox[keep])), shape=(n_rows, nz * ny * nx)
    )
    csr.indices = csr.indices.astype(np.int32)
    view = (a * directions + b).astype(np.int64)
    return csr, view, (nz, ny, nx)


@numba.njit(parallel=True, cache=True)
def _back_by_colour(indptr, indices, data, rows, chunk_ptr, group_ptr, image, acc, out):
    """Alternative back projection: one shared accumulator; the chunks of one colour (sharing
    no voxel) scatter in parallel, colours in turn (one barrier per colour)."""
    for j in numba.prange(acc.shape[0]):
        acc[j] = 0.0
    for g in range(group_ptr.shape[0] - 1):
        for c in numba.prange(group_ptr[g], group_ptr[g + 1]):
            for k in range(chunk_ptr[c], chunk_ptr[c + 1]):
                i = rows[k]
                v = image[i]
                if v == 0.0:
                    continue
                for p in range(indptr[i], indptr[i + 1]):
                    acc[indices[p]] += data[p] * v
    for j in numba.prange(acc.shape[0]):
        out[j] = acc[j]


@numba.njit(cache=True)
def _mart_sequential(indptr, indices, data, intensity, bright, volume, relaxation):
    """Reference point: the MART sweep in plain pixel order, one thread."""
    for i in range(indptr.shape[0] - 1):
        if not bright[i]:
            continue
        s = 0.0
        for p in range(indptr[i], indptr[i + 1]):
            s += data[p] * volume[indices[p]]
        if s <= 0.0:
            continue
        gain = np.float32(relaxation * np.log(intensity[i] / s))
        for p in range(indptr[i], indptr[i + 1]):
            volume[indices[p]] = volume[indices[p]] * np.exp(gain * data[p])


def time_transposed_back(csr, y, repeat):
    """Time SparseProjector(transpose=True): building its transposed copy, then back()."""
    W = SparseProjector.from_scipy(csr, check=False, transpose=True)
    t0 = time.perf_counter()
    W.back(y)
    t_build = time.perf_counter() - t0
    return t_build, best_of(lambda: W.back(y), repeat), W.nbytes


def time_passes(W, image, first_guess, rows_schedule, blocks, repeat):
    """Best-of times (s) of one MART sweep (parallel, and in pixel order on one thread), one
    block sweep and one SMART iteration, each starting from ``first_guess`` (ones if None)."""
    bright = image > 0
    start = np.ones(W.n_voxels, np.float32) if first_guess is None else first_guess
    vol = start.copy()
    log_ratio = np.zeros(W.n_pixels, np.float64)
    mu = np.float32(1.0)
    colsum = np.maximum(W.column_sums(), 1.0)

    def mart_pass():
        vol[:] = start
        mk.mart_sweep(W.indptr, W.indices, W.data, W.row_index, W.row_scale,
                      rows_schedule.rows, rows_schedule.chunk_ptr, rows_schedule.group_ptr,
                      image, bright, vol, mu)

    def mart_sequential():
        vol[:] = start
        _mart_sequential(W.indptr, W.indices, W.data, image, bright, vol, mu)

    def block_pass():
        vol[:] = start
        mk.block_sweep(W.indptr, W.indices, W.data, W.row_index, W.row_scale,
                       blocks.block_column_sums, blocks.rows,
                       blocks.chunk_ptr, blocks.group_ptr, blocks.block_group_ptr, image,
                       bright, vol, mu, log_ratio)

    def smart_pass():
        vol[:] = start
        proj = W.forward(vol)
        lr = np.zeros(W.n_pixels, np.float32)
        m = bright & (proj > 0)
        lr[m] = np.log(image[m] / proj[m])
        vol[:] *= np.exp(W.back(lr) / colsum)

    return tuple(best_of(fn, repeat)
                 for fn in (mart_pass, mart_sequential, block_pass, smart_pass))


def best_of(fn, repeat):
    """Smallest wall time of ``repeat`` calls, seconds (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lenslets", type=int, default=35, help="lenslets per side")
    ap.add_argument("--directions", type=int, default=10, help="pixels per lenslet per side")
    ap.add_argument("--nz", type=int, default=64, help="depth slices")
    ap.add_argument("--voxels-per-lenslet", type=int, default=2)
    ap.add_argument("--max-slope", type=float, default=0.5, help="voxels per slice")
    ap.add_argument("--particles", type=float, default=0.002,
                    help="fraction of voxels holding a particle in the sparse scene")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)

    t0 = time.perf_counter()
    csr, view, shape = plenoptic_like_matrix(args.lenslets, args.directions, args.nz,
                                             args.voxels_per_lenslet, args.max_slope, rng)
    t_build = time.perf_counter() - t0
    W = SparseProjector.from_scipy(csr, check=False)
    nnz, mnnz = W.nnz, W.nnz / 1e6
    print(f"matrix: {W.n_pixels} pixels x {W.n_voxels} voxels {shape}, nnz = {nnz:,} "
          f"({nnz / W.n_pixels:.0f}/row, {nnz / W.n_voxels:.0f}/column), built in "
          f"{t_build:.1f} s; numba threads = {numba.get_num_threads()}")

    x = rng.uniform(0.5, 1.5, W.n_voxels).astype(np.float32)
    y = rng.uniform(0.5, 1.5, W.n_pixels).astype(np.float32)
    Wt = csr.T
    t_sp_fwd = best_of(lambda: csr @ x, args.repeat)
    t_sp_back = best_of(lambda: Wt @ y, args.repeat)
    t_sp = t_sp_fwd + t_sp_back
    t_fwd = best_of(lambda: W.forward(x), args.repeat)

    t_back = best_of(lambda: W.back(y), args.repeat)
    t0 = time.perf_counter()
    rows_schedule = W.row_schedule()
    t_colour = time.perf_counter() - t0
    acc = np.empty(W.n_voxels, np.float64)
    out = np.empty(W.n_voxels, np.float32)
    t_back_colour = best_of(lambda: _back_by_colour(
        W.indptr, W.indices, W.data, rows_schedule.rows, rows_schedule.chunk_ptr,
        rows_schedule.group_ptr, y, acc, out),
        args.repeat)
    n_threads = numba.get_num_threads()
    t_csc, t_back_csc, transposed_bytes = time_transposed_back(csr, y, args.repeat)

    t0 = time.perf_counter()
    blocks = W.block_schedule(view)
    t_blocks = time.perf_counter() - t0

    def per(t):
        return 1e3 * t / mnnz

    print(f"{'operation':50s} {'ms':>9s} {'ms/Mnnz':>9s}")
    for name, t in [
        ("scipy  W @ x   (CSR, 1 thread)", t_sp_fwd),
        ("scipy  W.T @ y (CSC view, 1 thread)", t_sp_back),
        ("scipy  W @ x + W.T @ y", t_sp),
        ("SparseProjector.forward", t_fwd),
        ("SparseProjector.back (per-thread accumulators)", t_back),
        (f"  alt. back: by colour ({rows_schedule.n_groups} colours)", t_back_colour),
        ("  back with transpose=True (gather from a copy)", t_back_csc),
    ]:
        print(f"{name:50s} {1e3 * t:9.1f} {per(t):9.2f}")

    # scene 1, worst case: every pixel lit, an image of a dense random volume, start from ones
    truth = rng.uniform(0.5, 1.5, W.n_voxels).astype(np.float32)
    dense = time_passes(W, W.forward(truth), None, rows_schedule, blocks, args.repeat)
    # scene 2: a particle volume (a fraction of the voxels lit), start from its MLOS volume
    truth = np.zeros(W.n_voxels, np.float32)
    lit = rng.choice(W.n_voxels, max(1, int(args.particles * W.n_voxels)), replace=False)
    truth[lit] = rng.uniform(0.5, 1.5, lit.shape[0])
    image = W.forward(truth)
    first_guess = mlos(image, W)
    scene = time_passes(W, image, first_guess, rows_schedule, blocks, args.repeat)
    for label, (t_mart, t_mart_seq, t_block, t_smart), lit_pixels, alive in [
        ("every pixel lit", dense, 1.0, 1.0),
        (f"particles in {args.particles:.1%} of voxels", scene, np.mean(image > 0),
         np.mean(first_guess > 0)),
    ]:
        print(f"-- scene: {label} ({lit_pixels:.0%} of pixels lit, {alive:.1%} of voxels "
              f"non-zero at the start)")
        for name, t in [
            (f"MART sweep, {rows_schedule.n_groups} colours, parallel", t_mart),
            ("  MART sweep in pixel order, 1 thread", t_mart_seq),
            (f"block sweep, {blocks.n_blocks} view blocks, parallel", t_block),
            ("SMART iteration (forward + back + exp)", t_smart),
        ]:
            print(f"{name:50s} {1e3 * t:9.1f} {per(t):9.2f}")
        print(f"ratio block sweep / scipy (W@x + W.T@y) = {t_block / t_sp:.2f}   "
              f"(MART / scipy = {t_mart / t_sp:.2f}, SMART / scipy = {t_smart / t_sp:.2f})")
    print(f"one-off: row colouring {1e3 * t_colour:.0f} ms, block schedule {1e3 * t_blocks:.0f} ms"
          f" ({blocks.n_groups} groups in {blocks.n_blocks} blocks), transposed copy "
          f"{1e3 * t_csc:.0f} ms")
    mb = 1e6
    print("memory per million non-zeros:")
    print(f"  CSR (int32 indices + float32 weights + row pointers): {W.nbytes / mnnz / mb:.2f} MB")
    print(f"  back-projection scratch ({n_threads} threads x n_voxels float64): "
          f"{8 * n_threads * W.n_voxels / mnnz / mb:.2f} MB")
    print(f"  row schedule (MART, back): {rows_schedule.nbytes / mnnz / mb:.2f} MB")
    print(f"  block schedule ({blocks.n_blocks} blocks, with block column sums): "
          f"{blocks.nbytes / mnnz / mb:.2f} MB")
    print(f"  SparseProjector(transpose=True), W and its copy: "
          f"{transposed_bytes / mnnz / mb:.2f} MB; alt. colour scatter: one n_voxels "
          f"float64, {8 * W.n_voxels / mnnz / mb:.2f} MB")
    print(f"  scipy CSR (same arrays; W.T is a view): "
          f"{(csr.data.nbytes + csr.indices.nbytes + csr.indptr.nbytes) / mnnz / mb:.2f} MB")


if __name__ == "__main__":
    main()
