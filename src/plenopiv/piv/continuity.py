"""The depth component of a vector field fitted to the continuity of an incompressible flow.

A plenoptic camera sees depth through a small angular aperture: near the focal plane a
particle's light stays in one lenslet for a move of a fraction of a depth cell, so the
correlation there measures a fraction of w, while u and v are measured to about a tenth of a
voxel. For an incompressible flow ``∂w/∂z = -(∂u/∂x + ∂v/∂y)``: along each column of vectors
in depth, w is fitted by weighted least squares to its own measurement and to the slope that
the lateral divergence demands; u and v are left as they are. See
docs/methods.md#depth-from-continuity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["CONSISTENCY_CHI2", "ContinuityFit", "column_gain_sigma", "depth_from_continuity",
           "gradient_matrix", "gradient_sigma", "layer_sigma"]

#: Largest normalised misfit of the fit (chi-square per vector) at which it is used: an rms
#: of three standard uncertainties. A larger one says the flow is not incompressible at the
#: vectors' resolution, or the uncertainties are far off; the field is then kept as measured.
CONSISTENCY_CHI2 = 9.0


def gradient_matrix(coords) -> np.ndarray:
    """The derivative along one axis as a matrix: ``G @ f == np.gradient(f, coords)``.

    ``coords``: the strictly increasing positions (n,), any unit; second-order differences
    inside (for uneven spacing too), first-order one-sided at the two ends. Returns an
    (n, n) array in 1/unit.
    """
    x = np.asarray(coords, dtype=float)
    n = len(x)
    g = np.zeros((n, n))
    if n < 2:
        return g
    h = np.diff(x)
    g[0, :2] = -1 / h[0], 1 / h[0]
    g[-1, -2:] = -1 / h[-1], 1 / h[-1]
    for i in range(1, n - 1):
        a, b = h[i - 1], h[i]             # left and right spacing
        g[i, i - 1:i + 2] = -b / (a * (a + b)), (b - a) / (a * b), a / (b * (a + b))
    return g


def gradient_sigma(sigma: np.ndarray, coords, axis: int) -> np.ndarray:
    """Standard uncertainty of ``np.gradient(f, coords, axis=axis)`` for independent errors.

    ``sigma``: the standard uncertainty of each sample of f; the result has its shape, in
    sigma's unit per coords' unit (GUM 5.1.2: the root sum of squared coefficients times
    uncertainties).
    """
    g2 = gradient_matrix(coords) ** 2
    s2 = np.moveaxis(np.asarray(sigma, float) ** 2, axis, 0)
    out = (g2 @ s2.reshape(s2.shape[0], -1)).reshape(s2.shape)
    return np.sqrt(np.moveaxis(out, 0, axis))


def layer_sigma(sigma: np.ndarray) -> np.ndarray:
    """Each depth layer's median uncertainty, broadcast over the layer ``[z, y, x]``.

    A vector's own uncertainty estimate scatters with its window's particles; the depth
    response it stands for is a property of the layer (its distance from focus). NaN where
    a layer has no finite value.
    """
    s = np.asarray(sigma, float)
    with np.errstate(all="ignore"):
        flat = s.reshape(s.shape[0], -1)
        med = np.array([np.median(r[np.isfinite(r)]) if np.isfinite(r).any() else np.nan
                        for r in flat])
    return np.broadcast_to(med[:, None, None], s.shape).copy()


def column_gain_sigma(sigma_w, w, gain_error) -> np.ndarray:
    """The uncertainty of w with the chain's gain term taken at its column's displacement.

    The response puts ``e_k · |w|`` into each vector's uncertainty (``e_k``: the relative
    gain error of layer k, ``gain_error``, dimensionless): right for one vector, but as a
    weight across the layers of a column it trusts a w the more the more it is attenuated,
    and near the focal plane, where the depth gain is lowest, w is smallest. Here that term
    is replaced by ``e_k · w_col``, w_col the column's rms measured w, so that the layers
    of a column weigh by their gain error alone (the rest of the uncertainty kept):

        σ² = max(σ_w² − (e_k w)², 0) + (e_k w_col)²

    ``sigma_w``, ``w`` (nz, ny, nx), one unit; ``gain_error`` (nz,). NaN stays NaN.
    """
    s = np.asarray(sigma_w, float)
    w = np.asarray(w, float)
    e = np.asarray(gain_error, float)[:, None, None]
    with np.errstate(all="ignore"):
        col = np.sqrt(np.nanmean(w ** 2, axis=0, keepdims=True))
    rest = np.maximum(s ** 2 - (e * w) ** 2, 0.0)
    return np.sqrt(rest + (e * np.nan_to_num(col)) ** 2)


@dataclass(frozen=True)
class ContinuityFit:
    """What :func:`depth_from_continuity` found.

    ``w``: the fitted depth component (nz, ny, nx), the unit of the input; a vector
    without a finite measurement and uncertainty keeps its input (NaN stays NaN);
    ``sigma_w``: its standard uncertainty (NaN where not fitted), the fit's posterior (the
    diagonal of the inverse normal matrix), scaled by ``sqrt(chi2_per_vector)`` where that
    exceeds 1 (the Birge ratio); ``chi2_per_vector``: the fit's normalised misfit, the sum
    of squared weighted residuals over the vectors fitted (about 1 where model and
    uncertainties hold); ``vectors``: how many were fitted; ``consistent``: ``chi2_per_vector <=``
    :data:`CONSISTENCY_CHI2`.
    """

    w: np.ndarray
    sigma_w: np.ndarray
    chi2_per_vector: float
    vectors: int

    @property
    def consistent(self) -> bool:
        """Whether the misfit is within :data:`CONSISTENCY_CHI2`."""
        return bool(self.chi2_per_vector <= CONSISTENCY_CHI2)


#: Bytes of the per-column normal matrices solved at once.
_CHUNK_BYTES = 64 * 2 ** 20


def depth_from_continuity(u, v, w, sigma_u, sigma_v, sigma_w, x, y, z) -> ContinuityFit:
    """Fit w along each depth column to its measurement and to ``∂w/∂z = -(∂u/∂x + ∂v/∂y)``.

    Parameters
    ----------
    u, v, w : ndarray (nz, ny, nx)
        Displacement (or velocity) along x, y, z on the window-centre grid, one unit.
    sigma_u, sigma_v, sigma_w : ndarray (nz, ny, nx)
        Their standard uncertainties, the same unit; each layer's median is used
        (:func:`layer_sigma`).
    x, y, z : ndarray (nx,), (ny,), (nz,)
        Window centres, one length unit, strictly increasing; at least two along each axis
        (:class:`ValueError` otherwise).

    Returns
    -------
    ContinuityFit

    Notes
    -----
    With δ = ∂u/∂x + ∂v/∂y (``np.gradient``) and σ_δ its uncertainty propagated from the
    layers' σ_u, σ_v (:func:`gradient_sigma`), w minimises, over every column,

        Σ_k (w_k − w_k^meas)² / σ_w,k²  +  Σ_k ((G_z w)_k + δ_k)² / σ_δ,k²

    G_z the depth derivative of :func:`gradient_matrix`. The columns are independent: each
    solves its normal equations ``N w = b`` (nz × nz), and ``diag(N⁻¹)`` is the fit's
    variance. Where σ_w is large against what δ fixes over a vector spacing (near focus) w
    follows continuity; where it is small (far from focus) w keeps its measurement and gives
    the integration its constant. A NaN vector, or one whose layer has no finite
    uncertainty, takes no part: its data row and the depth derivatives that reach it are
    left out, and its w stays as given.
    """
    u, v, w = (np.asarray(a, float) for a in (u, v, w))
    nz, ny, nx = w.shape
    if min(w.shape) < 2:
        raise ValueError(f"a field of {nz} x {ny} x {nx} vectors: continuity needs at least "
                         "two along each axis")
    su, sv, sw = (layer_sigma(s) for s in (sigma_u, sigma_v, sigma_w))
    delta = np.gradient(u, np.asarray(x, float), axis=2) + \
        np.gradient(v, np.asarray(y, float), axis=1)
    sd = np.hypot(gradient_sigma(su, x, 2), gradient_sigma(sv, y, 1))

    def columns(f):                        # (nz, ny, nx) -> (ny * nx, nz)
        return np.moveaxis(f, 0, -1).reshape(-1, nz)

    meas, s_meas, div, s_div = columns(w), columns(sw), columns(delta), columns(sd)
    g = gradient_matrix(z)
    data = np.isfinite(meas) & np.isfinite(s_meas) & (s_meas > 0)
    # a depth derivative counts where δ is known and every w it reaches was measured
    reach = (~data).astype(float) @ (g != 0).T.astype(float) == 0
    rule = np.isfinite(div) & np.isfinite(s_div) & (s_div > 0) & reach
    wd = np.where(data, np.where(data, s_meas, 1.0) ** -2.0, 0.0)
    wr = np.where(rule, np.where(rule, s_div, 1.0) ** -2.0, 0.0)
    meas, div = np.where(data, meas, 0.0), np.where(rule, div, 0.0)
    pin = np.where(data, 0.0, 1.0)         # a w without data: its own equation, kept below
    fit, var = np.empty_like(meas), np.empty_like(meas)
    chi2 = 0.0
    step = max(1, _CHUNK_BYTES // (8 * nz * nz))
    for lo in range(0, len(meas), step):
        c = slice(lo, lo + step)
        normal = np.einsum("ki,ck,kj->cij", g, wr[c], g) + (wd[c] + pin[c])[:, :, None] \
            * np.eye(nz)
        rhs = wd[c] * meas[c] - (wr[c] * div[c]) @ g
        inverse = np.linalg.inv(normal)
        fit[c] = np.einsum("cij,cj->ci", inverse, rhs)
        var[c] = np.diagonal(inverse, axis1=1, axis2=2)
        chi2 += float(np.sum(wd[c] * (fit[c] - meas[c]) ** 2)
                      + np.sum(wr[c] * (fit[c] @ g.T + div[c]) ** 2))
    n = int(data.sum())
    chi2 /= max(n, 1)
    # a w without a usable uncertainty keeps its value (NaN stays NaN), with no fitted sigma
    fit[~data], var[~data] = columns(w)[~data], np.nan

    def grid(f):                           # back to (nz, ny, nx)
        return np.moveaxis(f.reshape(ny, nx, nz), -1, 0)

    return ContinuityFit(w=grid(fit), sigma_w=grid(np.sqrt(var * max(1.0, chi2))),
                         chi2_per_vector=chi2, vectors=n)
