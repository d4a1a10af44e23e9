"""numba kernels behind :mod:`plenopiv.reconstruction.mart` (private; arrays and scalars only).

W (rows = pixels, columns = voxels) comes as CSR ``indptr, indices, data`` read through a
row view ``row_index, row_scale`` (see :mod:`plenopiv.reconstruction._kernels.projector`:
view row i is CSR row ``row_index[i]`` times ``row_scale[i]``), together with a
row schedule (:class:`plenopiv.reconstruction.projector.RowSchedule`): groups of chunks of
rows, no two chunks of a group sharing a voxel, so that they may update their voxels in
parallel without a race. The volume (float32) is updated in place. Each sweep has a plain
NumPy twin here (``<kernel>_numpy``, same arguments).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from plenopiv.reconstruction._kernels.projector import csr_row, row_factor

#: Bound on |log(I_i / sum_j w_ij E_j)| in one update: a pixel that sees its voxels only
#: through tiny projections (an inconsistent system, e.g. after masking) cannot blow a voxel
#: up to infinity; consistent updates are far inside it (e^12 ≈ 1.6e5).
LOG_RATIO_BOUND = 12.0
#: Largest voxel value kept (float32 range), so that a runaway voxel never becomes inf/NaN.
VOXEL_MAX = np.float32(1e30)


@numba.njit(parallel=True, cache=True)
def mart_sweep(indptr, indices, data, row_index, row_scale, rows, chunk_ptr, group_ptr,
               intensity, bright, volume, relaxation):
    """One row-action MART sweep (Elsinga et al. 2006) over the rows in schedule order.

    For each bright pixel i: ``s = sum_j w_ij E_j``; if ``s > 0``,
    ``E_j <- E_j * (I_i / s) ** (relaxation * w_ij)`` for every voxel j of row i. Rows that
    project to zero are left alone (none of their voxels can change). The chunks of a group
    share no voxel, so running them in parallel (each chunk's rows in order) gives exactly
    the sequential sweep in the order ``rows``.
    """
    for g in range(group_ptr.shape[0] - 1):
        for c in numba.prange(group_ptr[g], group_ptr[g + 1]):
            for k in range(chunk_ptr[c], chunk_ptr[c + 1]):
                i = rows[k]
                if not bright[i]:
                    continue
                r = csr_row(row_index, i)
                f = row_factor(row_scale, i)
                s = 0.0
                for p in range(indptr[r], indptr[r + 1]):
                    s += (data[p] * f) * volume[indices[p]]
                if s <= 0.0:
                    continue
                lr = min(max(math.log(intensity[i] / s), -LOG_RATIO_BOUND), LOG_RATIO_BOUND)
                gain = np.float32(relaxation * lr)
                if gain == 0.0:
                    continue
                for p in range(indptr[r], indptr[r + 1]):
                    j = indices[p]
                    volume[j] = min(volume[j] * math.exp(gain * (data[p] * f)), VOXEL_MAX)


@numba.njit(parallel=True, cache=True)
def block_sweep(indptr, indices, data, row_index, row_scale, block_column_sums, rows, chunk_ptr,
                group_ptr, block_group_ptr, intensity, bright, volume, relaxation, log_ratio):
    """One block-iterative multiplicative sweep: the pixels of a block act simultaneously.

    For each block B in order: first, in parallel over its pixels,
    ``log_ratio[i] = log(I_i / sum_j w_ij E_j)`` (0 for dark pixels and for pixels that
    project to zero); then every voxel j seen by the block is multiplied by
    ``exp(relaxation * sum_{i in B} w_ij log_ratio[i] / max(1, sum_{i in B} w_ij))``,
    applied one pixel's factor at a time (the factors commute): the groups in turn, the
    chunks of a group (which share no voxel) in parallel. ``block_column_sums[p]`` is the
    block's weight sum on entry p's voxel; ``log_ratio`` is a float64 work array of length
    n_pixels. Zero voxels stay zero and are skipped.
    """
    for b in range(block_group_ptr.shape[0] - 1):
        g0 = block_group_ptr[b]
        g1 = block_group_ptr[b + 1]
        for k in numba.prange(chunk_ptr[group_ptr[g0]], chunk_ptr[group_ptr[g1]]):
            i = rows[k]
            lr = 0.0
            if bright[i]:
                r = csr_row(row_index, i)
                f = row_factor(row_scale, i)
                s = 0.0
                for p in range(indptr[r], indptr[r + 1]):
                    s += (data[p] * f) * volume[indices[p]]
                if s > 0.0:
                    lr = min(max(math.log(intensity[i] / s), -LOG_RATIO_BOUND),
                             LOG_RATIO_BOUND)
            log_ratio[i] = lr
        for g in range(g0, g1):
            for c in numba.prange(group_ptr[g], group_ptr[g + 1]):
                for k in range(chunk_ptr[c], chunk_ptr[c + 1]):
                    i = rows[k]
                    gain = np.float32(relaxation * log_ratio[i])
                    if gain == 0.0:
                        continue
                    r = csr_row(row_index, i)
                    f = row_factor(row_scale, i)
                    for p in range(indptr[r], indptr[r + 1]):
                        j = indices[p]
                        e = volume[j]
                        if e > 0.0:
                            volume[j] = min(e * math.exp(
                                gain * (data[p] * f)
                                / max(np.float32(1.0), block_column_sums[p])), VOXEL_MAX)


def _view_rows(indptr, indices, data, row_index, row_scale, i):
    """Voxel indices and float64 weights of view row ``i`` (NumPy; see :func:`csr_row`)."""
    r = int(row_index[i]) if row_index.shape[0] > 0 else int(i)
    f = np.float64(row_scale[i]) if row_scale.shape[0] > 0 else 1.0
    return indices[indptr[r]:indptr[r + 1]], data[indptr[r]:indptr[r + 1]].astype(np.float64) * f


def mart_sweep_numpy(indptr, indices, data, row_index, row_scale, rows, chunk_ptr, group_ptr,
                     intensity, bright, volume, relaxation):
    """Plain-NumPy twin of :func:`mart_sweep`: the rows one after another, in float64.

    Same arguments; ``volume`` is updated in place (rounded to its dtype once, at the end).
    The log-ratio is not bounded (consistent problems stay far inside the bound).
    """
    e = volume.astype(np.float64)
    for k in range(chunk_ptr[group_ptr[0]], chunk_ptr[group_ptr[-1]]):
        i = rows[k]
        if not bright[i]:
            continue
        cols, w = _view_rows(indptr, indices, data, row_index, row_scale, i)
        s = w @ e[cols]
        if s > 0:
            e[cols] *= (intensity[i] / s) ** (relaxation * w)
    volume[:] = e


def block_sweep_numpy(indptr, indices, data, row_index, row_scale, block_column_sums, rows,
                      chunk_ptr, group_ptr, block_group_ptr, intensity, bright, volume,
                      relaxation, log_ratio):
    """Plain-NumPy twin of :func:`block_sweep`: each block's update at once, in float64.

    Same arguments; the block's column sums are recomputed from its rows (so
    ``block_column_sums`` is not read), ``log_ratio`` receives each pixel's log-ratio, and
    ``volume`` is updated in place (rounded to its dtype once, at the end).
    """
    e = volume.astype(np.float64)
    for b in range(block_group_ptr.shape[0] - 1):
        g0, g1 = block_group_ptr[b], block_group_ptr[b + 1]
        block = rows[chunk_ptr[group_ptr[g0]]:chunk_ptr[group_ptr[g1]]]
        entries = [_view_rows(indptr, indices, data, row_index, row_scale, i) for i in block]
        for i, (cols, w) in zip(block, entries, strict=True):
            s = w @ e[cols]
            ok = bright[i] and s > 0
            log_ratio[i] = np.log(intensity[i] / s) if ok else 0.0
        column_sum = np.zeros(e.shape[0])
        update = np.zeros(e.shape[0])
        for i, (cols, w) in zip(block, entries, strict=True):
            np.add.at(column_sum, cols, w)
            np.add.at(update, cols, w * log_ratio[i])
        e *= np.exp(relaxation * update / np.maximum(1.0, column_sum))
    volume[:] = e
