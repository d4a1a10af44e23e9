"""The correlation field corrected by the pair's particle tracks.

A track measures its particle's displacement directly, from ray-bundle positions; the
correlation field measures the mean over a window, biased toward zero in depth where the
reconstructed particles are elongated and the ghosts stand still. Each track's residual,
its displacement less the field interpolated at its mid-point, is spread over the vectors
near it with Gaussian weights of a third of the window's edge (standard deviation, per
axis), shrunk toward no change by a prior of ``prior_tracks`` tracks::

    d_n  <-  d_n + sum_t K(x_n - x_t) r_t / (sum_t K(x_n - x_t) + prior_tracks)

so a vector far from every track keeps its value, and one amid several takes their mean
residual. See docs/methods.md#track-correction.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse
from scipy.spatial import cKDTree

from plenopiv.products.vectors import VectorResult
from plenopiv.tracking.matching import interpolate_displacement
from plenopiv.tracking.tracks import TrackResult

__all__ = ["KERNEL_FRACTION", "KERNEL_REACH", "TrackCorrection", "correct_with_tracks",
           "residual_weights"]

#: Standard deviation of the Gaussian kernel as a fraction of the last pass's window edge.
KERNEL_FRACTION = 1.0 / 3.0
#: Tracks farther than this many standard deviations from a vector are left out (weight
#: below exp(-4.5) = 1.1 %).
KERNEL_REACH = 3.0


@dataclass(frozen=True)
class TrackCorrection:
    """What :func:`correct_with_tracks` did.

    ``tracks``: tracks used (inside the field, the field finite at their mid-point);
    ``sigma``: the kernel's standard deviation along x, y, z, metres; ``prior_tracks``: the
    shrinkage; ``weight``: (nz, ny, nx) summed kernel weight of the tracks at each vector;
    ``rms_change``: rms of the correction over the finite vectors, metres, per component.
    """

    tracks: int
    sigma: tuple[float, float, float]
    prior_tracks: float
    weight: np.ndarray
    rms_change: tuple[float, float, float]

    def record(self) -> dict:
        """The product attribute ``track_correction`` (metres, counts)."""
        return {"tracks": self.tracks, "sigma_m": list(self.sigma),
                "prior_tracks": self.prior_tracks,
                "vectors_with_a_track": int(np.sum(self.weight >= 0.5)),
                "rms_change_m": list(self.rms_change)}


def residual_weights(nodes, points, sigma, reach: float = KERNEL_REACH):
    """Sparse Gaussian weights ``K[n, t] = exp(-|(nodes_n - points_t) / sigma|² / 2)``.

    ``nodes`` (N, 3), ``points`` (M, 3) and ``sigma`` (3,) in one unit; pairs farther than
    ``reach`` standard deviations are zero. Returns a CSR matrix (N, M).
    """
    s = np.asarray(sigma, float)
    a = np.asarray(nodes, float).reshape(-1, 3) / s
    b = np.asarray(points, float).reshape(-1, 3) / s
    if not len(a) or not len(b):
        return scipy.sparse.csr_matrix((len(a), len(b)))
    # the COO output keeps pairs at distance zero (a track on a vector)
    dist = cKDTree(a).sparse_distance_matrix(cKDTree(b), reach, output_type="coo_matrix")
    return scipy.sparse.coo_matrix((np.exp(-0.5 * dist.data ** 2), (dist.row, dist.col)),
                                   shape=dist.shape).tocsr()


def correct_with_tracks(vectors: VectorResult, tracks: TrackResult, *, prior_tracks: float,
                        kernel_fraction: float = KERNEL_FRACTION
                        ) -> tuple[VectorResult, TrackCorrection]:
    """Return the field corrected by the tracks' residuals, and what was done.

    Parameters
    ----------
    vectors : VectorResult
        The correlation field (physical coordinates) with its ``grid`` and ``window_vox``.
    tracks : TrackResult
        The pair's tracks, physical positions (metres).
    prior_tracks : float
        Shrinkage of the correction, in tracks (> 0): a vector with one track on it takes
        1 / (1 + prior_tracks) of that track's residual.
    kernel_fraction : float
        The kernel's standard deviation as a fraction of the window's edge.

    Vectors that are not finite stay so; ``valid``, flags and uncertainties are kept.
    """
    x, y, z = (np.asarray(a, float) for a in (vectors.x, vectors.y, vectors.z))
    sigma = _kernel_sigma(vectors, kernel_fraction)
    shape = (len(z), len(y), len(x))
    field = [np.asarray(c, float) for c in (vectors.u, vectors.v, vectors.w)]
    mid = 0.5 * (tracks.position_a + tracks.position_b)
    inside = np.ones(len(mid), bool)
    for axis, a in enumerate((x, y, z)):
        half = 0.5 * (a[1] - a[0]) if len(a) > 1 else sigma[axis]
        inside &= (mid[:, axis] >= a[0] - half) & (mid[:, axis] <= a[-1] + half)
    at_mid = interpolate_displacement(x, y, z, *field, mid[inside])
    residual = tracks.displacement[inside] - at_mid
    ok = np.all(np.isfinite(residual), axis=1)
    mid, residual = mid[inside][ok], residual[ok]
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    k = residual_weights(np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1), mid, sigma)
    weight = np.asarray(k.sum(axis=1)).ravel()
    delta = (k @ residual) / (weight + prior_tracks)[:, None]
    new = [f + delta[:, c].reshape(shape) for c, f in enumerate(field)]
    finite = np.isfinite(new[0]) & np.isfinite(new[1]) & np.isfinite(new[2])
    rms = tuple(float(np.sqrt(np.mean(delta[finite.ravel(), c] ** 2))) if finite.any()
                else 0.0 for c in range(3))
    out = replace(vectors, u=new[0], v=new[1], w=new[2])
    return out, TrackCorrection(int(len(mid)), tuple(float(s) for s in sigma),
                                float(prior_tracks), weight.reshape(shape), rms)


def _kernel_sigma(vectors: VectorResult, fraction: float) -> np.ndarray:
    """The kernel's standard deviation along x, y, z: ``fraction`` of the window, metres."""
    if vectors.grid is None or vectors.window_vox is None:
        raise ValueError("correct_with_tracks: the vectors carry no grid or window_vox (the "
                         "correlation's products do): the kernel's width is a share of the "
                         "window")
    edge = np.asarray(vectors.window_vox, float)[::-1] * np.asarray(vectors.grid.voxel, float)
    return fraction * edge
