"""Ray-bundle particle positions: the 3-D point nearest the rays that saw the particle.

A reconstructed particle is elongated in depth and its centroid inherits that blur; the light
field holds sharper information. :func:`bundle_positions` selects, around each particle's
current estimate, the lit pixels whose rays pass within a beam width of it across every
lenslet that sees it, and solves for the point of least intensity-weighted squared
perpendicular distance to those rays (3 x 3 normal equations per particle), ``iterations``
times from the volume centroid. Effective (air-equivalent) coordinates, metres
(docs/design.md §4); :class:`plenopiv.camera.corrections.DepthCorrection` applies as to centroids.

See docs/methods.md#ray-bundle-positions.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from plenopiv.errors import ReconstructionError
from plenopiv.lightfield import LightField

#: Implementations of :func:`bundle_positions`.
ENGINES = ("numba", "numpy")

__all__ = ["ENGINES", "PARTICLE_BUNDLE", "BundlePositions", "BundleSettings", "RayTable",
           "bundle_positions", "closest_point", "closest_points", "lenslet_table", "lit_rays",
           "ray_lines", "ray_table", "ray_weights", "spatial_order"]


@dataclass(frozen=True)
class BundleSettings:
    """Options of :func:`bundle_positions`.

    Attributes
    ----------
    radius : float
        A ray belongs to a particle when it passes within ``radius`` half beam widths of it
        (dimensionless, > 0). The half beam width at depth Z is
        ``(b |t| + c |1 - t|) / 2`` with b the lenslet footprint, c the aperture cell and
        t = (S_o + Z)/S_o: a pixel sees the particle when its chief ray misses it by less.
    iterations : int
        Solves, each re-selecting the rays around the previous estimate (>= 1; the first one
        starts from the seed).
    seed_depth_error : float
        Depth uncertainty of the seeds, in depth resolution cells (>= 0): the first selection
        widens the radius by the lateral drift of the steepest ray over that depth.
    floor : float
        Pixel values at or below this fraction of the image's maximum carry no weight; above
        it a pixel weighs ``value - floor * max`` (dimensionless, in [0, 1)).
    min_rays : int
        Fewer selected rays than this leave the particle at its seed, flagged (>= 3).
    margin : float
        Lenslet footprints added to every selection radius (>= 0). All rays of a lenslet
        pass through its conjugate, whereas the light reached it anywhere on its footprint,
        so near focus the rays of a lenslet that saw only the rim of a particle's cone miss
        the fitted point by up to a footprint. Without a margin (the tracking's fit, which
        refines afterwards from several starts) such a lenslet is in or out of the selection
        depending on the seed; with half a footprint it is always in, and the fit of an
        isolated particle is the same from any seed within the volume's blur
        (:data:`PARTICLE_BUNDLE`). Beyond focus the current estimate is close and a pixel's
        beam already bounds the miss of its ray, so the margin only takes in neighbours' light
        (in a seeded flow it raises the depth error beyond focus): it applies in full within
        ``margin_cells`` depth cells of focus and fades linearly to zero at twice that.
    margin_cells : float
        See ``margin`` (depth resolution cells, > 0).
    """

    radius: float = 1.5
    iterations: int = 4
    seed_depth_error: float = 0.5
    floor: float = 0.003
    min_rays: int = 6
    margin: float = 0.0
    margin_cells: float = 2.0

    def __post_init__(self):
        if not (np.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"bundle radius = {self.radius!r}: expected a number > 0 "
                             "(half beam widths)")
        if int(self.iterations) != self.iterations or self.iterations < 1:
            raise ValueError(f"bundle iterations = {self.iterations!r}: expected an int >= 1")
        if not (np.isfinite(self.seed_depth_error) and self.seed_depth_error >= 0):
            raise ValueError(f"seed_depth_error = {self.seed_depth_error!r}: expected >= 0 "
                             "depth cells")
        if not (0 <= self.floor < 1):
            raise ValueError(f"bundle floor = {self.floor!r}: expected a fraction in [0, 1)")
        if int(self.min_rays) != self.min_rays or self.min_rays < 3:
            raise ValueError(f"bundle min_rays = {self.min_rays!r}: expected an int >= 3")
        if not (np.isfinite(self.margin) and self.margin >= 0):
            raise ValueError(f"bundle margin = {self.margin!r}: expected >= 0 footprints")
        if not (np.isfinite(self.margin_cells) and self.margin_cells > 0):
            raise ValueError(f"bundle margin_cells = {self.margin_cells!r}: expected > 0 "
                             "depth cells")


#: The fit of the particle table (``[particles] position = "light_field"``): half a footprint
#: of margin makes each particle's position independent of its seed, and so of the voxel grid
#: the seed (the volume's centroid) came from. Three solves: a near-focus particle's spread
#: over random sub-voxel grids halves with each solve and is a small fraction of a voxel
#: after three.
PARTICLE_BUNDLE = BundleSettings(margin=0.5, iterations=3)


@dataclass(frozen=True, eq=False)
class BundlePositions:
    """Ray-bundle positions of N particles (effective coordinates).

    Attributes
    ----------
    position : (N, 3) float64
        ``(x, y, z)`` in metres, effective (air-equivalent) coordinates.
    covariance : (N, 3, 3) float64
        Covariance of each position from the fit, m² (see :func:`bundle_positions`).
    n_rays : (N,) int64
        Rays in the final fit.
    n_lenslets : (N,) int64
        Lenslets those rays came through.
    converged : (N,) bool
        False where too few rays were found (the position is then the seed's).
    light : (N,) float64 or None
        The image's light the final fit gave each particle: the sum of its rays' weights
        (pixel values above the floor, times the particle's share of each), image units.
    """

    position: np.ndarray
    covariance: np.ndarray
    n_rays: np.ndarray
    n_lenslets: np.ndarray
    converged: np.ndarray
    light: np.ndarray | None = None

    def __len__(self) -> int:
        """Return the number of particles."""
        return int(self.position.shape[0])

    @property
    def uncertainty(self) -> np.ndarray:
        """Standard uncertainty per axis ``(x, y, z)``, metres (N, 3)."""
        return np.sqrt(np.maximum(np.einsum("nii->ni", self.covariance), 0.0))


def ray_lines(lf: LightField, rays=None) -> tuple[np.ndarray, np.ndarray]:
    """Every ray of a light field as a line in effective volume coordinates.

    ``rays``: indices of the rays to return (default: all of them).

    Returns
    -------
    origin : (P, 3) float64
        The ray's point on the main-lens plane ``(u_x, u_y, -S_o,eff)``, metres.
    direction : (P, 3) float64
        Unit vector from there to its focal-plane point ``(X_f, 0)``.
    """
    so, u, xf = lf.object_distance, lf.u, lf.focal_plane_position
    u, xf = (u, xf) if rays is None else (u[rays], xf[rays])
    origin = np.column_stack([u, np.full(len(u), -so)])
    d = np.column_stack([xf - u, np.full(len(u), so)])
    return origin, d / np.linalg.norm(d, axis=1, keepdims=True)


def closest_point(origin, direction, weight=None) -> np.ndarray:
    r"""Return the point nearest a bundle of lines in the weighted least-squares sense.

    Parameters
    ----------
    origin : array_like, shape (R, 3)
        A point of each line, metres.
    direction : array_like, shape (R, 3)
        Each line's direction (normalised here; must not be zero).
    weight : array_like, shape (R,), optional
        Non-negative weights (default 1).

    Returns
    -------
    ndarray, shape (3,)
        The point P minimising :math:`\sum_i w_i |(I - d_i d_i^T)(P - a_i)|^2`.

    Raises
    ------
    ValueError
        Fewer than two non-parallel lines carry weight (the point is undefined).

    Notes
    -----
    Setting the gradient to zero gives the normal equations
    :math:`\left(\sum_i w_i M_i\right) P = \sum_i w_i M_i a_i` with the projector
    :math:`M_i = I - d_i d_i^T` onto the plane normal to line i.

    Examples
    --------
    >>> closest_point([[0, 0, 0], [1, 0, 0]], [[1, 0, 0], [0, 1, 0]]).round(12) + 0.0
    array([1., 0., 0.])
    """
    a = np.asarray(origin, float).reshape(-1, 3)
    d = np.asarray(direction, float).reshape(-1, 3)
    w = np.ones(len(a)) if weight is None else np.asarray(weight, float).reshape(-1)
    if len(d) != len(a) or len(w) != len(a):
        raise ValueError(f"origin, direction and weight must have the same length; got "
                         f"{len(a)}, {len(d)}, {len(w)}")
    p, _, ok = closest_points(np.zeros(len(a), np.int64), a, d, w, 1)
    if not ok[0]:
        raise ValueError("the lines do not define a point: fewer than two non-parallel "
                         "lines with positive weight")
    return p[0]


def closest_points(group, origin, direction, weight, n_groups: int):
    """:func:`closest_point` for many bundles at once.

    Parameters
    ----------
    group : (R,) int
        Bundle index of each line, in ``[0, n_groups)``.
    origin, direction : (R, 3)
        Lines, as in :func:`closest_point` (directions need not be unit vectors).
    weight : (R,)
        Non-negative weights.
    n_groups : int

    Returns
    -------
    point : (n_groups, 3)
        NaN for bundles without a solution.
    normal : (n_groups, 3, 3)
        The normal matrix ``sum_i w_i M_i`` of each bundle.
    ok : (n_groups,) bool
        The normal matrix is well conditioned (reciprocal condition number > 1e-12).
    """
    g = np.asarray(group, np.int64)
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    a = np.asarray(origin, float)
    w = np.asarray(weight, float)
    normal = np.empty((n_groups, 3, 3))
    rhs = np.empty((n_groups, 3))
    eye = np.eye(3)
    for i in range(3):
        for j in range(3):
            m_ij = eye[i, j] - d[:, i] * d[:, j]
            normal[:, i, j] = np.bincount(g, w * m_ij, n_groups)
        ma = a[:, i] - d[:, i] * np.einsum("ij,ij->i", d, a)
        rhs[:, i] = np.bincount(g, w * ma, n_groups)
    point, ok = _solve(normal, rhs)
    return point, normal, ok


def _solve(normal, rhs):
    """Solve each well-conditioned 3 x 3 system (reciprocal condition > 1e-12); NaN else."""
    point = np.full((len(normal), 3), np.nan)
    ev = np.linalg.eigvalsh(normal)
    ok = (ev[:, -1] > 0) & (ev[:, 0] > 1e-12 * np.maximum(ev[:, -1], 1e-300))
    if ok.any():
        point[ok] = np.linalg.solve(normal[ok], rhs[ok][..., None])[..., 0]
    return point, ok


def lenslet_table(lf: LightField):
    """Rays grouped by lenslet: ``(order, ptr, conjugates, has)``.

    ``order`` sorts the rays by lenslet, lenslet L's rays are ``order[ptr[L]:ptr[L + 1]]``,
    ``conjugates`` (K, 2) is each lenslet's focal-plane point X_f (metres) and ``has`` marks
    the lenslets with rays (K = largest lenslet index + 1). Within a lenslet the rays run down
    in aperture y, which the kernels' bisection needs (:func:`_lenslet_order`).
    """
    order = _lenslet_order(lf.lenslet, lf.u[:, 1])
    lens = lf.lenslet[order]
    k = int(lf.lenslet.max()) + 1 if lf.n_rays else 0
    ptr = np.searchsorted(lens, np.arange(k + 1))
    conj = np.zeros((k, 2))
    has = ptr[1:] > ptr[:-1]
    conj[has] = lf.focal_plane_position[order[ptr[:-1][has]]]
    return order, ptr, conj, has


def _lenslet_order(lenslet, u_y) -> np.ndarray:
    """Order of rays by lenslet and, within one, down in aperture y ``u_y`` (metres).

    The sensor's row order, kept by a stable sort on the lenslet, gives the second key where
    it already runs down in y; otherwise the rays are sorted on both keys.
    """
    order = np.argsort(lenslet, kind="stable")
    lens = lenslet[order]
    if np.any(np.diff(u_y[order])[lens[1:] == lens[:-1]] > 0.0):
        order = np.lexsort((-u_y, lenslet))
    return order


def lit_rays(lf: LightField, image, floor: float) -> LightField:
    """The rays of ``lf`` whose pixel in ``image`` exceeds ``floor`` times the maximum.

    Rays at or below the floor carry no weight in :func:`bundle_positions`, so a fit on these
    alone is the same (half the rays at 16 MP). They come in the order of
    :func:`lenslet_table`, so that :func:`ray_table` uses their arrays in place.
    """
    values = lf.values(image)
    keep = np.flatnonzero(values > floor * float(values.max(initial=0.0)))
    return lf.subset(keep[_lenslet_order(lf.lenslet[keep], lf.u[keep, 1])])


class RayTable(NamedTuple):
    """A light field's rays grouped by lenslet (:func:`ray_table`), shared by every image.

    Attributes
    ----------
    order, ptr : (P,), (K + 1,) int
        Lenslet L's rays are ``order[ptr[L]:ptr[L + 1]]`` (:func:`lenslet_table`).
    lens_ids : (L,) int
        The lenslets with rays.
    tree : cKDTree
        Their focal-plane points X_f (metres).
    focal : (P, 2) float64
        Every ray's focal-plane point X_f, metres (the light field's order).
    u, focal_sorted : (P, 2) float64
        Aperture point u and X_f of the rays in lenslet order, metres (contiguous).
    """

    order: np.ndarray
    ptr: np.ndarray
    lens_ids: np.ndarray
    tree: cKDTree
    focal: np.ndarray
    u: np.ndarray
    focal_sorted: np.ndarray


def ray_table(lf: LightField) -> RayTable:
    """Group the rays of ``lf`` by lenslet (:class:`RayTable`; built once per light field).

    A light field already in that order (:func:`lit_rays`) lends its own arrays instead of
    sorted copies.
    """
    order, ptr, conj, has = lenslet_table(lf)
    xf = lf.focal_plane_position
    in_order = bool(np.all(order[1:] > order[:-1]))   # a permutation: the identity
    u, xf_sorted = (lf.u, xf) if in_order else (lf.u[order], xf[order])
    return RayTable(order, ptr, np.flatnonzero(has), cKDTree(conj[has]), xf,
                    np.ascontiguousarray(u, np.float64), np.ascontiguousarray(xf_sorted,
                                                                              np.float64))


def _selection_radius(lf: LightField, settings: BundleSettings, depth, depth_cell: float, *,
                      first: bool) -> np.ndarray:
    """Radius of a solve's ray selection around estimates at effective depth ``depth``, m.

    ``radius`` half beam widths; on the ``first`` solve widened by the steepest ray's drift
    over ``seed_depth_error`` depth cells; plus ``margin`` footprints within
    ``margin_cells`` depth cells of focus, none beyond twice that, linear between (see
    :class:`BundleSettings`).
    """
    depth = np.asarray(depth, float)
    widen = (lf.aperture_radius / lf.object_distance * settings.seed_depth_error * depth_cell
             if first else 0.0)
    fade = np.clip(2.0 - np.abs(depth) / (settings.margin_cells * depth_cell), 0.0, 1.0)
    return (settings.radius * _half_beam(lf, depth) + widen
            + settings.margin * fade * lf.footprint)


def _half_beam(lf: LightField, depth) -> np.ndarray:
    """Half width of a pixel's beam at effective depth ``depth`` (metres)."""
    t = (lf.object_distance + np.asarray(depth, float)) / lf.object_distance
    return 0.5 * (lf.footprint * np.abs(t) + lf.cell * np.abs(1.0 - t))


def checked_image(lf: LightField, image, engine: str) -> np.ndarray:
    """Return ``image`` as an array after checking it is the light field's sensor.

    Raises ValueError for an engine not in ``ENGINES``, ReconstructionError for an image of
    another shape.
    """
    if engine not in ENGINES:
        raise ValueError(f"engine = {engine!r}: expected one of {ENGINES}")
    img = np.asarray(image)
    if img.shape != tuple(lf.shape):
        raise ReconstructionError(f"image is {img.shape}; the light field's sensor is "
                                  f"{tuple(lf.shape)}")
    return img


def _checked_inputs(lf: LightField, image, seeds, settings: BundleSettings, engine: str):
    """Return the seeds as (N, 3) floats and each ray's light above the floor (float64).

    Raises ValueError for an unknown engine or non-finite seeds, ReconstructionError for an
    image that is not the light field's sensor.
    """
    img = checked_image(lf, image, engine)
    seeds = np.asarray(seeds, float).reshape(-1, 3)
    if not np.isfinite(seeds).all():
        raise ValueError("seed positions contain NaN or infinity")
    return seeds, ray_weights(lf, img, settings.floor)


def ray_weights(lf: LightField, image, floor: float) -> np.ndarray:
    """Each ray's light above ``floor`` times the image's brightest ray (float64, P)."""
    values = lf.values(image).astype(np.float64)
    top = float(values.max()) if len(values) else 0.0
    return np.maximum(values - floor * top, 0.0)


def _engine_inputs(lf: LightField, table: RayTable, weight, engine: str) -> tuple:
    """What each engine of :func:`bundle_positions` reads, built once for every solve.

    ``(rays, total, (origin, direction))``: for the numba kernels the rays in lenslet order
    (aperture points, focal-plane points, pixel weights) and a buffer for the rays' summed
    shares (P,); for NumPy the ray lines (:func:`ray_lines`). The other engine's parts are
    None.
    """
    if engine != "numba":
        return None, None, ray_lines(lf)
    rays = (table.u, table.focal_sorted, np.ascontiguousarray(weight[table[0]], np.float64))
    return rays, np.zeros(lf.n_rays), (None, None)


def bundle_positions(lf: LightField, image, seeds, *,
                     settings: BundleSettings = BundleSettings(), depth_cell: float | None = None,
                     brightness=None, chunk: int = 1024,
                     engine: str = "numba", table: RayTable | None = None) -> BundlePositions:
    r"""Refine particle positions to the point nearest the bundle of rays that saw each.

    Parameters
    ----------
    lf : LightField
        The calibrated light field (of the recording's f-number).
    image : ndarray, shape ``lf.shape``
        The raw image (dark-subtracted for real data).
    seeds : array_like, shape (N, 3)
        First estimates ``(x, y, z)`` in effective coordinates, metres (volume centroids).
    settings : BundleSettings
    depth_cell : float, optional
        Depth resolution cell, metres, for ``settings.seed_depth_error`` (default
        ``footprint * S_o / (2 R)`` with R the aperture radius).
    brightness : array_like, shape (N,), optional
        Relative brightness of each particle (e.g. the volume's integrated intensity), for
        sharing the rays that pass several particles (default: all equal).
    chunk : int
        Particles per vectorised ray selection (``engine="numpy"``; memory only).
    engine : {"numba", "numpy"}
        The compiled kernels (default) or their plain NumPy twin (same estimator).
    table : RayTable, optional
        :func:`ray_table` of ``lf``, when already built (one per light field serves every
        image).

    Returns
    -------
    BundlePositions

    Notes
    -----
    Rays: ``a_i = (u_i, -S_o)``, direction ``(X_f,i - u_i, S_o)``. A ray i passing particle p
    at miss distance m (its lateral distance at the particle's depth) within the selection
    radius r_p is expected to carry ``k_ip = B_p (1 - m/r_p)`` of its light (B_p the
    brightness, the beam profile taken as a cone); its weight for particle p is its share of
    the pixel value, ``w_ip = max(I_i - floor, 0) k_ip / sum_q k_iq``, so that a pixel lit by
    two particles does not pull each towards the other. An isolated particle weighs its rays
    by their values. The point solves :math:`(\sum_i w_i M_i) P = \sum_i w_i M_i a_i`
    (:func:`closest_point`).

    Covariance: the sandwich (cluster-robust) estimator with the lenslets as clusters, plus
    the quantisation of the lenslet plane. All rays of one lenslet pass through its
    conjugate X_f = s/M, whereas the light reached it anywhere on its footprint b (t b at
    depth Z), so each lenslet's bundle is placed with a lateral error of variance
    (t b)²/12. With :math:`A = \sum_i w_i M_i`, the residual
    :math:`r_i = M_i (P - a_i)` and per lenslet k the sums :math:`g_k = \sum_{i \in k} w_i r_i`,
    :math:`W_k = \sum_{i \in k} w_i`, :math:`\bar M_k = \sum_{i \in k} w_i M_i / W_k`:

    .. math:: C_r = A^{-1}\Big(\sum_k g_k g_k^T\Big) A^{-1},\qquad
              C_q = A^{-1}\frac{(t b)^2}{12}\sum_k\Big(W_k^2\,\bar M_k \Pi \bar M_k
              + \frac{v_k v_k^T}{\mathrm{var}_k\theta}\Big) A^{-1}

    with Π the lateral projector diag(1, 1, 0), θ the rays' slopes, var_k θ their weighted
    variance in lenslet k and :math:`v_k = \sum_{i\in k} w_i M_i (\theta_i - \bar\theta_k, 0)`:
    the first term shifts the lenslet's fan sideways, the second moves its convergence point
    in depth. The reported variance per axis is the larger of C_r and C_q (the residuals of a
    many-lenslet bundle already hold the quantisation), with the correlations of
    C_r + C_q. A particle seen through one lenslet (near focus) has no residual scatter and
    so gets σ_x = t b/√12 and a depth uncertainty of its depth of field.
    """
    seeds, weight = _checked_inputs(lf, image, seeds, settings, engine)
    n = len(seeds)
    table = ray_table(lf) if table is None else table
    index = tuple(table[:4])                   # order, ptr, lens_ids, tree
    rays, total, (origin, direction) = _engine_inputs(lf, table, weight, engine)
    depth_cell = (lf.footprint * lf.object_distance / (2.0 * lf.aperture_radius)
                  if depth_cell is None else depth_cell)
    bright = np.ones(n) if brightness is None else np.asarray(brightness, float).reshape(n)
    # the kernels read each particle's lenslets from memory: in spatial order neighbours
    # find them in cache; each particle's sums are unchanged
    perm = spatial_order(lf, seeds) if engine == "numba" else np.arange(n)
    seeds, bright = seeds[perm], bright[perm]
    pos, ok = seeds.copy(), np.ones(n, bool)
    pool: dict = {}                            # the numba selections' buffers, reused
    for it in range(settings.iterations):
        radius = _selection_radius(lf, settings, pos[:, 2], depth_cell, first=it == 0)
        if engine == "numba":
            sel, normal, rhs, nr = _numba_normal_equations(lf, index, rays, pos, radius,
                                                           bright, total, pool)
            p, good = _solve(normal, rhs)
        else:
            pid, ray, w = _shared_rays(lf, index, pos, radius, weight, bright, chunk)
            nr = np.bincount(pid, w > 0, n)
            p, normal, good = closest_points(pid, origin[ray], direction[ray], w, n)
        good &= nr >= settings.min_rays
        pos = np.where(good[:, None], p, pos)
        ok = good
    pos = np.where(ok[:, None], pos, seeds)
    if engine == "numba":
        cov, n_lens = _numba_covariance(lf, rays, sel, bright, total, pos, normal, ok)
    else:
        cov, n_lens = _covariance(lf, pid, ray, w, origin, direction, pos, normal, ok)
    back = np.argsort(perm)                    # the caller's order
    light = 0.5 * np.trace(normal, axis1=1, axis2=2)      # the trace of each ray's M is 2
    return BundlePositions(pos[back], cov[back], nr.astype(np.int64)[back], n_lens[back],
                           ok[back], light[back])


def spatial_order(lf: LightField, points, band: float = 4.0) -> np.ndarray:
    """Order of ``points`` (N, 3; effective, metres) by where their light reaches the lenslets.

    A particle's candidate lenslets lie around its conjugate ``(x, y) / t`` on the focal
    plane (t = (S_o + Z)/S_o): the points are sorted into bands of ``band`` lenslet
    footprints in y, then by x within a band, so that consecutive particles share most of
    their lenslets (a permutation (N,) int).
    """
    p = np.asarray(points, float).reshape(-1, 3)
    t = (lf.object_distance + p[:, 2]) / lf.object_distance
    t = np.where(np.abs(t) > 1e-12, t, 1e-12)
    conj = p[:, :2] / t[:, None]
    return np.lexsort((conj[:, 0], np.floor(conj[:, 1] / (band * lf.footprint))))


def _candidates(lf, index, centre, radius):
    """Candidate lenslets of each particle as CSR ``(lptr (N+1,), lidx)`` (lenslet ids)."""
    _, _, lens_ids, tree = index
    so, ap = lf.object_distance, lf.aperture_radius
    t = (so + centre[:, 2]) / so
    reach = (ap * np.abs(1.0 - t) + radius) / np.abs(t)
    lists = tree.query_ball_point(centre[:, :2] / t[:, None], reach)
    return flat_lists(lists, lens_ids)


def flat_lists(lists, ids) -> tuple[np.ndarray, np.ndarray]:
    """A KD-tree's lists of neighbours as CSR: ``(ptr (N + 1,), ids[neighbours])`` int64."""
    counts = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    ptr = np.zeros(len(lists) + 1, np.int64)
    np.cumsum(counts, out=ptr[1:])
    flat = np.fromiter(itertools.chain.from_iterable(lists), np.int64, int(ptr[-1]))
    return ptr, np.asarray(ids, np.int64)[flat]


def _threads() -> int:
    """Threads of the numba kernels."""
    import numba

    return numba.get_num_threads()


class RaySelection(NamedTuple):
    """The rays one solve of :func:`bundle_positions` reads (numba path), selected once.

    Attributes
    ----------
    lptr, lidx : (N + 1,), (C,) int64
        Candidate lenslets of each particle (CSR, lenslet ids).
    cptr : (C + 1,) int64
        Candidate ``a``'s rays are ``ray[cptr[a]:cptr[a + 1]]``.
    ray : (S,) int64
        Rows of the lenslet-sorted ray arrays of :class:`RayTable` passing within the radius
        of their particle and carrying weight (a pixel above the floor).
    share : (S,) float64
        Their cone profile ``1 - m/r`` (m the miss distance, r the radius).
    """

    lptr: np.ndarray
    lidx: np.ndarray
    cptr: np.ndarray
    ray: np.ndarray
    share: np.ndarray

    @property
    def particle_ptr(self) -> np.ndarray:
        """Particle p's rays are ``ray[particle_ptr[p]:particle_ptr[p + 1]]`` (N + 1,)."""
        return self.cptr[self.lptr]


def ray_selection(lf: LightField, index, rays, centre, radius,
                  pool: dict | None = None) -> RaySelection:
    """Select the rays within ``radius`` (N,) of ``centre`` (N, 3) that carry weight, once.

    ``index``: ``(order, ptr, lens_ids, tree)`` of :class:`RayTable`; ``rays``: the lenslet-
    sorted ``(u, X_f, weight)`` of :func:`_engine_inputs`. Blocks of particles (balanced by
    their candidate lenslets) run on the numba kernels in threads, twice:
    :func:`~plenopiv.particles._bundle_kernels.count_rays` counts each candidate's rays,
    :func:`~plenopiv.particles._bundle_kernels.fill_rays` writes them into arrays of the exact
    size. The result is in particle,
    candidate, ray order, as the passes of one solve read it (NumPy twin:
    :func:`_select_rays`).

    ``pool``: a dict whose ``"ray"`` and ``"share"`` buffers are reused when large enough
    (and grown in it otherwise): the selections of a fit's solves are about the same size, and
    fresh arrays of this size (a third of a gigabyte at 16 MP) cost more in page faults than
    the pass that fills them. The selection then holds views of the pool's buffers, valid
    until the pool's next use.
    """
    from concurrent.futures import ThreadPoolExecutor

    from plenopiv.particles import _bundle_kernels as _k

    ptr = index[1].astype(np.int64)
    lptr, lidx = _candidates(lf, index, centre, radius)
    u, xf, w = rays
    n = len(centre)
    c, r = (np.ascontiguousarray(a, np.float64) for a in (centre, radius))
    counts = np.zeros(len(lidx), np.int64)
    threads = _threads()
    n_blocks = max(1, min(n, 4 * threads))
    edges = np.searchsorted(lptr, np.linspace(0, lptr[-1], n_blocks + 1)).astype(np.int64)
    edges[0], edges[-1] = 0, n
    spans = [(int(edges[b]), int(edges[b + 1])) for b in range(n_blocks)
             if edges[b + 1] > edges[b]]
    so, margin = lf.object_distance, lf.cell
    cptr = np.zeros(len(lidx) + 1, np.int64)

    def count(span):
        _k.count_rays(c, r, lptr, lidx, ptr, u, xf, so, margin, w, span[0], span[1], counts)

    def fill(span):
        _k.fill_rays(c, r, lptr, lidx, ptr, u, xf, so, margin, w, span[0], span[1], cptr,
                     ray, share)

    def run(task):
        if len(spans) > 1 and threads > 1:
            with ThreadPoolExecutor(threads) as pool_:
                list(pool_.map(task, spans))
        else:
            for span in spans:
                task(span)

    run(count)
    np.cumsum(counts, out=cptr[1:])
    size = int(cptr[-1])
    pool = {} if pool is None else pool
    if "ray" not in pool or len(pool["ray"]) < size:
        pool["ray"], pool["share"] = None, None             # the old buffers first
        pool["ray"] = np.empty(size + size // 4, np.int64)
        pool["share"] = np.empty(size + size // 4)
    ray, share = pool["ray"][:size], pool["share"][:size]
    run(fill)
    return RaySelection(lptr, lidx, cptr, ray, share)


def _numba_normal_equations(lf, index, rays, centre, radius, bright, total, pool):
    """Run one solve on the numba path: one ray selection, ray shares, normal equations.

    ``total`` (P,) receives the rays' summed shares (overwritten); ``pool``: the selection's
    buffers (:func:`ray_selection`). Returns ``(selection, normal (N, 3, 3), rhs (N, 3),
    rays with weight (N,))``.
    """
    from plenopiv.particles import _bundle_kernels as _k

    sel = ray_selection(lf, index, rays, centre, radius, pool)
    u, xf, w = rays
    n = len(centre)
    b = np.ascontiguousarray(bright, np.float64)
    sptr = sel.particle_ptr
    total.fill(0.0)
    _k.selected_totals(sptr, sel.share, b, sel.ray, total)
    normal, rhs, nr = np.zeros((n, 3, 3)), np.zeros((n, 3)), np.zeros(n, np.int64)
    _k.selected_normal_equations(sptr, sel.ray, sel.share, b, u, xf, lf.object_distance, w,
                                 total, normal, rhs, nr)
    return sel, normal, rhs, nr


def _numba_covariance(lf, rays, sel, bright, total, point, normal, ok):
    """Return :func:`_covariance` by the numba path (same estimator, the last solve's rays)."""
    from plenopiv.particles import _bundle_kernels as _k

    n = len(point)
    u, xf, w = rays
    meat_r, meat_q = np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
    n_lens = np.zeros(n, np.int64)
    b, pt = (np.ascontiguousarray(a, np.float64) for a in (bright, point))
    _k.selected_covariance_sums(sel.lptr, sel.cptr, sel.ray, sel.share, b, u, xf,
                                lf.object_distance, w, total, pt, lf.footprint, meat_r, meat_q,
                                n_lens)
    return _combine(normal, meat_r, meat_q, ok), n_lens


def _combine(normal, meat_r, meat_q, ok):
    """Covariance from the two meats: per axis the larger variance (see bundle_positions)."""
    cov = np.full((len(normal), 3, 3), np.nan)
    good = np.flatnonzero(ok)
    if len(good):
        inv = np.linalg.inv(normal[good])
        c_r, c_q = inv @ meat_r[good] @ inv, inv @ meat_q[good] @ inv
        # the scatter the fit sees and the quantisation it cannot see overlap (the
        # residuals of a many-lenslet bundle hold the quantisation): per axis the larger
        # variance, with the correlations of their sum
        both = c_r + c_q
        sd = np.sqrt(np.maximum(np.einsum("nii->ni", both), 1e-300))
        keep = np.sqrt(np.maximum(np.einsum("nii->ni", c_r), np.einsum("nii->ni", c_q)))
        cov[good] = both / (sd[:, :, None] * sd[:, None, :]) * (keep[:, :, None]
                                                                 * keep[:, None, :])
    return cov


def _shared_rays(lf, index, pos, radius, weight, bright, chunk):
    """(particle, ray, weight) of every ray within ``radius`` (N,) of a particle.

    A ray that passes several particles is shared among them in proportion to their expected
    contributions (beam overlap x brightness).
    """
    pid, ray, share = [], [], []
    for lo in range(0, len(pos), chunk):
        hi = min(len(pos), lo + chunk)
        p_, r_, m_ = _select_rays(lf, *index, pos[lo:hi], radius[lo:hi])
        pid.append(p_ + lo)
        ray.append(r_)
        share.append(np.maximum(1.0 - m_ / radius[p_ + lo], 0.0) * bright[p_ + lo])
    pid, ray, share = (np.concatenate(a) for a in (pid, ray, share))
    total = np.bincount(ray, share, lf.n_rays)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = weight[ray] * np.where(total[ray] > 0, share / total[ray], 0.0)
    return pid, ray, w


def _select_rays(lf, order, ptr, lens_ids, tree, centre, radius):
    """(particle, ray, miss) of the rays passing within ``radius`` (N,) of ``centre`` (N, 3)."""
    so, ap = lf.object_distance, lf.aperture_radius
    t = (so + centre[:, 2]) / so
    reach = (ap * np.abs(1.0 - t) + radius) / np.abs(t)
    lists = tree.query_ball_point(centre[:, :2] / t[:, None], reach)
    counts = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    if counts.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    pid = np.repeat(np.arange(len(lists)), counts)
    lens = lens_ids[np.concatenate([np.asarray(x, np.int64) for x in lists])]
    n_r = ptr[lens + 1] - ptr[lens]
    pid = np.repeat(pid, n_r)
    first = np.repeat(ptr[lens] - (np.cumsum(n_r) - n_r), n_r)
    ray = order[first + np.arange(len(first))]
    xy = lf.u[ray] * (1.0 - t[pid, None]) + lf.focal_plane_position[ray] * t[pid, None]
    miss = np.hypot(*(xy - centre[pid, :2]).T)
    keep = miss <= radius[pid]
    return pid[keep], ray[keep], miss[keep]


def _covariance(lf, pid, ray, w, origin, direction, point, normal, ok):
    """Sandwich covariance clustered by lenslet (see :func:`bundle_positions`)."""
    n = len(point)
    cov = np.full((n, 3, 3), np.nan)
    n_lens = np.zeros(n, np.int64)
    if not len(pid):
        return cov, n_lens
    use = w > 0
    pid, ray, w = pid[use], ray[use], w[use]
    if not len(pid):
        return cov, n_lens
    d = direction[ray]
    diff = point[pid] - origin[ray]
    r = diff - d * np.einsum("ij,ij->i", d, diff)[:, None]
    # cluster = (particle, lenslet)
    n_k = int(lf.lenslet.max()) + 1
    uniq, cl = np.unique(pid * n_k + lf.lenslet[ray], return_inverse=True)
    n_cl = len(uniq)
    cl_pid = uniq // n_k
    n_lens = np.bincount(cl_pid, minlength=n)
    wk = np.bincount(cl, w, n_cl)
    g = np.stack([np.bincount(cl, w * r[:, i], n_cl) for i in range(3)], axis=1)
    mw = np.empty((len(w), 3, 3))
    eye = np.eye(3)
    for i in range(3):
        for j in range(3):
            mw[:, i, j] = w * (eye[i, j] - d[:, i] * d[:, j])
    mbar = np.stack([np.stack([np.bincount(cl, mw[:, i, j], n_cl) for j in range(3)], axis=1)
                     for i in range(3)], axis=1) / wk[:, None, None]
    t = (lf.object_distance + point[cl_pid, 2]) / lf.object_distance
    var_q = (t * lf.footprint) ** 2 / 12.0
    # lateral placement of the lenslet's fan: a shift delta of all its rays
    lat = (wk ** 2)[:, None, None] * (mbar[:, :, :2] @ mbar[:, :2, :])
    # convergence of the fan: its rays are spread over the footprint, not through one point,
    # so they tilt by dtheta * eps with eps of variance var_q / var(theta)
    theta = d[:, :2] / d[:, 2:3]
    mean = np.stack([np.bincount(cl, w * theta[:, i], n_cl) for i in range(2)], axis=1)
    dth = theta - mean[cl] / wk[cl, None]
    var_t = np.bincount(cl, w * (dth ** 2).sum(axis=1), n_cl) / wk
    v = np.einsum("nij,nj->ni", mw[:, :, :2], dth)
    v = np.stack([np.bincount(cl, v[:, i], n_cl) for i in range(3)], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        # (a lenslet with one ray, or rays of one slope, has no convergence to place; the
        # slopes of one lenslet's pixels differ by a cell / S_o ~ 0.01, variance ~ 1e-4)
        v = np.where(var_t[:, None] > 1e-12, v / np.sqrt(var_t)[:, None], 0.0)
    meat_r = np.zeros((n, 3, 3))
    np.add.at(meat_r, cl_pid, g[:, :, None] * g[:, None, :])
    meat_q = np.zeros((n, 3, 3))
    np.add.at(meat_q, cl_pid, var_q[:, None, None] * (lat + v[:, :, None] * v[:, None, :]))
    cov = _combine(normal, meat_r, meat_q, ok)
    return cov, n_lens
