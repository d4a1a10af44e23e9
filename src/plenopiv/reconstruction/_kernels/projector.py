"""numba kernels behind :mod:`plenopiv.reconstruction.projector` (private; arrays and scalars only).

W is held in CSR form (``indptr, indices, data``) and read through a *row view*: row k is CSR
row ``row_index[k]`` scaled by ``row_scale[k]`` (empty arrays: the identity and scale 1), so
that row-normalised and row-selected projectors share the one CSR. The back projection
scatters race-free into one accumulator per chunk of rows, or gathers from an optional
transposed copy; :func:`colour_chunks` colours the chunks of a row schedule so that the chunks
of one colour share no voxel (the MART updates, :mod:`plenopiv.reconstruction._kernels.mart`,
follow it). Every kernel ``k`` has its plain-NumPy twin ``k_numpy`` (float64 sums, rounded
once into float32 outputs); :data:`ENGINES` holds the two sets and the tests run both.
"""

from __future__ import annotations

from types import SimpleNamespace

import numba
import numpy as np


@numba.njit(inline="always")
def csr_row(row_index, k):
    """CSR row of view row ``k`` (``k`` itself for an empty ``row_index``)."""
    if row_index.shape[0] > 0:
        return np.int64(row_index[k])
    return np.int64(k)


@numba.njit(inline="always")
def row_factor(row_scale, k):
    """Scale of view row ``k`` (float32; 1 for an empty ``row_scale``)."""
    if row_scale.shape[0] > 0:
        return np.float32(row_scale[k])
    return np.float32(1.0)


@numba.njit(parallel=True, cache=True)
def forward_csr(indptr, indices, data, row_index, row_scale, volume, out):
    """``out[k] = sum_p w_p * volume[indices[p]]`` over view row k (W·E), in float64."""
    for k in numba.prange(out.shape[0]):
        i = csr_row(row_index, k)
        f = row_factor(row_scale, k)
        acc = 0.0
        for p in range(indptr[i], indptr[i + 1]):
            acc += np.float64(data[p] * f) * volume[indices[p]]
        out[k] = acc


@numba.njit(parallel=True, cache=True)
def back_scatter(indptr, indices, data, row_index, row_scale, image, row_bounds, acc, out):
    """``out = Wᵀ·image`` by a race-free parallel scatter, no transposed copy.

    Chunk c of view rows (``row_bounds[c]:row_bounds[c + 1]``) scatters into its own float64
    accumulator ``acc[c]`` (length n_voxels); the accumulators are then summed voxel by voxel
    and rounded once into ``out`` (float32). Rows whose image value is zero are skipped.
    """
    n_chunks = row_bounds.shape[0] - 1
    for c in numba.prange(n_chunks):
        a = acc[c]
        a[:] = 0.0
        for k in range(row_bounds[c], row_bounds[c + 1]):
            v = np.float64(image[k])
            if v == 0.0:
                continue
            i = csr_row(row_index, k)
            f = row_factor(row_scale, k)
            for p in range(indptr[i], indptr[i + 1]):
                a[indices[p]] += np.float64(data[p] * f) * v
    for j in numba.prange(out.shape[0]):
        s = 0.0
        for c in range(n_chunks):
            s += acc[c, j]
        out[j] = s


@numba.njit(cache=True)
def transpose_csr(indptr, indices, data, row_index, row_scale, n_rows, n_voxels):
    """CSR of the view's Wᵀ (its CSC) by a counting sort: ``(t_indptr, t_indices, t_data)``.

    ``t_indices`` are view row indices (int32), ascending within each voxel's run; ``n_rows``
    is the number of view rows.
    """
    t_indptr = np.zeros(n_voxels + 1, np.int64)
    for k in range(n_rows):
        i = csr_row(row_index, k)
        for p in range(indptr[i], indptr[i + 1]):
            t_indptr[indices[p] + 1] += 1
    for j in range(n_voxels):
        t_indptr[j + 1] += t_indptr[j]
    nnz = t_indptr[n_voxels]
    fill = t_indptr[:-1].copy()
    t_indices = np.empty(nnz, np.int32)
    t_data = np.empty(nnz, np.float32)
    for k in range(n_rows):
        i = csr_row(row_index, k)
        f = row_factor(row_scale, k)
        for p in range(indptr[i], indptr[i + 1]):
            q = fill[indices[p]]
            t_indices[q] = k
            t_data[q] = data[p] * f
            fill[indices[p]] = q + 1
    return t_indptr, t_indices, t_data


