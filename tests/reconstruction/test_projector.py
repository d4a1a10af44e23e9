"""The projector: numba kernels and their NumPy twins against scipy.sparse, adjointness,
schedules, validation."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
from hypothesis import given, settings
from hypothesis import strategies as st

from plenopiv import ReconstructionError
from plenopiv.reconstruction._kernels import projector as pk
from plenopiv.reconstruction.projector import Projector, RowAccessProjector, SparseProjector

#: The identity row view of the kernels: pixel i is CSR row i, scale 1.
NO_ROWS = np.zeros(0, np.int64)
NO_SCALE = np.zeros(0, np.float32)

#: The kernel sets of :data:`plenopiv.reconstruction._kernels.projector.ENGINES`.
ENGINE_NAMES = tuple(pk.ENGINES)

#: float32 unit roundoff: a float64 sum rounded once to float32 is off by at most this, relative.
U32 = 2.0**-24


def random_csr(rng, n_pixels, n_voxels, density, *, index_dtype=np.int64):
    """Random non-negative CSR with float32 weights in (0, 1], some empty rows and columns."""
    m = scipy.sparse.random_array((n_pixels, n_voxels), density=density, rng=rng,
                                  dtype=np.float32, format="csr")
    m.data = (1.0 - m.data).astype(np.float32)  # (0, 1], no explicit zeros
    m.indptr = m.indptr.astype(index_dtype)
    m.indices = m.indices.astype(np.int32)
    return m


def sum_bound(w, x):
    """Bound on |float32(sum) - exact| for a float64 sum of non-negative w times x, rounded once.

    ``U32 * sum |w x|`` for the final rounding, plus a float64 accumulation term that is
    negligible but kept honest.
    """
    return (U32 + 64 * 2.0**-53) * (abs(w) @ np.abs(x))


@pytest.mark.parametrize("transpose", [False, True])
@pytest.mark.parametrize("index_dtype", [np.int32, np.int64])
@pytest.mark.parametrize("shape,density", [((1, 1), 1.0), ((37, 53), 0.1), ((200, 90), 0.05)])
def test_forward_and_back_match_scipy(rng, index_dtype, shape, density, transpose):
    m = random_csr(rng, *shape, density, index_dtype=index_dtype)
    W = SparseProjector.from_scipy(m, transpose=transpose)
    assert W.indptr.dtype == index_dtype
    x = rng.normal(size=shape[1]).astype(np.float32)
    y = rng.normal(size=shape[0]).astype(np.float32)
    m64 = m.astype(np.float64)
    fx, by = W.forward(x), W.back(y)
    assert fx.dtype == np.float32 and by.dtype == np.float32
    assert np.all(np.abs(fx - m64 @ x) <= sum_bound(m64, x))
    assert np.all(np.abs(by - m64.T @ y) <= sum_bound(m64.T, y))


def row_view(rng, m, n_rows):
    """A row view of ``m``: ``n_rows`` CSR rows (repeats allowed) with float32 scales."""
    rows = rng.integers(0, m.shape[0], n_rows).astype(np.int64)
    scale = rng.uniform(0.5, 2.0, n_rows).astype(np.float32)
    # the view's matrix as the kernels form it: each weight the float32 product data * scale
    view = scipy.sparse.csr_array(m[rows].multiply(scale[:, None]).astype(np.float32))
    return rows, scale, view.astype(np.float64)


@pytest.mark.parametrize("engine", ENGINE_NAMES)
@pytest.mark.parametrize("view", [False, True])
def test_forward_kernel_matches_scipy(rng, engine, view):
    m = random_csr(rng, 40, 33, 0.15)
    rows, scale, m64 = (NO_ROWS, NO_SCALE, m.astype(np.float64)) if not view else \
        row_view(rng, m, 25)
    x = rng.normal(size=33).astype(np.float32)
    out = np.empty(m64.shape[0], np.float32)
    pk.ENGINES[engine].forward_csr(m.indptr, m.indices, m.data, rows, scale, x, out)
    assert np.all(np.abs(out - m64 @ x) <= sum_bound(m64, x))


@pytest.mark.parametrize("engine", ENGINE_NAMES)
@pytest.mark.parametrize("n_chunks", [1, 2, 3, 7, 50])
def test_back_scatter_kernel_any_chunking(rng, engine, n_chunks):
    """The per-chunk accumulators sum to Wᵀy however the rows are cut (empty chunks too)."""
    m = random_csr(rng, 23, 31, 0.2)
    y = rng.normal(size=23).astype(np.float32)
    y[::4] = 0.0  # rows of zero value are skipped
    bounds = np.linspace(0, 23, n_chunks + 1).astype(np.int64)
    acc = np.empty((n_chunks, 31))
    out = np.empty(31, np.float32)
    pk.ENGINES[engine].back_scatter(m.indptr, m.indices, m.data, NO_ROWS, NO_SCALE, y, bounds,
                                    acc, out)
    m64 = m.astype(np.float64)
    assert np.all(np.abs(out - m64.T @ y) <= sum_bound(m64.T, y))


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_back_kernels_on_a_row_view(rng, engine):
    """Scatter and gather (through the view's transpose) both give Wᵀy of a row view."""
    m = random_csr(rng, 30, 26, 0.2)
    rows, scale, m64 = row_view(rng, m, 35)
    y = rng.normal(size=35).astype(np.float32)
    k = pk.ENGINES[engine]
    scatter = np.empty(26, np.float32)
    k.back_scatter(m.indptr, m.indices, m.data, rows, scale, y, np.array([0, 17, 35]),
                   np.empty((2, 26)), scatter)
    gather = np.empty(26, np.float32)
    k.back_gather(*k.transpose_csr(m.indptr, m.indices, m.data, rows, scale, 35, 26), y, gather)
    for out in (scatter, gather):
        assert np.all(np.abs(out - m64.T @ y) <= sum_bound(m64.T, y))


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_column_count_kernel_counts_and_accumulates(rng, engine):
    """Entries per voxel, added to the counts it is given (so the counts may come in parts)."""
    indices = rng.integers(0, 17, 500).astype(np.int32)
    counts = np.zeros(17, np.int64)
    pk.ENGINES[engine].column_counts(indices[:200], counts)
    pk.ENGINES[engine].column_counts(indices[200:], counts)
    np.testing.assert_array_equal(counts, [np.count_nonzero(indices == j) for j in range(17)])


@pytest.mark.parametrize("with_sums", [False, True])
@pytest.mark.parametrize("chunk_rows", [1, 3])
def test_colour_kernel_matches_its_numpy_twin(rng, chunk_rows, with_sums):
    """Same first-fit colours, colour counts and block column sums (float64 sums rounded
    once to float32 in both, in different orders: equal within one float32 rounding)."""
    m = random_csr(rng, 50, 20, 0.15)
    scale = rng.uniform(0.5, 2.0, 50).astype(np.float32)
    labels = rng.integers(0, 3, 50)
    block_rows = np.argsort(labels, kind="stable").astype(np.int64)
    block_ptr = np.searchsorted(labels[block_rows], np.arange(4)).astype(np.int64)
    args = (m.indptr, m.indices, m.data, NO_ROWS, scale, block_ptr, block_rows, chunk_rows,
            20, 1, with_sums)
    fast, twin = pk.colour_chunks(*args), pk.colour_chunks_numpy(*args)
    np.testing.assert_array_equal(fast[0], twin[0])
    np.testing.assert_array_equal(fast[1], twin[1])
    np.testing.assert_allclose(fast[2], twin[2], rtol=2 * U32)
    assert (fast[2].size > 0) == with_sums


def test_colour_kernels_give_up_alike_when_colours_run_out():
    """Every row on one voxel: 70 single-row chunks need 70 colours, more than 64 · 1."""
    m = scipy.sparse.csr_array(np.ones((70, 1), np.float32))
    args = (m.indptr.astype(np.int64), m.indices.astype(np.int32), m.data, NO_ROWS, NO_SCALE,
            np.array([0, 70]), np.arange(70), 1, 1, 1, False)
    fast, twin = pk.colour_chunks(*args), pk.colour_chunks_numpy(*args)
    assert np.all(fast[1] == -1) and np.all(twin[1] == -1)
    np.testing.assert_array_equal(fast[0], twin[0])


@settings(max_examples=40, deadline=None)
@given(n_pixels=st.integers(1, 60), n_voxels=st.integers(1, 60),
       density=st.floats(0.01, 0.6), seed=st.integers(0, 2**32 - 1), transpose=st.booleans())
def test_forward_and_back_are_adjoint(n_pixels, n_voxels, density, seed, transpose):
    """(W x)·y == x·(Wᵀ y) to float32 precision.

    Each entry of W x and Wᵀ y is a float64 sum rounded once to float32 (relative error
    <= U32); the dot products are taken in float64. So the two sides differ from the exact
    value by at most U32 * sum|Wx||y| and U32 * sum|x||Wᵀy| respectively.
    """
    rng = np.random.default_rng(seed)
    W = SparseProjector.from_scipy(random_csr(rng, n_pixels, n_voxels, density),
                                   transpose=transpose)
    x = rng.normal(size=n_voxels).astype(np.float32)
    y = rng.normal(size=n_pixels).astype(np.float32)
    wx = W.forward(x).astype(np.float64)
    wty = W.back(y).astype(np.float64)
    lhs = wx @ y.astype(np.float64)
    rhs = x.astype(np.float64) @ wty
    bound = 1.01 * U32 * (np.abs(wx) @ np.abs(y) + np.abs(x) @ np.abs(wty)) + 1e-300
    assert abs(lhs - rhs) <= bound


def test_row_and_column_sums(rng):
    m = random_csr(rng, 40, 30, 0.2)
    W = SparseProjector.from_scipy(m)
    m64 = m.astype(np.float64)
    np.testing.assert_allclose(W.row_sums(), m64.sum(axis=1), rtol=2 * U32)
    np.testing.assert_allclose(W.column_sums(), m64.sum(axis=0), rtol=2 * U32)
    assert W.row_sums() is W.row_sums()  # cached


@pytest.mark.parametrize("transpose", [False, True])
def test_duplicates_are_summed_like_scipy(transpose):
    W = SparseProjector([0, 3], [2, 2, 0], [0.25, 0.5, 1.0], n_voxels=3, transpose=transpose)
    np.testing.assert_array_equal(W.forward([1.0, 0.0, 2.0]), [2.5])
    np.testing.assert_array_equal(W.back([2.0]), [2.0, 0.0, 1.5])


@pytest.mark.parametrize("engine", ENGINE_NAMES)
def test_transpose_kernel_matches_scipy(rng, engine):
    m = random_csr(rng, 30, 20, 0.2)
    t_indptr, t_indices, t_data = pk.ENGINES[engine].transpose_csr(
        m.indptr, m.indices, m.data, NO_ROWS, NO_SCALE, m.shape[0], 20)
    csc = m.tocsc()
    csc.sort_indices()
    np.testing.assert_array_equal(t_indptr, csc.indptr)
    np.testing.assert_array_equal(t_indices, csc.indices)
    np.testing.assert_array_equal(t_data, csc.data)
    W = SparseProjector.from_scipy(m, transpose=True)
    W.back(np.ones(30))
    assert W.nbytes == 2 * (m.data.nbytes + m.indices.nbytes) + m.indptr.nbytes + 21 * 8


@pytest.mark.parametrize("transpose", [False, True])
def test_empty_matrix_and_empty_rows(transpose):
    W = SparseProjector(np.zeros(4, np.int64), np.zeros(0, np.int32), np.zeros(0), n_voxels=5,
                        transpose=transpose)
    np.testing.assert_array_equal(W.forward(np.ones(5)), np.zeros(3))
    np.testing.assert_array_equal(W.back(np.ones(3)), np.zeros(5))
    assert W.row_schedule().rows.shape == (3,)


def test_protocols_and_scipy_round_trip(rng):
    m = random_csr(rng, 10, 12, 0.3)
    W = SparseProjector.from_scipy(m)
    assert isinstance(W, Projector) and isinstance(W, RowAccessProjector)
    assert W.shape == (10, 12) and W.nnz == m.nnz
    assert W.nbytes == m.data.nbytes + m.indices.nbytes + m.indptr.nbytes
    back = W.to_scipy()
    assert (back != m).nnz == 0


@pytest.mark.parametrize(
    "indptr,indices,data,match",
    [
        ([0, 1], [3], [1.0], r"voxel indices must lie in \[0, 3\)"),
        ([0, 1], [-1], [1.0], r"voxel indices must lie in \[0, 3\)"),
        ([0, 1], [0], [-0.5], "weights must be finite and >= 0"),
        ([0, 1], [0], [np.nan], "weights must be finite and >= 0"),
        ([0, 2], [0], [1.0], "end at nnz = 1"),
        ([0, 2, 1, 2], [0, 1], [1.0, 1.0], "non-decreasing"),
        ([0.0, 1.0], [0], [1.0], "indptr must be a 1-D integer array"),
        ([0, 2], [0, 1], [1.0], "data must be 1-D with the length of indices"),
    ],
)
def test_bad_matrices_are_refused(indptr, indices, data, match):
    with pytest.raises(ReconstructionError, match=match):
        SparseProjector(np.asarray(indptr), np.asarray(indices), np.asarray(data), n_voxels=3)


def test_wrong_vector_sizes_name_what_was_expected(rng):
    W = SparseProjector.from_scipy(random_csr(rng, 6, 4, 0.5))
    with pytest.raises(ReconstructionError, match="n_voxels = 4"):
        W.forward(np.ones(5))
    with pytest.raises(ReconstructionError, match="n_pixels = 6"):
        W.back(np.ones((2, 2)))
    W.back(np.ones((2, 3)))  # any shape of the right size is fine


# -- row schedules ---------------------------------------------------------------------------


def check_schedule(m, schedule, block_of_row):
    """Rows form a permutation; chunks are ascending runs of one block; groups share no voxel."""
    n = m.shape[0]
    assert np.array_equal(np.sort(schedule.rows), np.arange(n))
    for b in range(schedule.n_blocks):
        g0, g1 = schedule.block_group_ptr[b], schedule.block_group_ptr[b + 1]
        for g in range(g0, g1):
            owner = {}
            for c in range(schedule.group_ptr[g], schedule.group_ptr[g + 1]):
                rows = schedule.rows[schedule.chunk_ptr[c]:schedule.chunk_ptr[c + 1]]
                assert np.all(np.diff(rows) > 0)
                assert np.all(block_of_row[rows] == b)
                for i in rows:
                    for j in m.indices[m.indptr[i]:m.indptr[i + 1]]:
                        assert owner.setdefault(int(j), c) == c, "two chunks of a group share"


@pytest.mark.parametrize("chunk_rows", [1, 3, 16])
def test_row_schedule_is_a_race_free_order(rng, chunk_rows):
    m = random_csr(rng, 70, 40, 0.08)
    W = SparseProjector.from_scipy(m)
    s = W.row_schedule(chunk_rows=chunk_rows)
    assert s.n_blocks == 1 and s.block_column_sums is None
    check_schedule(m, s, np.zeros(70, np.int64))
    assert W.row_schedule(chunk_rows=chunk_rows) is s


@pytest.mark.parametrize("chunk_rows", [1, 4])
def test_block_schedule_blocks_and_column_sums(rng, chunk_rows):
    m = random_csr(rng, 60, 25, 0.15)
    W = SparseProjector.from_scipy(m)
    labels = rng.choice([-7, 3, 11, 40], size=60)  # any integers, unsorted
    s = W.block_schedule(labels, chunk_rows=chunk_rows)
    np.testing.assert_array_equal(s.labels, [-7, 3, 11, 40])
    block_of_row = np.searchsorted(s.labels, labels)
    check_schedule(m, s, block_of_row)
    # block column sums: for each entry, the block's total weight on that voxel
    m64 = m.astype(np.float64)
    for label in s.labels:
        rows = np.flatnonzero(labels == label)
        col = np.asarray(m64[rows].sum(axis=0)).ravel()
        for i in rows:
            p = slice(m.indptr[i], m.indptr[i + 1])
            np.testing.assert_allclose(s.block_column_sums[p], col[m.indices[p]], rtol=2 * U32)
    assert W.block_schedule(labels.copy(), chunk_rows=chunk_rows) is s  # cached by content


def test_block_schedule_refuses_bad_labels(rng):
    W = SparseProjector.from_scipy(random_csr(rng, 6, 4, 0.5))
    with pytest.raises(ReconstructionError, match="one per pixel"):
        W.block_schedule(np.zeros(5, int))
    with pytest.raises(ReconstructionError, match="must be integers"):
        W.block_schedule(np.zeros(6))
    with pytest.raises(ValueError, match="chunk_rows must be an integer >= 1"):
        W.block_schedule(np.zeros(6, int), chunk_rows=0)


@pytest.mark.parametrize("transpose", [False, True])
def test_row_views_share_the_csr_and_act_like_their_copy(rng, transpose):
    """scale_rows and select_rows are views of one CSR: they project, back-project, schedule
    and sweep exactly like an explicit copy of the scaled, selected rows."""
    from plenopiv.reconstruction._kernels import mart as mk

    m = random_csr(rng, 60, 40, 0.15)
    W = SparseProjector.from_scipy(m, transpose=transpose)
    factors = rng.uniform(0.5, 4.0, 60).astype(np.float32)
    keep = rng.uniform(size=60) > 0.3
    view = W.scale_rows(factors).select_rows(keep)
    assert view.data is W.data and view.indices is W.indices and view.n_pixels == keep.sum()
    scaled = m.copy()
    scaled.data = (m.data * np.repeat(factors, np.diff(m.indptr))).astype(np.float32)
    copy = SparseProjector.from_scipy(scaled[np.flatnonzero(keep)], transpose=transpose)
    np.testing.assert_array_equal(view.to_scipy().toarray(), copy.to_scipy().toarray())
    x = rng.uniform(size=40).astype(np.float32)
    y = rng.uniform(size=int(keep.sum())).astype(np.float32)
    np.testing.assert_array_equal(view.forward(x), copy.forward(x))
    np.testing.assert_array_equal(view.back(y), copy.back(y))
    np.testing.assert_array_equal(view.row_max(), copy.row_max())
    a, b = view.row_schedule(chunk_rows=3), copy.row_schedule(chunk_rows=3)
    np.testing.assert_array_equal(a.rows, b.rows)
    volumes = [np.full(40, 1.0, np.float32) for _ in range(2)]
    bright = np.ones(view.n_pixels, bool)
    for P, vol in zip((view, copy), volumes, strict=True):
        s = P.row_schedule(chunk_rows=3)
        mk.mart_sweep(P.indptr, P.indices, P.data, P.row_index, P.row_scale, s.rows,
                      s.chunk_ptr, s.group_ptr, y + 0.5, bright, vol, np.float32(0.7))
    np.testing.assert_array_equal(volumes[0], volumes[1])
