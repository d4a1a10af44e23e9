"""MLOS and MART: kernels against NumPy twins, invariants, a toy tomography problem, validation."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
from hypothesis import given, settings
from hypothesis import strategies as st

from plenopiv import ImageError, ReconstructionError
from plenopiv.reconstruction._kernels import mart as mk
from plenopiv.reconstruction.mart import METHODS, mlos, reconstruct, reconstruction_quality
from plenopiv.reconstruction.projector import SparseProjector

U32 = 2.0**-24

#: The classical MART (Elsinga et al. 2006: row action, μ = 1, five sweeps) these tests were
#: written for; reconstruct has no defaults of its own (the settings are the configuration's).
CLASSIC = dict(method="mart", iterations=5, relaxation=1.0)


def random_csr(rng, n_pixels, n_voxels, density):
    """Random CSR, float32 weights in (0, 1], no duplicates, some empty rows/columns."""
    m = scipy.sparse.random_array((n_pixels, n_voxels), density=density, rng=rng,
                                  dtype=np.float32, format="csr")
    m.data = (1.0 - m.data).astype(np.float32)
    m.indices = m.indices.astype(np.int32)
    return m


def consistent_problem(rng, n_pixels=80, n_voxels=60, density=0.1):
    """W, a positive truth and its exact image (float32)."""
    m = random_csr(rng, n_pixels, n_voxels, density)
    W = SparseProjector.from_scipy(m)
    truth = rng.uniform(0.5, 1.5, n_voxels).astype(np.float32)
    return m, W, truth, W.forward(truth)


# -- the kernels against their NumPy twins (plenopiv.reconstruction._kernels.mart) -----------


def sweep_rtol(m):
    """Relative tolerance of a float32 sweep against the float64 twin.

    A voxel of column degree d is multiplied d times per sweep; each update rounds the
    projection, the log-ratio gain, the exponent and the product to float32 (about 4 U32
    each, the gain's error entering through the exponent), and those errors feed the later
    projections to first order: 16 U32 per update, d_max updates.
    """
    d_max = int(np.bincount(m.indices, minlength=m.shape[1]).max())
    return 16 * d_max * U32


@pytest.mark.parametrize("chunk_rows", [1, 5, 1000])
@pytest.mark.parametrize("relaxation", [1.0, 0.4])
def test_mart_kernel_matches_numpy_twin(rng, chunk_rows, relaxation):
    m, W, truth, image = consistent_problem(rng)
    bright = rng.uniform(size=image.shape) > 0.2  # some dark pixels are skipped
    volume = rng.uniform(0.5, 1.5, W.n_voxels).astype(np.float32)
    schedule = W.row_schedule(chunk_rows=chunk_rows)
    expected = volume.copy()
    mk.mart_sweep_numpy(W.indptr, W.indices, W.data, W.row_index, W.row_scale, schedule.rows,
                        schedule.chunk_ptr, schedule.group_ptr, image, bright, expected,
                        relaxation)
    mk.mart_sweep(W.indptr, W.indices, W.data, W.row_index, W.row_scale,
                  schedule.rows, schedule.chunk_ptr, schedule.group_ptr, image, bright,
                  volume, np.float32(relaxation))
    np.testing.assert_allclose(volume, expected, rtol=sweep_rtol(m))


@pytest.mark.parametrize("chunk_rows", [1, 3, 64])
def test_block_kernel_matches_numpy_twin(rng, chunk_rows):
    m, W, truth, image = consistent_problem(rng, density=0.2)  # blocks with column sums > 1
    labels = rng.integers(0, 4, W.n_pixels)
    bright = rng.uniform(size=image.shape) > 0.2
    volume = rng.uniform(0.5, 1.5, W.n_voxels).astype(np.float32)
    schedule = W.block_schedule(labels, chunk_rows=chunk_rows)
    assert schedule.block_column_sums.max() > 1  # the max(1, .) normalisation is exercised
    expected = volume.copy()
    mk.block_sweep_numpy(W.indptr, W.indices, W.data, W.row_index, W.row_scale, None,
                         schedule.rows, schedule.chunk_ptr, schedule.group_ptr,
                         schedule.block_group_ptr, image, bright, expected, 0.8,
                         np.zeros(W.n_pixels))
    log_ratio = np.zeros(W.n_pixels)
    mk.block_sweep(W.indptr, W.indices, W.data, W.row_index, W.row_scale,
                   schedule.block_column_sums, schedule.rows,
                   schedule.chunk_ptr, schedule.group_ptr, schedule.block_group_ptr, image,
                   bright, volume, np.float32(0.8), log_ratio)
    np.testing.assert_allclose(volume, expected, rtol=sweep_rtol(m))


def test_one_pixel_blocks_are_mart_and_one_block_is_smart(rng):
    """With weights <= 1, a block of one pixel applies exactly the MART factor; one block of
    all pixels is SMART."""
    m, W, truth, image = consistent_problem(rng)
    kw = dict(iterations=3, relaxation=1.0, initial="ones")
    by_pixel = reconstruct(image, W, method="block", blocks=np.arange(W.n_pixels), **kw)
    expected = np.ones(W.n_voxels, np.float32)
    in_order = (np.arange(W.n_pixels), np.array([0, W.n_pixels]), np.array([0, 1]))
    for _ in range(3):
        mk.mart_sweep_numpy(W.indptr, W.indices, W.data, W.row_index, W.row_scale, *in_order,
                            image, np.ones(W.n_pixels, bool), expected, 1.0)
    np.testing.assert_allclose(by_pixel, expected, rtol=3 * sweep_rtol(m))
    one_block = reconstruct(image, W, method="block", blocks=np.zeros(W.n_pixels, int), **kw)
    smart = reconstruct(image, W, method="smart", **kw)
    np.testing.assert_allclose(one_block, smart, rtol=3 * sweep_rtol(m))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), method=st.sampled_from(METHODS),
       relaxation=st.floats(0.05, 2.0), iterations=st.integers(1, 3),
       dark_fraction=st.floats(0.0, 0.9), initial=st.sampled_from(["mlos", "ones"]))
def test_volumes_stay_non_negative(seed, method, relaxation, iterations, dark_fraction,
                                   initial):
    """Every update multiplies by exp(finite) > 0: E >= 0 and finite, even for an image no
    volume can explain (random intensities, many dark pixels)."""
    rng = np.random.default_rng(seed)
    m = random_csr(rng, 50, 40, 0.15)
    W = SparseProjector.from_scipy(m)
    image = rng.exponential(size=50).astype(np.float32)
    image[rng.uniform(size=50) < dark_fraction] = 0.0
    image[0] = 1.0  # at least one bright pixel
    blocks = rng.integers(0, 3, 50) if method == "block" else None
    kw = dict(method=method, iterations=iterations, blocks=blocks, relaxation=relaxation,
              initial=initial)
    m64 = m.astype(np.float64)
    free = ((m64.T @ (image <= 0).astype(float)) == 0) & (np.asarray(m64.sum(axis=0)) > 0)
    if not free.any():      # every seen voxel is seen by a dark pixel: refused
        with pytest.raises(ReconstructionError, match="empty volume"):
            reconstruct(image, W, **kw)
        return
    volume = reconstruct(image, W, **kw)
    assert volume.dtype == np.float32
    assert np.all(np.isfinite(volume)) and np.all(volume >= 0)


# -- MLOS -------------------------------------------------------------------------------------


def test_mlos_zeroes_what_dark_pixels_see_and_is_a_geometric_mean(rng):
    m, W, truth, image = consistent_problem(rng)
    image[rng.uniform(size=image.shape) < 0.1] = 0.5  # dark at threshold 1.0 (<= threshold)
    threshold = 1.0
    bright = image > threshold
    volume = mlos(image, W, pixel_threshold=threshold)
    m64 = m.astype(np.float64)
    seen_dark = (m64.T @ (~bright).astype(float)) > 0
    unseen = np.asarray(m64.sum(axis=0)).ravel() == 0
    assert np.all(volume[seen_dark | unseen] == 0)
    # elsewhere: exp(sum_i w_ij ln(I_i / R_i) / sum_i w_ij)
    row_sums = np.asarray(m64.sum(axis=1)).ravel()
    log_norm = np.where(bright & (row_sums > 0),
                        np.log(np.where(bright, image, 1) / np.maximum(row_sums, 1e-300)), 0)
    expected = np.exp((m64.T @ log_norm) / np.maximum(m64.sum(axis=0), 1e-300))
    keep = ~(seen_dark | unseen)
    assert keep.any() and seen_dark.any()
    np.testing.assert_allclose(volume[keep], expected[keep], rtol=1e-5)


def test_dark_pixels_zero_their_voxels_whatever_the_first_guess(rng):
    m, W, truth, image = consistent_problem(rng)
    image[:10] = 0.0
    seen_dark = (m[:10].astype(float).sum(axis=0) > 0)
    for initial in ("mlos", "ones", np.full(W.n_voxels, 2.0)):
        volume = reconstruct(image, W, **{**CLASSIC, "iterations": 0}, initial=initial)
        assert np.all(volume[seen_dark] == 0)
        assert np.all(volume[~seen_dark & (W.column_sums() > 0)] > 0)


def test_a_line_of_sight_that_empties_the_volume_is_refused(rng):
    """Each voxel seen by some dark pixel (every pixel sees every voxel, one is dark): the
    hard zeroing leaves nothing to iterate, and an all-zero volume would be a silent wrong
    result; with the dark pixel as a ceiling the same image reconstructs."""
    W = SparseProjector.from_scipy(scipy.sparse.csr_matrix(rng.uniform(0.1, 1.0, (6, 4))))
    image = np.array([0.0, 2.0, 3.0, 1.0, 2.5, 1.5], np.float32)
    for method in METHODS:
        blocks = np.zeros(6, int) if method == "block" else None
        with pytest.raises(ReconstructionError, match="empty volume.*ceiling"):
            reconstruct(image, W, method=method, iterations=2, relaxation=1.0, blocks=blocks)
    floor = np.where(image > 0, image, 0.01).astype(np.float32)
    volume = reconstruct(floor, W, method="smart", iterations=2, relaxation=1.0,
                         ceiling=image <= 0)
    assert volume.max() > 0


# -- a toy tomography problem -----------------------------------------------------------------


def line_views(shape, slopes):
    """W for parallel-ray views of a volume [z, y, x]: one view per (slope_y, slope_x).

    Each pixel is a line through ``(y0, x0)`` on the middle depth slice with the view's
    slopes (voxels per slice), as a plenoptic perspective view sees the volume; at every
    slice it deposits bilinear weights on the 2 x 2 voxels around the line (they sum to 1
    per slice, so each weight is the line's share of that slice). Returns the projector and
    the view label of each pixel.
    """
    nz, ny, nx = shape
    z = np.arange(nz)
    y0, x0 = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    rows, cols, vals, view = [], [], [], []
    n_rows = 0
    for v, (sy, sx) in enumerate((sy, sx) for sy in slopes for sx in slopes):
        y = y0.ravel()[:, None] + sy * (z - (nz - 1) / 2)
        x = x0.ravel()[:, None] + sx * (z - (nz - 1) / 2)
        iy, ix = np.floor(y).astype(int), np.floor(x).astype(int)
        fy, fx = y - iy, x - ix
        r = n_rows + np.arange(ny * nx)[:, None] + 0 * z
        for dy, wy in ((0, 1 - fy), (1, fy)):
            for dx, wx in ((0, 1 - fx), (1, fx)):
                yy, xx, w = iy + dy, ix + dx, wy * wx
                ok = (w > 0) & (yy >= 0) & (yy < ny) & (xx >= 0) & (xx < nx)
                rows.append(r[ok])
                cols.append(((z + 0 * yy) * ny * nx + yy * nx + xx)[ok])
                vals.append(w[ok])
        view.append(np.full(ny * nx, v))
        n_rows += ny * nx
    m = scipy.sparse.csr_array(
        (np.concatenate(vals).astype(np.float32),
         (np.concatenate(rows), np.concatenate(cols))), shape=(n_rows, nz * ny * nx))
    return SparseProjector.from_scipy(m), np.concatenate(view)


def gaussian_blobs(shape, centres, sigma, radius=np.inf):
    """Sum of Gaussian particles, each cut to zero beyond ``radius`` voxels (compact)."""
    grid = np.indices(shape, dtype=float)
    volume = np.zeros(shape)
    for c in centres:
        r2 = sum((grid[a] - c[a]) ** 2 for a in range(3))
        volume += np.where(r2 <= radius**2, np.exp(-r2 / (2 * sigma**2)), 0.0)
    return volume.astype(np.float32)


TOY_SHAPE = (12, 16, 16)
TOY_SLOPES = (-0.5, 0.0, 0.5)


def toy_centres(rng, n):
    """n particle centres, at least 3 voxels apart and 2.5 voxels from the edges."""
    centres = []
    while len(centres) < n:
        c = rng.uniform(2.5, np.array(TOY_SHAPE) - 3.5)
        if all(np.linalg.norm(c - o) >= 3 for o in centres):
            centres.append(c)
    return centres


@pytest.fixture(scope="module")
def toy():
    """Six compact Gaussian particles (sigma 0.7, cut at 1.5 voxels) seen in 9 perspective
    views of +-0.5 voxel/slice parallax: a consistent problem (pixels off the particles are
    exactly zero, so pixel_threshold = 0 loses nothing)."""
    W, views = line_views(TOY_SHAPE, TOY_SLOPES)
    truth = gaussian_blobs(TOY_SHAPE, toy_centres(np.random.default_rng(11), 6), 0.7,
                           radius=1.5).ravel()
    return W, views, truth, W.forward(truth), 0.0


def test_toy_problem_is_ghost_free_by_construction(toy):
    """Premise of the Q bounds below: an empty voxel survives MLOS only if every view has a
    lit pixel on its lines; with lit fraction f_v per view that happens to about
    n_voxels * prod_v f_v voxels (ghost candidates). Keep that well below one."""
    W, views, truth, image, threshold = toy
    lit = np.array([np.mean(image[views == v] > threshold) for v in np.unique(views)])
    assert W.n_voxels * np.prod(lit) < 0.05


@pytest.mark.parametrize("method", METHODS)
def test_toy_reconstruction_converges(toy, method):
    """Q >= 0.99 (MART, block) or 0.95 (SMART) after 10 sweeps; more sweeps do not lose Q.

    Without ghosts (previous test) the voxels MLOS keeps are the particles' own support plus
    a thin rim, so the iterations only have to share each line's intensity among the voxels
    of one particle, which 9 views resolve; the problem is consistent, so the
    multiplicative iterations converge to the data (the image residual falls) and Q -> 1
    (Elsinga et al. 2006 call Q >= 0.75 adequate). SMART moves every voxel by the weighted
    mean of its pixels' log-ratios over all 9 views at once, a ninth of a MART step, and
    converges more slowly.
    """
    W, views, truth, image, threshold = toy
    blocks = views if method == "block" else None
    quality, residual = [], []

    def record(iteration, volume):
        quality.append(reconstruction_quality(volume, truth))
        residual.append(np.linalg.norm(W.forward(volume) - image) / np.linalg.norm(image))

    reconstruct(image, W, method=method, iterations=20, relaxation=1.0,
                pixel_threshold=threshold, blocks=blocks, callback=record)
    q_mlos = reconstruction_quality(mlos(image, W, pixel_threshold=threshold), truth)
    bound = 0.95 if method == "smart" else 0.99
    assert quality[9] >= bound > q_mlos
    assert quality[19] >= quality[4] - 1e-3
    assert residual[19] < 0.5 * residual[0]


def test_pixel_threshold_caps_quality_at_the_mlos_support(toy):
    """Thresholding the Gaussian tails makes the pixels near a threshold inconsistent.

    MART never revives a voxel MLOS zeroed, so for the support S of the MLOS volume
    Cauchy-Schwarz gives Q(E, E*) <= |E*_S| / |E*| for every E it can produce: the
    threshold, not the iterations, sets the ceiling. MART gets close to it.
    """
    W, views, _, _, _ = toy
    truth = gaussian_blobs(TOY_SHAPE, toy_centres(np.random.default_rng(11), 6), 0.7).ravel()
    image = W.forward(truth)
    threshold = 0.02 * float(image.max())
    support = mlos(image, W, pixel_threshold=threshold) > 0
    ceiling = np.linalg.norm(truth[support]) / np.linalg.norm(truth)
    q = reconstruction_quality(reconstruct(image, W, **{**CLASSIC, "iterations": 10},
                                           pixel_threshold=threshold), truth)
    assert ceiling - 0.05 <= q <= ceiling


def test_callback_sees_every_iteration_read_only(toy):
    W, views, truth, image, threshold = toy
    seen = []

    def callback(iteration, volume):
        seen.append((iteration, volume.shape))
        with pytest.raises(ValueError):
            volume[0] = 1.0

    out = reconstruct(image, W, **{**CLASSIC, "iterations": 3}, shape=TOY_SHAPE,
                      callback=callback)
    assert seen == [(1, TOY_SHAPE), (2, TOY_SHAPE), (3, TOY_SHAPE)]
    assert out.shape == TOY_SHAPE and out.dtype == np.float32


def test_zero_iterations_return_the_first_guess(toy):
    W, views, truth, image, threshold = toy
    first = reconstruct(image, W, **{**CLASSIC, "iterations": 0}, pixel_threshold=threshold)
    np.testing.assert_array_equal(first, mlos(image, W, pixel_threshold=threshold))


class DenseProjector:
    """A matrix-free stand-in: only the Projector protocol, backed by a dense array."""

    def __init__(self, matrix):
        self.matrix = np.asarray(matrix, dtype=np.float64)

    n_pixels = property(lambda self: self.matrix.shape[0])
    n_voxels = property(lambda self: self.matrix.shape[1])

    @staticmethod
    def _into(values, out):
        if out is None:
            return values.astype(np.float32)
        out[:] = values
        return out

    def forward(self, volume, *, out=None):
        return self._into(self.matrix @ np.ravel(volume), out)

    def back(self, image, *, out=None):
        return self._into(self.matrix.T @ np.ravel(image), out)

    def row_sums(self):
        return self.matrix.sum(axis=1)

    def column_sums(self):
        return self.matrix.sum(axis=0)


def test_smart_and_mlos_need_only_the_protocol(rng):
    m, W, truth, image = consistent_problem(rng)
    dense = DenseProjector(m.toarray())
    smart = {**CLASSIC, "method": "smart"}
    for fn in (lambda p: mlos(image, p), lambda p: reconstruct(image, p, **smart)):
        np.testing.assert_allclose(fn(dense), fn(W), rtol=1e-4, atol=1e-6)
    with pytest.raises(ReconstructionError, match="method='mart' walks the rows"):
        reconstruct(image, dense, **CLASSIC)


# -- quality and validation -------------------------------------------------------------------


def test_reconstruction_quality_definition():
    a = np.array([0.0, 1.0, 2.0, 0.0])
    assert reconstruction_quality(a, 3 * a) == pytest.approx(1.0)
    assert reconstruction_quality(a, [1.0, 0.0, 0.0, 5.0]) == 0.0
    assert reconstruction_quality([1.0, 1.0], [1.0, 0.0]) == pytest.approx(2**-0.5)
    with pytest.raises(ReconstructionError, match="must match"):
        reconstruction_quality(a, a[:3])
    with pytest.raises(ReconstructionError, match="all zero"):
        reconstruction_quality(a, np.zeros(4))


@pytest.mark.parametrize(
    "change,error,match",
    [
        (lambda i: np.where(np.arange(i.size) == 3, np.nan, i), ImageError, "1 NaN or infinite"),
        (lambda i: np.where(np.arange(i.size) < 2, -1.0, i), ImageError, "2 negative pixels"),
        (lambda i: np.zeros_like(i), ImageError, "no pixel is above pixel_threshold"),
        (lambda i: i[:-1], ReconstructionError, "n_pixels = 80"),
        (lambda i: i.astype(complex), ImageError, "real numbers"),
    ],
)
def test_bad_images_are_refused(rng, change, error, match):
    m, W, truth, image = consistent_problem(rng)
    with pytest.raises(error, match=match):
        reconstruct(change(image), W, **CLASSIC)


@pytest.mark.parametrize(
    "kwargs,error,match",
    [
        (dict(method="art"), ValueError, r"method must be one of \('mart', 'block', 'smart'\)"),
        (dict(initial="zeros"), ValueError, r"initial must be one of \('mlos', 'ones'\)"),
        (dict(initial=np.ones(3)), ReconstructionError, "n_voxels = 60"),
        (dict(initial=-np.ones(60)), ReconstructionError, "finite and >= 0"),
        (dict(iterations=-1), ValueError, "iterations must be an integer >= 0"),
        (dict(iterations=2.5), ValueError, "iterations must be an integer >= 0"),
        (dict(relaxation=0.0), ValueError, "relaxation must be finite and > 0"),
        (dict(pixel_threshold=-1.0), ValueError, "pixel_threshold must be finite and >= 0"),
        (dict(method="block"), ValueError, "method='block' needs blocks"),
        (dict(blocks=np.zeros(80, int)), ValueError, "blocks is used only by method='block'"),
        (dict(method="block", blocks=np.zeros(79, int)), ReconstructionError, "one per pixel"),
        (dict(shape=(4, 4, 4)), ReconstructionError, "nz\\*ny\\*nx = n_voxels = 60"),
        (dict(callback=3), ValueError, "callback must be callable"),
    ],
)
def test_bad_options_are_refused(rng, kwargs, error, match):
    m, W, truth, image = consistent_problem(rng)
    with pytest.raises(error, match=match):
        reconstruct(image, W, **{**CLASSIC, **kwargs})


def test_not_a_projector_is_refused(rng):
    with pytest.raises(ReconstructionError,
                       match="must implement plenopiv.reconstruction.projector.Projector"):
        reconstruct(np.ones(4), np.eye(4), **CLASSIC)


def test_ceiling_rows_only_lower_their_voxels():
    """A dark row given as a ceiling (its value an upper bound) leaves voxels whose projection
    stays below it alone, and lowers those that send more light into it."""
    w = SparseProjector.from_scipy(scipy.sparse.csr_matrix(np.array(
        [[1.0, 1.0, 0.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]], np.float32)))
    start = np.array([1.0, 1.0, 0.1], np.float32)
    image = np.array([2.0, 5.0, 0.5], np.float32)          # row 2: ceiling 0.5 above 0.1
    ceiling = np.array([False, False, True])
    lifted = reconstruct(image, w, method="smart", iterations=1, relaxation=1.0, initial=start)
    capped = reconstruct(image, w, method="smart", iterations=1, relaxation=1.0, initial=start,
                         ceiling=ceiling)
    assert lifted[2] > start[2]                              # a measurement pulls voxel 2 up
    # as a ceiling, row 2 does nothing: the update is that of rows 0 and 1 alone
    alone = start.copy()
    proj = w.forward(alone)
    ratio = np.log(image[:2] / proj[:2])
    col = np.maximum(np.asarray(w.column_sums()), 1.0)
    alone *= np.exp(np.array([ratio[0], ratio[0] + ratio[1], ratio[1]]) / col)   # μ = 1
    np.testing.assert_allclose(capped, alone, rtol=1e-5)
    # a ceiling below the projection lowers its voxel
    low = reconstruct(np.array([2.0, 5.0, 0.01], np.float32), w, method="smart", iterations=1,
                      relaxation=1.0, initial=start, ceiling=ceiling)
    assert low[2] < capped[2]


def test_ceiling_is_for_smart_only():
    w = SparseProjector.from_scipy(scipy.sparse.csr_matrix(np.eye(2, dtype=np.float32)))
    with pytest.raises(ValueError, match="ceiling"):
        reconstruct(np.ones(2, np.float32), w, **CLASSIC, ceiling=[True, False])
    with pytest.raises(ReconstructionError, match="ceiling has 3"):
        reconstruct(np.ones(2, np.float32), w, **{**CLASSIC, "method": "smart"},
                    ceiling=[True, False, True])