@numba.njit(parallel=True, cache=True)
def back_gather(t_indptr, t_indices, t_data, image, out):
    """``out = Wᵀ·image`` from the CSR of Wᵀ, one gather per voxel (float64 sums)."""
    for j in numba.prange(out.shape[0]):
        acc = 0.0
        for q in range(t_indptr[j], t_indptr[j + 1]):
            acc += np.float64(t_data[q]) * image[t_indices[q]]
        out[j] = acc


@numba.njit(cache=True)
def column_counts(indices, counts):
    """Add to ``counts[j]`` the number of entries of voxel j in ``indices`` (in place).

    One pass, no copy of ``indices`` (``np.bincount`` would convert them to int64: 8 bytes per
    non-zero, as much as the CSR itself).
    """
    for p in range(indices.shape[0]):
        counts[indices[p]] += 1


@numba.njit(cache=True)
def colour_chunks(indptr, indices, data, row_index, row_scale, block_ptr, block_rows,
                  chunk_rows, n_voxels, words, with_sums):
    """First-fit colouring of chunks of rows: chunks that share a voxel differ in colour.

    The view rows of block b, ``block_rows[block_ptr[b]:block_ptr[b + 1]]``, are cut into chunks
    of ``chunk_rows`` consecutive rows (the last may be shorter), coloured in that order.
    Each voxel keeps a bit mask of the colours of the block's chunks that touch it
    (``words`` 64-bit words, so at most ``64 * words`` colours per block); a chunk takes the
    smallest colour free on all the voxels of all its rows. The masks are cleared between
    blocks.

    Returns
    -------
    chunk_colour : int32 (n_chunks,)
        Colour of each chunk, chunks numbered block by block.
    n_colours : int64 (n_blocks,)
        Colours used by each block; all -1 when ``64 * words`` were not enough (call again
        with more words).
    block_column_sums : float32 (nnz,), or (0,) unless ``with_sums``
        For CSR entry p of a row in block B: ``sum_{i in B} w_{i, indices[p]}`` (scaled
        weights; entries of CSR rows outside the view stay 0).
    """
    n_blocks = block_ptr.shape[0] - 1
    n_chunks = 0
    for b in range(n_blocks):
        n_chunks += (block_ptr[b + 1] - block_ptr[b] + chunk_rows - 1) // chunk_rows
    masks = np.zeros((n_voxels, words), np.uint64)
    acc = np.zeros(n_voxels if with_sums else 0, np.float64)
    block_column_sums = np.zeros(indices.shape[0] if with_sums else 0, np.float32)
    chunk_colour = np.zeros(n_chunks, np.int32)
    n_colours = np.zeros(n_blocks, np.int64)
    used = np.zeros(words, np.uint64)
    full = np.uint64(0xFFFFFFFFFFFFFFFF)
    one = np.uint64(1)
    c_index = 0
    for b in range(n_blocks):
        r0 = block_ptr[b]
        r1 = block_ptr[b + 1]
        for k0 in range(r0, r1, chunk_rows):
            k1 = min(k0 + chunk_rows, r1)
            used[:] = 0
            for k in range(k0, k1):
                i = csr_row(row_index, block_rows[k])
                f = row_factor(row_scale, block_rows[k])
                for p in range(indptr[i], indptr[i + 1]):
                    j = indices[p]
                    for w in range(words):
                        used[w] |= masks[j, w]
                    if with_sums:
                        acc[j] += data[p] * f
            c = -1
            for w in range(words):
                u = used[w]
                if u != full:
                    bit = 0
                    while (u >> np.uint64(bit)) & one:
                        bit += 1
                    c = 64 * w + bit
                    break
            if c < 0:
                n_colours[:] = -1
                return chunk_colour, n_colours, block_column_sums
            chunk_colour[c_index] = c
            c_index += 1
            if c + 1 > n_colours[b]:
                n_colours[b] = c + 1
            w = c // 64
            mask = one << np.uint64(c % 64)
            for k in range(k0, k1):
                i = csr_row(row_index, block_rows[k])
                for p in range(indptr[i], indptr[i + 1]):
                    masks[indices[p], w] |= mask
        for k in range(r0, r1):
            i = csr_row(row_index, block_rows[k])
            for p in range(indptr[i], indptr[i + 1]):
                if with_sums:
                    block_column_sums[p] = acc[indices[p]]
        for k in range(r0, r1):
            i = csr_row(row_index, block_rows[k])
            for p in range(indptr[i], indptr[i + 1]):
                j = indices[p]
                masks[j, :] = 0
                if with_sums:
                    acc[j] = 0.0
    return chunk_colour, n_colours, block_column_sums


