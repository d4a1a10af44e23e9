"""PIV-guided matching of particles between two exposures (hybrid PIV-PTV).

The correlation field predicts where each particle of exposure A went (Keane, Adrian & Zhang
1995), so the search for its partner in B shrinks to a small sphere around the prediction:
:func:`predict_positions`, :func:`match_particles` (nearest candidate within the search
radius, mutual and unambiguous both ways) and :func:`neighbour_median_test` (tracks that
disagree with their neighbours). Distances are measured in resolution cells, ``(b, b, ΔZ)``
metres per unit (:func:`plenopiv.camera.resolution.resolution_cell`), so that one search
radius suits the sharp lateral and the blurred depth direction.

See docs/methods.md#matching.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np
import scipy.ndimage
from scipy.spatial import cKDTree

__all__ = ["MatchSettings", "Matches", "interpolate_displacement", "match_particles",
           "neighbour_median_test", "predict_positions"]


@dataclass(frozen=True)
class MatchSettings:
    """Options of :func:`match_particles` (distances in resolution cells).

    Attributes
    ----------
    search_radius_cells : float
        Largest distance from the prediction to a partner, cells (> 0).
    median_threshold : float
        Normalised median test threshold on the neighbouring tracks (> 0).
    median_epsilon_cells : float
        Noise floor of the test, cells (> 0): the displacement scatter of correct tracks
        expected from position noise.
    neighbours : int
        Neighbouring tracks compared with each track (>= 3).
    neighbour_radius : float
        Only tracks within this distance (cells) count as neighbours (> 0); a track with
        fewer than 3 neighbours is kept untested.
    ambiguity_ratio : float
        Ratio test, in (0, 1]: a match is refused when its distance exceeds this fraction of
        the distance to the runner-up, in either direction (the second-nearest B particle to
        the A particle's prediction, or the second-nearest prediction to the B particle).
        1: no test (a mutual nearest partner is never further than its runner-up).
    """

    search_radius_cells: float = 1.0
    median_threshold: float = 2.0
    median_epsilon_cells: float = 0.1
    neighbours: int = 8
    neighbour_radius: float = 8.0
    ambiguity_ratio: float = 1.0

    def __post_init__(self):
        for name in ("search_radius_cells", "median_threshold", "median_epsilon_cells",
                     "neighbour_radius"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"tracking {name} = {v!r}: expected a number > 0")
        if int(self.neighbours) != self.neighbours or self.neighbours < 3:
            raise ValueError(f"tracking neighbours = {self.neighbours!r}: expected an int >= 3")
        if not (np.isfinite(self.ambiguity_ratio) and 0 < self.ambiguity_ratio <= 1):
            raise ValueError(f"tracking ambiguity_ratio = {self.ambiguity_ratio!r}: expected "
                             "a number in (0, 1]")


@dataclass(frozen=True, eq=False)
class Matches:
    """Particle pairs between exposures A and B.

    Attributes
    ----------
    index_a, index_b : (M,) int64
        Row of each track's particle in the A and B tables.
    residual : (M,) float64
        Distance of the B particle from the predicted position, cells.
    quality : (M,) float64
        1 - d1/d2, d1 the match's distance and d2 the runner-up's, in the more ambiguous of
        the two directions (the second-nearest B particle to the prediction, the
        second-nearest prediction to the B particle; 1: unique, 0: a tie), dimensionless.
    n_candidates : (M,) int64
        B particles within the search radius of the prediction.
    rejected_mutual, rejected_median, rejected_ambiguous : int
        Matches dropped by the two-way check, by the neighbour test and by the ratio test.
    """

    index_a: np.ndarray
    index_b: np.ndarray
    residual: np.ndarray
    quality: np.ndarray
    n_candidates: np.ndarray
    rejected_mutual: int = 0
    rejected_median: int = 0
    rejected_ambiguous: int = 0

    def __len__(self) -> int:
        """Return the number of tracks."""
        return int(len(self.index_a))


def interpolate_displacement(x, y, z, u, v, w, points) -> np.ndarray:
    """Trilinear interpolation of a displacement field on a regular grid.

    Parameters
    ----------
    x, y, z : 1-D arrays
        Evenly spaced grid coordinates, metres (any length >= 1).
    u, v, w : (nz, ny, nx) arrays
        Displacement components, metres.
    points : (N, 3) array
        ``(x, y, z)`` metres; points outside the grid take the nearest edge value.

    Returns
    -------
    ndarray, shape (N, 3)
        Displacement ``(dx, dy, dz)`` at each point, metres.
    """
    p = np.asarray(points, float).reshape(-1, 3)
    idx = []
    for k, axis in enumerate((z, y, x)):
        a = np.asarray(axis, float)
        step = a[1] - a[0] if len(a) > 1 else 1.0
        idx.append(np.clip((p[:, 2 - k] - a[0]) / step, 0, len(a) - 1))
    coords = np.array(idx)
    return np.stack([scipy.ndimage.map_coordinates(np.asarray(c, float), coords, order=1,
                                                   mode="nearest") for c in (u, v, w)], axis=1)


def predict_positions(vectors, positions) -> np.ndarray:
    """Predicted B positions of A particles from a correlation field.

    Parameters
    ----------
    vectors : object with ``x, y, z, u, v, w``
        Displacement field in metres on the same axes as ``positions`` (e.g. a
        :class:`~plenopiv.products.vectors.VectorResult`).
    positions : (N, 3)
        Particle positions in exposure A, metres.

    Returns
    -------
    ndarray, shape (N, 3)
        ``p + d(p + d(p)/2)``, metres.
    """
    p = np.asarray(positions, float).reshape(-1, 3)
    args = (vectors.x, vectors.y, vectors.z, vectors.u, vectors.v, vectors.w)
    d = interpolate_displacement(*args, p)
    return p + interpolate_displacement(*args, p + 0.5 * d)


def neighbour_median_test(positions, displacements, *, threshold: float = 2.0,
                          epsilon: float = 0.1, neighbours: int = 8,
                          radius: float = np.inf) -> np.ndarray:
    r"""Normalised median test of scattered displacements (Westerweel & Scarano 2005).

    Parameters
    ----------
    positions, displacements : (M, 3)
        Track positions and displacements in the same (normalised) units.
    threshold : float
        Outlier when :math:`|d - \tilde d| / (\tilde r + \epsilon)` exceeds this for any
        component, with :math:`\tilde d` the median of the neighbours' displacements and
        :math:`\tilde r` the median of their own residuals :math:`|d_j - \tilde d|`.
    epsilon : float
        Noise floor, units of the displacements.
    neighbours : int
        Nearest tracks compared (the track itself excluded).
    radius : float
        Only tracks closer than this are neighbours; a track with fewer than 3 is not tested.

    Returns
    -------
    ndarray of bool, shape (M,)
        True for outliers.
    """
    p = np.asarray(positions, float).reshape(-1, 3)
    d = np.asarray(displacements, float).reshape(-1, 3)
    m = len(p)
    out = np.zeros(m, bool)
    if m < 4:
        return out
    k = min(neighbours + 1, m)
    dist, nb = cKDTree(p).query(p, k=k, distance_upper_bound=radius)
    dist, nb = dist[:, 1:], nb[:, 1:]
    have = np.isfinite(dist)
    nd = np.where(have[..., None], d[np.minimum(nb, m - 1)], np.nan)
    with warnings.catch_warnings():  # rows without neighbours: all-NaN medians
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(nd, axis=1)
        res = np.nanmedian(np.abs(nd - med[:, None, :]), axis=1)
    norm = np.abs(d - med) / (res + epsilon)
    tested = have.sum(axis=1) >= 3
    out[tested] = (norm[tested] > threshold).any(axis=1)
    return out


def match_particles(positions_a, positions_b, predicted_b, scale, *,
                    settings: MatchSettings = MatchSettings()) -> Matches:
    """Match particles of A to B around their predicted positions.

    Parameters
    ----------
    positions_a : (Na, 3)
        Particles of exposure A, metres.
    positions_b : (Nb, 3)
        Particles of exposure B, metres.
    predicted_b : (Na, 3)
        Predicted B position of each A particle (:func:`predict_positions`), metres.
    scale : (3,) float
        Resolution cell ``(x, y, z)`` in metres: distances are measured in these units.
    settings : MatchSettings

    Returns
    -------
    Matches
        Tracks sorted by A index. A particle whose position or prediction is not finite (the
        field masked or rejected there) is matched to nothing.
    """
    pa = np.asarray(positions_a, float).reshape(-1, 3)
    pb = np.asarray(positions_b, float).reshape(-1, 3)
    pred = np.asarray(predicted_b, float).reshape(-1, 3)
    sc = np.asarray(scale, float).reshape(3)
    if pred.shape != pa.shape:
        raise ValueError(f"predicted_b has shape {pred.shape}; expected {pa.shape} (one per A)")
    if not (np.isfinite(sc).all() and (sc > 0).all()):
        raise ValueError(f"scale = {scale!r}: expected 3 positive lengths (metres)")
    empty = np.zeros(0, np.int64)
    # a particle with no prediction (the field is masked or rejected there) or no position
    # takes no part; the indices stay those of the tables given
    ok_a = np.flatnonzero(np.isfinite(pa).all(axis=1) & np.isfinite(pred).all(axis=1))
    ok_b = np.flatnonzero(np.isfinite(pb).all(axis=1))
    if len(ok_a) < len(pa) or len(ok_b) < len(pb):
        m = match_particles(pa[ok_a], pb[ok_b], pred[ok_a], sc, settings=settings)
        return replace(m, index_a=ok_a[m.index_a], index_b=ok_b[m.index_b])
    if not len(pa) or not len(pb):
        return Matches(empty, empty, np.zeros(0), np.zeros(0), empty)
    qb, qp = pb / sc, pred / sc
    r = settings.search_radius_cells
    tree_b, tree_p = cKDTree(qb), cKDTree(qp)
    d_ab, j_ab = _two_nearest(tree_b, qp)
    found = d_ab[:, 0] <= r
    ia = np.flatnonzero(found)
    ib = j_ab[found, 0]
    dist = d_ab[found, 0]
    n_cand = np.array([len(c) for c in tree_b.query_ball_point(qp[ia], r)], np.int64)
    # consistency both ways: the B particle's nearest prediction must be this A particle
    d_ba, j_ba = _two_nearest(tree_p, qb[ib])
    mutual = j_ba[:, 0] == ia
    n_mutual = int((~mutual).sum())
    # ratio test both ways: the runner-up, a B particle near the prediction or a prediction
    # near the B particle, must lie clearly further than the partner
    ratio = np.maximum(_ratio(dist, d_ab[found, 1]), _ratio(dist, d_ba[:, 1]))
    quality = 1.0 - ratio
    clear = ratio <= settings.ambiguity_ratio
    n_ambiguous = int((mutual & ~clear).sum())
    keep = mutual & clear
    ia, ib, dist, quality, n_cand = ia[keep], ib[keep], dist[keep], quality[keep], n_cand[keep]
    # the test runs on the deviation from the prediction: the correlation field has removed
    # the resolved flow (gradients included), what is left is position noise and mismatch
    bad = neighbour_median_test(pa[ia] / sc, (pb[ib] - pred[ia]) / sc,
                                threshold=settings.median_threshold,
                                epsilon=settings.median_epsilon_cells,
                                neighbours=settings.neighbours,
                                radius=settings.neighbour_radius)
    keep = ~bad
    return Matches(ia[keep], ib[keep], dist[keep], quality[keep], n_cand[keep],
                   n_mutual, int(bad.sum()), n_ambiguous)


def _two_nearest(tree: cKDTree, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices of the two nearest tree points of each point, (N, 2).

    A missing runner-up (a tree of one point) is at infinite distance.
    """
    k = min(2, tree.n)
    d, j = tree.query(points, k=k)
    d, j = d.reshape(len(points), k), j.reshape(len(points), k)
    if d.shape[1] < 2:
        d = np.hstack([d, np.full((len(points), 1), np.inf)])
        j = np.hstack([j, np.full((len(points), 1), tree.n)])
    return d, j


def _ratio(nearest: np.ndarray, runner_up: np.ndarray) -> np.ndarray:
    """d1/d2 of each match (0 without a runner-up; 1 for a tie at zero distance)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        q = nearest / runner_up
    return np.where(runner_up > 0, np.where(np.isfinite(runner_up), q, 0.0), 1.0)
