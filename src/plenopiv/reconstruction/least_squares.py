"""Non-negative least-squares reconstruction of ``W E = I``: FISTA, projected SIRT, clipped CGLS.

Beside the multiplicative MART/SMART (:mod:`plenopiv.reconstruction.mart`) these solve
``min ½ Σ_i r_i² (+ λ Σ_j E_j)``, ``r = W E - I``, with ``E >= 0``, through the
:class:`~plenopiv.reconstruction.projector.Projector` protocol alone (``forward``/``back``/
``row_sums``/``column_sums``), so they run on explicit and matrix-free weights alike. A
``ceiling`` row (a dark pixel given the noise floor) enters one-sided, ``r_i = max(W E - I,
0)_i``: it only pulls its voxels down, as in SMART (FISTA and SIRT). CGLS is linear: its
ceiling rows are equations at the floor, and its negative voxels are clipped at the end.
Voxels outside ``support`` stay zero. Volumes are flat float32 ``(n_voxels,)`` arrays.

See docs/methods.md#least-squares-solvers and docs/validation/solvers.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from plenopiv.errors import ReconstructionError
from plenopiv.reconstruction.projector import Projector

__all__ = ["SOLVERS", "least_squares", "lipschitz_bound"]

#: Valid values of ``least_squares(solver=...)``.
SOLVERS = ("fista", "sirt", "cgls")


def least_squares(image, projector: Projector, *, solver: str, iterations: int,
                  ceiling=None, support=None, initial=None, l1: float = 0.0,
                  relaxation: float = 1.0, power_iterations: int = 3,
                  callback: Callable[[int, np.ndarray], None] | None = None) -> np.ndarray:
    r"""Reconstruct E >= 0 from ``image`` by a least-squares solver.

    Parameters
    ----------
    image : array_like, n_pixels values
        Intensities I of the rows (counts, finite, >= 0); a ceiling row holds its bound.
    projector : Projector
        The weights W (explicit or matrix-free).
    solver : {"fista", "sirt", "cgls"}
        ``"fista"``: projected gradient with Nesterov's momentum (Beck & Teboulle 2009),
        step ``1/L`` with ``L >= ||W_S||²`` from :func:`lipschitz_bound`; ``"sirt"``:
        ``E <- max(E - μ C Wᵀ R r, 0)`` with ``R = 1/row sums``, ``C = 1/column sums``;
        ``"cgls"``: conjugate gradients on the normal equations from ``initial``, negative
        voxels clipped after the last iteration (not between: that would break the
        conjugacy).
    iterations : int
        Iterations (>= 0), each one forward and one back projection.
    ceiling : array_like of bool, n_pixels values, optional
        Rows whose intensity is an upper bound. FISTA and SIRT: one-sided residual
        ``max(W E - I, 0)``; CGLS: ordinary rows (the textbook solver).
    support : array_like of bool, n_voxels values, optional
        Voxels allowed to be non-zero (e.g. the line of sight); default all.
    initial : array_like, n_voxels values, optional
        First guess (>= 0); default zero.
    l1 : float
        The sparsity term λ Σ E (FISTA only; with E >= 0 it is λ ||E||₁) as a fraction of
        ``λ_max = max_j (Wᵀ I)_j`` over the support, the λ from which E = 0 solves the
        problem without ceilings (dimensionless, >= 0; 0: no term).
    relaxation : float
        μ of SIRT, in (0, 2).
    power_iterations : int
        Power iterations of :func:`lipschitz_bound` (FISTA).
    callback : callable, optional
        ``callback(iteration, volume)`` after each iteration (CGLS: the clipped iterate).

    Returns
    -------
    ndarray of float32
        The volume E (>= 0), ``(n_voxels,)``.
    """
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {SOLVERS}; got {solver!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, int | np.integer) \
            or iterations < 0:
        raise ValueError(f"iterations must be an int >= 0; got {iterations!r}")
    if not (math.isfinite(l1) and l1 >= 0):
        raise ValueError(f"l1 must be finite and >= 0; got {l1!r}")
    if l1 and solver != "fista":
        raise ValueError(f"l1 is used only by solver='fista'; got solver={solver!r}")
    if not 0 < relaxation < 2:
        raise ValueError(f"relaxation must be in (0, 2); got {relaxation!r}")
    b = _vector(image, projector.n_pixels, "image", "n_pixels")
    if not np.all(np.isfinite(b)) or (b < 0).any():
        raise ReconstructionError("image must be finite and >= 0")
    ceil = None if ceiling is None else \
        _vector(ceiling, projector.n_pixels, "ceiling", "n_pixels").astype(bool)
    mask = np.ones(projector.n_voxels, bool) if support is None else \
        _vector(support, projector.n_voxels, "support", "n_voxels").astype(bool)
    x = np.zeros(projector.n_voxels, np.float32) if initial is None else \
        np.where(mask, np.maximum(_vector(initial, projector.n_voxels, "initial",
                                          "n_voxels"), 0), 0).astype(np.float32)
    run = {"fista": _fista, "sirt": _sirt, "cgls": _cgls}[solver]
    options = {"fista": dict(l1=l1, power_iterations=power_iterations),
               "sirt": dict(relaxation=relaxation), "cgls": {}}[solver]
    return run(projector, b, ceil, mask, x, iterations, callback, **options)


def lipschitz_bound(projector: Projector, support=None, *, iterations: int = 3) -> float:
    r"""An upper bound of ``||W_S||² = ρ(W_Sᵀ W_S)``, S the support's columns.

    ``A = W_Sᵀ W_S`` is non-negative, so for any positive v the Collatz-Wielandt bound
    ``ρ(A) <= max_j (A v)_j / v_j`` holds; v starts at one (the bound is then the largest
    ``Σ_i w_ij R_i``) and is refined by ``iterations`` power iterations. Each costs one
    forward and one back projection.
    """
    n = projector.n_voxels
    mask = np.ones(n, bool) if support is None else np.asarray(support, bool).reshape(-1)
    v = mask.astype(np.float32)
    bound = math.inf
    for _ in range(max(iterations, 1)):
        av = np.asarray(projector.back(projector.forward(v)), np.float64) * mask
        live = mask & (v > 0)
        if not live.any() or not av[live].any():
            return 1.0
        bound = min(bound, float(np.max(av[live] / v[live])))
        v = (av / av.max()).astype(np.float32)
        v[live & (v <= 0)] = np.float32(1e-12)      # stay positive on the support
    return bound


# -- the solvers ---------------------------------------------------------------------------


def _residual(projector, x, b, ceiling) -> np.ndarray:
    """``W x - b``, one-sided (>= 0) on the ceiling rows."""
    r = np.asarray(projector.forward(x), np.float32) - b
    if ceiling is not None:
        np.maximum(r, 0, out=r, where=ceiling)
    return r


def _report(callback, iteration, x) -> None:
    if callback is not None:
        view = x.view()
        view.flags.writeable = False
        callback(iteration, view)


def _fista(projector, b, ceiling, mask, x, iterations, callback, *, l1, power_iterations):
    step = np.float32(1.0 / lipschitz_bound(projector, mask, iterations=power_iterations))
    if l1:
        l1 = l1 * float(np.max(np.asarray(projector.back(b), np.float64) * mask))
    y, t = x.copy(), 1.0
    for k in range(1, iterations + 1):
        g = np.asarray(projector.back(_residual(projector, y, b, ceiling)), np.float32)
        x_new = np.maximum(y - step * (g + np.float32(l1)), 0, dtype=np.float32)
        x_new[~mask] = 0
        t_new = (1 + math.sqrt(1 + 4 * t * t)) / 2
        y = x_new + np.float32((t - 1) / t_new) * (x_new - x)
        x, t = x_new, t_new
        _report(callback, k, x)
    return x


def _sirt(projector, b, ceiling, mask, x, iterations, callback, *, relaxation):
    rows = np.asarray(projector.row_sums(), np.float32)
    cols = np.asarray(projector.column_sums(), np.float32)
    inv_r = np.divide(1, rows, out=np.zeros_like(rows), where=rows > 0)
    inv_c = np.divide(relaxation, cols, out=np.zeros_like(cols), where=(cols > 0) & mask)
    for k in range(1, iterations + 1):
        g = np.asarray(projector.back(inv_r * _residual(projector, x, b, ceiling)), np.float32)
        x = np.maximum(x - inv_c * g, 0, dtype=np.float32)
        _report(callback, k, x)
    return x


def _cgls(projector, b, ceiling, mask, x, iterations, callback):
    x = x.astype(np.float64)
    r = b.astype(np.float64) - np.asarray(projector.forward(x.astype(np.float32)), np.float64)
    s = np.asarray(projector.back(r.astype(np.float32)), np.float64) * mask
    p, gamma = s.copy(), float(s @ s)
    for k in range(1, iterations + 1):
        if gamma == 0:
            _report(callback, k, np.maximum(x, 0).astype(np.float32))
            continue
        q = np.asarray(projector.forward(p.astype(np.float32)), np.float64)
        alpha = gamma / float(q @ q)
        x += alpha * p
        r -= alpha * q
        s = np.asarray(projector.back(r.astype(np.float32)), np.float64) * mask
        gamma, gamma_old = float(s @ s), gamma
        p = s + (gamma / gamma_old) * p
        _report(callback, k, np.maximum(x, 0).astype(np.float32))
    return np.maximum(x, 0).astype(np.float32)


def _vector(values, length: int, name: str, what: str) -> np.ndarray:
    v = np.asarray(values, dtype=np.float32 if name in ("image", "initial") else None)
    v = v.reshape(-1)
    if v.size != length:
        raise ReconstructionError(f"{name} has {v.size} values; the projector expects "
                                  f"{what} = {length}")
    return v