# --------------------------------------------------------------------------------------------
# plain-NumPy twins (same arguments, same results; slow, for tests on small inputs)
# --------------------------------------------------------------------------------------------


def _view_numpy(indptr, indices, data, row_index, row_scale, n_rows):
    """The first ``n_rows`` rows of the view, entry by entry.

    Returns ``(row, voxel, weight, entry, start)``: the view row, voxel and float64 weight
    (the float32 product ``data * scale``, as the kernels form it) of each entry, its CSR
    entry index, and where each view row's entries start (``n_rows + 1``).
    """
    rows = np.arange(n_rows) if row_index.shape[0] == 0 else np.asarray(row_index, np.int64)
    scale = (np.ones(n_rows, np.float32) if row_scale.shape[0] == 0
             else np.asarray(row_scale[:n_rows], np.float32))
    lengths = (indptr[rows + 1] - indptr[rows]).astype(np.int64)
    start = np.zeros(n_rows + 1, np.int64)
    np.cumsum(lengths, out=start[1:])
    row = np.repeat(np.arange(n_rows), lengths)
    entry = np.repeat(indptr[rows].astype(np.int64) - start[:-1], lengths) + np.arange(start[-1])
    weight = (data[entry] * scale[row]).astype(np.float64)
    return row, indices[entry].astype(np.int64), weight, entry, start


def forward_csr_numpy(indptr, indices, data, row_index, row_scale, volume, out):
    """Twin of :func:`forward_csr`: ``out = W·volume`` by ``np.bincount`` in float64."""
    row, col, w, _, _ = _view_numpy(indptr, indices, data, row_index, row_scale, out.shape[0])
    out[:] = np.bincount(row, w * np.asarray(volume, np.float64)[col], minlength=out.shape[0])


def back_scatter_numpy(indptr, indices, data, row_index, row_scale, image, row_bounds, acc, out):
    """Twin of :func:`back_scatter`: ``out = Wᵀ·image`` by ``np.bincount`` in float64.

    ``row_bounds`` gives the number of view rows (its last entry); ``acc`` is not used (one
    float64 sum per voxel, rounded once into ``out``).
    """
    row, col, w, _, _ = _view_numpy(indptr, indices, data, row_index, row_scale,
                                    int(row_bounds[-1]))
    out[:] = np.bincount(col, w * np.asarray(image, np.float64)[row], minlength=out.shape[0])


def transpose_csr_numpy(indptr, indices, data, row_index, row_scale, n_rows, n_voxels):
    """Twin of :func:`transpose_csr`: the CSR of the view's Wᵀ by a stable sort on voxels."""
    row, col, w, _, _ = _view_numpy(indptr, indices, data, row_index, row_scale, n_rows)
    order = np.argsort(col, kind="stable")
    t_indptr = np.zeros(n_voxels + 1, np.int64)
    np.cumsum(np.bincount(col, minlength=n_voxels), out=t_indptr[1:])
    return t_indptr, row[order].astype(np.int32), w[order].astype(np.float32)


