"""Particle tracks between two exposures, and their binning onto the vector grid."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from plenopiv.products.vectors import VectorResult


@dataclass(frozen=True, eq=False)
class TrackResult:
    """Particle tracks between exposures A and B (physical coordinates, metres).

    Attributes
    ----------
    position_a, position_b : (N, 3)
        Ray-bundle positions ``(x, y, z)`` at the two exposures, depth corrections applied.
    uncertainty_a, uncertainty_b : (N, 3)
        Standard uncertainty of those positions from the bundle fits, metres.
    quality : (N,)
        Match uniqueness 1 - d1/d2 (:class:`plenopiv.tracking.matching.Matches`).
    residual_cells : (N,)
        Distance of the B particle from its PIV prediction, resolution cells.
    index_a, index_b : (N,) int
        Rows of the particle tables of the two volumes.
    n_lenslets_a, n_lenslets_b : (N,) int
        Lenslets whose rays fixed each position (1: the particle is in focus and its
        lateral position is known to a footprint only).
    dt : float or None
        Seconds between the exposures.
    counts : dict
        Particles in A and B, bundle fits that failed, matches dropped by each test.
    """

    position_a: np.ndarray
    position_b: np.ndarray
    uncertainty_a: np.ndarray
    uncertainty_b: np.ndarray
    quality: np.ndarray
    residual_cells: np.ndarray
    index_a: np.ndarray
    index_b: np.ndarray
    n_lenslets_a: np.ndarray
    n_lenslets_b: np.ndarray
    dt: float | None = None
    counts: dict = field(default_factory=dict)

    def __len__(self) -> int:
        """Return the number of tracks."""
        return int(len(self.position_a))

    @property
    def displacement(self) -> np.ndarray:
        """B - A, metres (N, 3)."""
        return self.position_b - self.position_a

    @property
    def uncertainty(self) -> np.ndarray:
        """Standard uncertainty of the displacement per axis (independent fits), metres."""
        return np.hypot(self.uncertainty_a, self.uncertainty_b)

    @property
    def velocity(self) -> np.ndarray | None:
        """Displacement / dt in m/s, or None without dt."""
        return None if self.dt is None else self.displacement / self.dt


def bin_tracks(tracks: TrackResult, vectors: VectorResult, *, min_tracks: int = 1
               ) -> VectorResult:
    """Average the tracks onto the PIV grid: Eulerian field of the vectors' schema.

    Each track counts in the grid cell (centred on a vector, one grid step wide) holding its
    mid-point (A + B)/2. ``u, v, w`` are the mean displacements (metres), ``valid`` where at
    least ``min_tracks`` tracks fell, ``snr`` holds the number of tracks of the cell.
    """
    shape = (len(vectors.z), len(vectors.y), len(vectors.x))
    mid = 0.5 * (tracks.position_a + tracks.position_b)
    idx = []
    for k, axis in enumerate((vectors.z, vectors.y, vectors.x)):
        a = np.asarray(axis, float)
        step = a[1] - a[0] if len(a) > 1 else np.inf
        i = np.rint((mid[:, 2 - k] - a[0]) / step) if np.isfinite(step) else np.zeros(len(mid))
        idx.append(i.astype(np.int64) if len(mid) else np.zeros(0, np.int64))
    idx = np.array(idx).reshape(3, -1)
    inside = np.all((idx >= 0) & (idx < np.array(shape)[:, None]), axis=0)
    flat = np.ravel_multi_index(idx[:, inside], shape) if inside.any() else np.zeros(0, int)
    n = np.bincount(flat, minlength=int(np.prod(shape)))
    d = tracks.displacement[inside]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = [np.bincount(flat, d[:, c], n.size) / n for c in range(3)]
    valid = (n >= min_tracks).reshape(shape)
    comp = [np.where(valid, m.reshape(shape), 0.0) for m in mean]
    return VectorResult(np.asarray(vectors.x), np.asarray(vectors.y), np.asarray(vectors.z),
                        comp[0], comp[1], comp[2], valid, n.reshape(shape).astype(float),
                        vectors.dt, 0)

