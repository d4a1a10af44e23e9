"""Least-squares solvers (plenopiv.reconstruction.least_squares): NumPy twins, invariants, KKT.

The twins below are the textbook updates written on a dense float64 matrix, one line each;
the solvers run float32 projections through the Projector protocol, so they agree to float32
rounding accumulated over the iterations (rtol 1e-3 after tens of iterations).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse

from plenopiv.calibration.model import Calibration
from plenopiv.camera.grid import VolumeGrid
from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import light_field
from plenopiv.reconstruction.lattice import LatticeProjector
from plenopiv.reconstruction.least_squares import SOLVERS, least_squares, lipschitz_bound
from plenopiv.reconstruction.mart import reconstruction_quality
from plenopiv.reconstruction.projector import SparseProjector
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.weights import build_weights
from plenopiv.synthetic.images import particle_image
from plenopiv.workflow.volume import reconstruct_volume


def problem(rng, n_pixels=90, n_voxels=60, density=0.15, dark=0.2):
    """Dense W, its SparseProjector, a sparse non-negative truth, its image and ceiling rows."""
    m = scipy.sparse.random_array((n_pixels, n_voxels), density=density, rng=rng,
                                  dtype=np.float32, format="csr")
    m.data = (1.0 - m.data).astype(np.float32)
    m.indices = m.indices.astype(np.int32)
    truth = np.where(rng.random(n_voxels) < 0.3, rng.uniform(0.5, 2, n_voxels), 0)
    image = (m @ truth).astype(np.float32)
    ceiling = (rng.random(n_pixels) < dark) & (image < 0.5)
    return m.toarray().astype(np.float64), SparseProjector.from_scipy(m), truth, image, ceiling


# -- NumPy twins on a dense matrix ----------------------------------------------------------


def one_sided(W, x, b, ceiling):
    r = W @ x - b
    return np.where(ceiling, np.maximum(r, 0), r)


def fista_twin(W, b, ceiling, support, x, iterations, l1, lipschitz):
    y, t = x.copy(), 1.0
    for _ in range(iterations):
        x_new = np.where(support, np.maximum(y - (W.T @ one_sided(W, y, b, ceiling) + l1)
                                             / lipschitz, 0), 0)
        t_new = (1 + math.sqrt(1 + 4 * t * t)) / 2
        y = x_new + (t - 1) / t_new * (x_new - x)
        x, t = x_new, t_new
    return x


def sirt_twin(W, b, ceiling, support, x, iterations, mu):
    rows, cols = W.sum(axis=1), W.sum(axis=0)
    R = np.where(rows > 0, 1 / np.where(rows > 0, rows, 1), 0)
    C = np.where((cols > 0) & support, mu / np.where(cols > 0, cols, 1), 0)
    x = np.where(support, x, 0)                 # voxels outside the support start at zero
    for _ in range(iterations):
        x = np.maximum(x - C * (W.T @ (R * one_sided(W, x, b, ceiling))), 0)
    return x


def cgls_twin(W, b, support, x, iterations):
    A = W[:, support]
    z = x[support].copy()
    r = b - A @ z
    s = A.T @ r
    p, gamma = s.copy(), s @ s
    for _ in range(iterations):
        q = A @ p
        alpha = gamma / (q @ q)
        z, r = z + alpha * p, r - alpha * q
        s = A.T @ r
        gamma, old = s @ s, gamma
        p = s + gamma / old * p
    out = np.zeros_like(x)
    out[support] = np.maximum(z, 0)
    return out


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("with_options", [False, True])
def test_solvers_match_their_numpy_twins(rng, solver, with_options):
    W, P, truth, image, ceiling = problem(rng)
    support = rng.random(W.shape[1]) < 0.8 if with_options else np.ones(W.shape[1], bool)
    start = rng.uniform(0, 1, W.shape[1]) if with_options and solver != "cgls" else \
        np.zeros(W.shape[1])
    ceil = ceiling if with_options else np.zeros(len(image), bool)
    l1 = 0.05 if with_options and solver == "fista" else 0.0
    got = least_squares(image, P, solver=solver, iterations=25, support=support,
                        initial=start, ceiling=ceil, l1=l1)
    if solver == "fista":
        lam = l1 * (W.T @ image)[support].max()
        want = fista_twin(W, image, ceil, support, start, 25, lam, lipschitz_bound(P, support))
    elif solver == "sirt":
        want = sirt_twin(W, image, ceil, support, start, 25, 1.0)
    else:
        want = cgls_twin(W, image.astype(np.float64), support, start, 25)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-3 * np.abs(want).max())


def test_lipschitz_bound_bounds_the_spectral_norm(rng):
    W, P, *_ = problem(rng)
    exact = np.linalg.norm(W, 2) ** 2
    bounds = [lipschitz_bound(P, iterations=k) for k in (1, 3, 10)]
    assert all(b >= exact * (1 - 1e-5) for b in bounds)      # an upper bound, float32
    assert bounds[0] <= 2 * exact and bounds[1] <= 1.05 * exact and bounds[2] <= 1.001 * exact


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("solver", SOLVERS)
def test_volumes_are_non_negative(seed, solver):
    rng = np.random.default_rng(seed)
    W, P, truth, image, ceiling = problem(rng)
    noisy = np.maximum(image + rng.normal(0, 0.5, image.shape), 0).astype(np.float32)
    seen = []
    x = least_squares(noisy, P, solver=solver, iterations=30, ceiling=ceiling,
                      callback=lambda k, v: seen.append(v.min()))
    assert x.min() >= 0 and min(seen) >= 0 and len(seen) == 30


def objective(W, x, b, ceiling):
    return 0.5 * float(np.sum(one_sided(W, x, b, ceiling) ** 2))


@pytest.mark.parametrize("solver", ["fista", "sirt"])
def test_convergence_to_a_kkt_point(rng, solver):
    """On a consistent problem the objective falls with the iterations and the result meets
    the KKT conditions of min f(E), E >= 0: ∇f >= 0, and ∇f = 0 where E > 0 (within 1e-3 of
    ‖∇f(0)‖∞, float32 projections)."""
    W, P, truth, image, ceiling = problem(rng)
    values = [objective(W, least_squares(image, P, solver=solver, iterations=k,
                                         ceiling=ceiling), image, ceiling)
              for k in (0, 10, 100, 2000)]
    assert values[0] > values[1] > values[2] > values[3]
    x = least_squares(image, P, solver=solver, iterations=2000, ceiling=ceiling)
    grad = W.T @ one_sided(W, x, image, ceiling)
    scale = np.abs(W.T @ one_sided(W, np.zeros_like(x), image, ceiling)).max()
    assert grad.min() >= -1e-3 * scale
    assert np.abs(grad[x > 1e-4]).max() <= 1e-3 * scale


def test_cgls_residual_decreases_and_solves_a_consistent_system(rng):
    W, P, truth, image, _ = problem(rng, n_pixels=120, n_voxels=40, density=0.3)
    norms = []
    for k in (1, 5, 20, 60):
        x = least_squares(image, P, solver="cgls", iterations=k)
        norms.append(np.linalg.norm(W @ x - image))
    assert all(a > b for a, b in zip(norms, norms[1:], strict=False))
    assert norms[-1] <= 1e-3 * np.linalg.norm(image)


def test_dark_rows_are_ceilings_in_fista_and_sirt_and_equations_in_cgls():
    """A ceiling above the projection changes nothing; one below pulls its voxels down and
    never up. CGLS takes the same row as an equation at the floor (a zero row when the floor
    is zero)."""
    W = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]])
    P = SparseProjector.from_scipy(scipy.sparse.csr_matrix(W.astype(np.float32)))
    start = np.array([1.0, 1.0, 0.1], np.float32)
    ceiling = np.array([False, False, True])
    for solver in ("fista", "sirt"):
        high = np.array([2.0, 5.0, 0.5], np.float32)      # row 2's bound above its 0.1
        free = least_squares(high, P, solver=solver, iterations=1, initial=start)
        capped = least_squares(high, P, solver=solver, iterations=1, initial=start,
                               ceiling=ceiling)
        drop = least_squares(np.array([2.0, 5.0, 0.0], np.float32), P, solver=solver,
                             iterations=1, initial=start, ceiling=ceiling)
        assert free[2] != capped[2]                       # as a measurement it acts
        # as a ceiling it does not: the step of rows 0 and 1 alone
        alone = SparseProjector.from_scipy(scipy.sparse.csr_matrix(W[:2].astype(np.float32)))
        if solver == "sirt":
            np.testing.assert_allclose(capped[:2], least_squares(
                high[:2], alone, solver=solver, iterations=1, initial=start)[:2], rtol=1e-5)
        assert drop[2] < capped[2]                        # a bound below pulls down
    zero = least_squares(np.array([6.0, 5.0, 0.0], np.float32), P, solver="cgls",
                         iterations=3, ceiling=ceiling)
    np.testing.assert_allclose(W @ zero, [6.0, 5.0, 0.0], atol=1e-4)


def test_bad_options_are_refused(rng):
    W, P, truth, image, ceiling = problem(rng)
    for kw, error, match in ((dict(solver="lsqr"), ValueError, "solver must be"),
                             (dict(iterations=-1), ValueError, "iterations"),
                             (dict(l1=-1.0), ValueError, "l1"),
                             (dict(l1=0.1, solver="cgls"), ValueError, "only by solver"),
                             (dict(relaxation=2.5, solver="sirt"), ValueError, "relaxation"),
                             (dict(support=np.ones(3, bool)), ReconstructionError,
                              "support has 3")):
        with pytest.raises(error, match=match):
            least_squares(image, P, **{"solver": "fista", "iterations": 2, **kw})
    with pytest.raises(ReconstructionError, match="finite"):
        least_squares(np.full(len(image), np.nan, np.float32), P, solver="sirt",
                      iterations=1)


# -- both projectors -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def projectors():
    from plenopiv.camera.model import load_camera

    cal = Calibration.from_camera(load_camera("small_test"))
    lf = light_field(cal, edge_centroid=False)
    b = lf.footprint
    vx, vz = 0.75 * b, 1.7 * b
    grid = VolumeGrid.from_bounds((-15 * vx, 15 * vx), (-10 * vx, 10 * vx), (-12 * vz, 12 * vz),
                                  voxel=(vx, vx, vz))
    return build_weights(lf, grid, min_weight=0.0).projector, \
        LatticeProjector.from_light_field(lf, grid)


@pytest.mark.parametrize("solver", SOLVERS)
def test_explicit_and_matrix_free_projectors_agree(projectors, solver):
    """Same W in two orders (forward/back equal to 1e-5): the volumes agree to 1e-3."""
    explicit, lattice = projectors
    rng = np.random.default_rng(3)
    truth = np.where(rng.random(explicit.n_voxels) < 0.01, 1.0, 0.0).astype(np.float32)
    image = explicit.forward(truth)
    ceiling = image <= 0
    vols = [least_squares(image, p, solver=solver, iterations=10, ceiling=ceiling)
            for p in (explicit, lattice)]
    np.testing.assert_allclose(vols[1], vols[0], rtol=1e-3, atol=1e-3 * vols[0].max())


def test_solve_volume_takes_a_solver_on_both_projectors(small_camera):
    """The pipeline's rows, ceilings and line of sight with FISTA: both projectors agree
    (Q >= 0.99 between them, the bar of SMART's own test) and the volume is non-negative;
    SMART sweeps may follow."""
    cal = Calibration.from_camera(small_camera)
    lf = light_field(cal)
    b = lf.footprint
    grid = VolumeGrid.from_bounds((-12 * b, 12 * b), (-8 * b, 8 * b), (-40 * b, 40 * b),
                                  voxel=(b, b, 4 * b))
    rng = np.random.default_rng(5)
    pos = rng.uniform(-np.array([10, 6, 32]) * b, np.array([10, 6, 32]) * b, (40, 3))
    img = particle_image(small_camera, pos, rays_per_particle=4000, seed=2)
    vols = {kind: reconstruct_volume(cal, img, grid, settings=ReconstructionSettings(
        projector=kind, iterations=10), solver="fista").volume for kind in ("sparse", "lattice")}
    assert min(v.min() for v in vols.values()) >= 0
    assert reconstruction_quality(vols["lattice"], vols["sparse"]) >= 0.99
    # SMART sweeps after FISTA are multiplicative: FISTA's zero voxels stay zero
    both = reconstruct_volume(cal, img, grid, settings=ReconstructionSettings(
        projector="sparse", iterations=10), solver="fista",
        solver_options={"smart_sweeps": 3}).volume
    assert both.min() >= 0 and not both[vols["sparse"] == 0].any()
    assert not np.array_equal(both, vols["sparse"])


def test_an_l1_term_of_lambda_max_keeps_the_volume_empty(rng):
    """λ = λ_max = max (Wᵀ I): the gradient at E = 0 is Wᵀ(0 - I) + λ >= 0, so E = 0 is the
    solution; a smaller λ lets voxels in, fewer than without the term."""
    W, P, truth, image, _ = problem(rng)
    assert not least_squares(image, P, solver="fista", iterations=20, l1=1.0).any()
    some = least_squares(image, P, solver="fista", iterations=50, l1=0.1)
    none = least_squares(image, P, solver="fista", iterations=50)
    assert 0 < np.count_nonzero(some) < np.count_nonzero(none)