def back_gather_numpy(t_indptr, t_indices, t_data, image, out):
    """Twin of :func:`back_gather`: ``out = Wᵀ·image`` from the CSR of Wᵀ, float64 sums."""
    voxel = np.repeat(np.arange(out.shape[0]), np.diff(t_indptr))
    values = t_data.astype(np.float64) * np.asarray(image, np.float64)[t_indices]
    out[:] = np.bincount(voxel, values, minlength=out.shape[0])


def column_counts_numpy(indices, counts):
    """Twin of :func:`column_counts`, by ``np.bincount``."""
    counts += np.bincount(indices, minlength=counts.shape[0]).astype(counts.dtype)


def colour_chunks_numpy(indptr, indices, data, row_index, row_scale, block_ptr, block_rows,
                        chunk_rows, n_voxels, words, with_sums):
    """Twin of :func:`colour_chunks`: the same first-fit colouring, with Python sets.

    A voxel keeps the set of colours of its block's chunks that touch it; a chunk takes the
    smallest colour in none of its voxels' sets. Same outputs; ``n_colours`` all -1 (and the
    colours found so far) when a block would need more than ``64 * words`` colours.
    """
    n_view = int(row_index.shape[0] or (block_rows.max(initial=-1) + 1))
    _, col, w, entry, start = _view_numpy(indptr, indices, data, row_index, row_scale, n_view)
    n_blocks = block_ptr.shape[0] - 1
    colours = np.zeros(_n_chunks(block_ptr, chunk_rows), np.int32)
    n_colours = np.zeros(n_blocks, np.int64)
    block_column_sums = np.zeros(indices.shape[0] if with_sums else 0, np.float32)
    n = 0
    for b in range(n_blocks):
        rows = block_rows[block_ptr[b]:block_ptr[b + 1]]
        taken: dict[int, set] = {}
        for k0 in range(0, len(rows), chunk_rows):
            voxels = {int(j) for k in rows[k0:k0 + chunk_rows] for j in col[start[k]:start[k + 1]]}
            busy = set().union(*(taken.get(j, set()) for j in voxels))
            c = min(set(range(len(busy) + 1)) - busy)
            if c >= 64 * words:
                return colours, np.full(n_blocks, -1, np.int64), block_column_sums
            colours[n], n = c, n + 1
            n_colours[b] = max(n_colours[b], c + 1)
            for j in voxels:
                taken.setdefault(j, set()).add(c)
        if with_sums and len(rows):
            sel = np.concatenate([np.arange(start[k], start[k + 1]) for k in rows])
            sums = np.bincount(col[sel], w[sel], minlength=n_voxels)
            block_column_sums[entry[sel]] = sums[col[sel]]
    return colours, n_colours, block_column_sums


def _n_chunks(block_ptr, chunk_rows) -> int:
    """Number of chunks of ``chunk_rows`` rows over all blocks."""
    sizes = np.diff(block_ptr)
    return int(((sizes + chunk_rows - 1) // chunk_rows).sum())


#: The kernel sets by name, ``"numba"`` and ``"numpy"``: the same six functions each.
ENGINES = {
    "numba": SimpleNamespace(forward_csr=forward_csr, back_scatter=back_scatter,
                             transpose_csr=transpose_csr, back_gather=back_gather,
                             column_counts=column_counts, colour_chunks=colour_chunks),
    "numpy": SimpleNamespace(forward_csr=forward_csr_numpy, back_scatter=back_scatter_numpy,
                             transpose_csr=transpose_csr_numpy, back_gather=back_gather_numpy,
                             column_counts=column_counts_numpy,
                             colour_chunks=colour_chunks_numpy),
}
