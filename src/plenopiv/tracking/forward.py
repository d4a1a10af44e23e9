r"""Forward-model refinement of particle positions: the pixel values a position predicts.

The ray bundle (:mod:`plenopiv.tracking.bundle`) treats every lit pixel as its chief ray, the
line from the centre of its aperture cell to the centre of its lenslet's footprint. Near the
focal plane that model loses the depth: a particle within a footprint-wide beam lights the
pixel whatever its place in the beam, all chief rays of a lenslet meet at the lenslet's
conjugate (Z = 0), and a particle seen through one to a few lenslets is drawn to Z = 0 or
pushed away from it by up to half a depth resolution cell. The information is in *which*
pixels are lit and how much: the edges of the lit patch in each micro-image move with depth.

A pixel is a beam: the lines from its aperture cell (width c at the main lens) to its lenslet
footprint (width b on the focal plane). At a particle's depth, t = (S_o + Z)/S_o, the
aperture cell spans ``w_a = c |1 - t|`` and the footprint ``w_b = b |t|``, both centred on
the chief ray (lateral miss m from the particle). The fraction of the particle's light
through the aperture cell that lands in the footprint is, per axis, the overlap of two
intervals,

.. math:: f(m) = \frac{o_x(m_x)\, o_y(m_y)}{w_a^2},\qquad
          o(m) = \max\big(0, \min(\tfrac{w_a}{2}, m + \tfrac{w_b}{2})
                 - \max(-\tfrac{w_a}{2}, m - \tfrac{w_b}{2})\big),

a trapezoid in m: flat across the beam, with ramps one aperture cell wide where the pixel
sees part of the particle's light. The predicted pixel value is ``A f`` with A the
particle's amplitude. The refinement moves each particle, from its ray-bundle position, to
the position whose prediction fits the pixel values around its beam best, by a search on
grids: joint depth x lateral grids around the start over halving ranges. Near focus depth
and lateral position trade off along a line through a footprint's corner (an edge of the lit
patch fixes only the ratio of lateral offset to depth), a valley that searches along one
axis at a time cross without following it. The misfit is
one-sided (:func:`refine_positions`): light the particle does not explain, a neighbour's
whose rays cross its beam, weighs little; light it predicts but that is missing weighs in
full. So a neighbour's rays (of a particle the reconstruction found or missed) do not pull
it, and the dark pixels around the lit patch fix its edges.

A particle in focus seen through a single lenslet lights all its pixels at any depth within
the depth of field: the image holds no depth there, and the position stays at the start.

Effective (air-equivalent) coordinates, metres, as in :mod:`plenopiv.tracking.bundle`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plenopiv.lightfield import LightField
from plenopiv.tracking.bundle import ENGINES, checked_image, lenslet_table

__all__ = ["ENGINES", "ForwardSettings", "beam_fraction", "refine_positions"]

#: Implementations of :func:`refine_positions`.


@dataclass(frozen=True)
class ForwardSettings:
    """Options of :func:`refine_positions`.

    Attributes
    ----------
    depth_range : float
        Half range of the depth search around the start, in depth resolution cells (> 0).
    depth_steps : int
        Depth grid points of each search (odd, >= 3).
    lateral_range : float
        Half range of the lateral search, in lenslet footprints (> 0), on a 5 x 5 grid.
    margin : float
        Pixels are taken within ``margin`` beam half widths of the start plus the lateral
        drift of the steepest ray over the depth range (dimensionless, >= 1).
    excess : float
        Light in a pixel beyond the prediction (a neighbour's, seen or missed) counts at most
        ``excess`` times the particle's amplitude (dimensionless, > 0); light missing from a
        pixel the candidate predicts lit counts in full.
    rounds : int
        After a joint depth x lateral grid search over the full ranges, ``rounds`` more joint
        searches, the n-th over ranges halved n times (>= 1).
    round_depth_steps : int
        Depth grid points of each of those later searches (odd, >= 3), times the 5 x 5
        lateral grid.
    """

    depth_range: float = 0.6
    depth_steps: int = 13
    lateral_range: float = 0.25
    margin: float = 1.5
    excess: float = 0.2
    rounds: int = 3
    round_depth_steps: int = 7

    def __post_init__(self):
        for name in ("depth_range", "lateral_range", "excess"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"forward {name} = {v!r}: expected a number > 0")
        for name in ("depth_steps", "round_depth_steps"):
            v = getattr(self, name)
            if int(v) != v or v < 3 or v % 2 == 0:
                raise ValueError(f"forward {name} = {v!r}: expected an odd int >= 3")
        if int(self.rounds) != self.rounds or self.rounds < 1:
            raise ValueError(f"forward rounds = {self.rounds!r}: expected an int >= 1")
        if not (np.isfinite(self.margin) and self.margin >= 1):
            raise ValueError(f"forward margin = {self.margin!r}: expected a number >= 1")


def _overlap(m, wa, wb):
    """Length of the overlap of intervals of widths ``wa`` (centred 0) and ``wb`` (at m)."""
    lo = np.maximum(-0.5 * wa, m - 0.5 * wb)
    hi = np.minimum(0.5 * wa, m + 0.5 * wb)
    return np.maximum(hi - lo, 0.0)


def beam_fraction(u, focal_point, point, *, object_distance: float, cell: float,
                  footprint: float) -> np.ndarray:
    """Fraction of a point's light through each pixel's aperture cell that its lenslet takes.

    Parameters
    ----------
    u : (R, 2)
        Centre of each pixel's aperture cell on the main lens, metres.
    focal_point : (R, 2)
        Centre of its lenslet's footprint on the focal plane (the conjugate X_f), metres.
    point : (R, 3) or (3,)
        The particle (effective coordinates, metres), per pixel or one for all.
    object_distance, cell, footprint : float
        S_o,eff, the aperture cell width c and the lenslet footprint b, metres.

    Returns
    -------
    (R,) float
        ``o_x o_y / w_a^2`` in [0, 1] (module docstring): 1 when the whole aperture cell
        sees the particle through the lenslet, 0 when none of it does.

    Examples
    --------
    A point on the focal plane inside a lenslet's footprint lights all its pixels fully:

    >>> float(beam_fraction([[0.0, 0.0]], [[0.0, 0.0]], [1e-5, 0.0, 0.0],
    ...                     object_distance=0.1, cell=1e-3, footprint=1e-4)[0])
    1.0
    """
    u = np.asarray(u, float).reshape(-1, 2)
    xf = np.asarray(focal_point, float).reshape(-1, 2)
    p = np.asarray(point, float)
    p = np.broadcast_to(p, (len(u), 3)) if p.ndim == 1 else p
    t = ((object_distance + p[:, 2]) / object_distance)[:, None]
    m = u * (1.0 - t) + xf * t - p[:, :2]
    # in the focal plane the aperture cell has no width: the limit is the footprint's test
    wa = np.maximum(cell * np.abs(1.0 - t), 1e-9 * cell)
    wb = footprint * np.abs(t)
    o = _overlap(m, wa, wb)
    return o[:, 0] * o[:, 1] / wa[:, 0] ** 2


def refine_positions(lf: LightField, image, start, *, depth_cell: float,
                     settings: ForwardSettings = ForwardSettings(),
                     engine: str = "numba", chunk_pixels: int = 1 << 22
                     ) -> tuple[np.ndarray, np.ndarray]:
    r"""Refine particle positions to those whose predicted pixel values fit the image best.

    Parameters
    ----------
    lf : LightField
    image : ndarray, shape ``lf.shape``
        The raw image (dark-subtracted for real data).
    start : (N, 3)
        Starting positions (ray-bundle positions), effective coordinates, metres.
    depth_cell : float
        Depth resolution cell, metres (scales ``settings.depth_range``).
    settings : ForwardSettings
    engine : {"numba", "numpy"}
        The compiled search (default) or its plain NumPy twin (same estimator).
    chunk_pixels : int
        Particles are refined in runs of about this many candidate pixels (memory only; a
        far-from-focus particle of a 16 MP camera has ~10^5).

    Returns
    -------
    position : (N, 3)
        Refined positions, metres (the start where no pixel was lit).
    amplitude : (N,)
        Fitted amplitude A of each particle (pixel value of a fully lit pixel).

    Notes
    -----
    For each particle and candidate position P the cost is
    :math:`\sum_i \rho(v_i - A f_i(P))` with :math:`\rho(r) = r^2` for r <= 0 and
    :math:`\min(r, \epsilon A)^2` for r > 0 (``epsilon = settings.excess``): a pixel the
    candidate predicts lit but found dark counts in full, light the candidate does not
    explain (a neighbour's, detected or missed by the reconstruction) counts at most
    epsilon A. A is the median of ``v_i / f_i`` over the pixels the current position lights
    at least half, updated before each search. The pixels i are all pixels (lit or dark)
    whose chief ray passes within ``margin`` half beam widths of the start, widened by the
    drift ``R/S_o x depth range`` of the steepest ray. The search is on joint depth x
    lateral grids: the last depth step is ``2 depth_range / (round_depth_steps - 1) /
    2^rounds`` cells (0.025 by default, 14 µm at a 0.55 mm cell), the last lateral step
    ``lateral_range / 2^(rounds + 1)`` footprints (1/64).
    """
    img = checked_image(lf, image, engine)
    start = np.asarray(start, float).reshape(-1, 3)
    n = len(start)
    if not n:
        return start.copy(), np.zeros(0)
    if not np.isfinite(start).all():
        raise ValueError("start positions contain NaN or infinity")
    values = lf.values(img).astype(np.float64)
    index = _lenslet_index(lf)
    dz = settings.depth_range * depth_cell
    pos, amp = start.copy(), np.zeros(n)
    # particles in chunks of a bounded number of candidate pixels (memory only: each
    # particle's search is independent)
    for sl in _chunks(lf, index, start, settings.margin, dz, chunk_pixels):
        pos[sl], amp[sl] = _refine_chunk(lf, index, values, start[sl], dz, settings, engine)
    return pos, amp


def _refine_chunk(lf, index, values, start, dz, settings, engine):
    """Return :func:`refine_positions` (positions, amplitudes) of some particles."""
    n = len(start)
    pid, ray = _pixels(lf, index, start, settings.margin, dz, engine)
    v = values[ray]
    geom = dict(object_distance=lf.object_distance, cell=lf.cell, footprint=lf.footprint)
    u, xf = lf.u[ray], index[4][ray]
    pos = start.copy()
    dl = settings.lateral_range * lf.footprint
    ptr = np.concatenate([[0], np.cumsum(np.bincount(pid, minlength=n))]).astype(np.int64)
    search = _best_offset_numba if engine == "numba" else _best_offset
    fractions = _fractions_numba if engine == "numba" else _fractions
    for depth, lateral in _schedule(dz, dl, settings.depth_steps, settings.rounds,
                                    settings.round_depth_steps):
        amp = _robust_amplitude(pid, fractions(ptr, pid, u, xf, pos, geom), v, n)
        pos = pos + search(ptr, u, xf, v, amp, pos, depth, lateral, geom, settings.excess)
    amp = _robust_amplitude(pid, fractions(ptr, pid, u, xf, pos, geom), v, n)
    return pos, amp


def _fractions(ptr, pid, u, xf, pos, geom):
    """:func:`beam_fraction` of every pixel for its particle's position (NumPy twin)."""
    return beam_fraction(u, xf, pos[pid], **geom)


def _fractions_numba(ptr, pid, u, xf, pos, geom):
    """Return :func:`_fractions` by the compiled kernel."""
    from plenopiv.tracking import _kernels as _k

    out = np.empty(len(pid))
    _k.pixel_fractions(ptr, np.ascontiguousarray(u, np.float64),
                       np.ascontiguousarray(xf, np.float64),
                       np.ascontiguousarray(pos, np.float64), float(geom["object_distance"]),
                       float(geom["cell"]), float(geom["footprint"]), out)
    return out


def _schedule(depth_range, lateral_range, depth_steps, rounds, round_depth_steps=7):
    """Return the searches of the refinement: ``(depth (nz,), lateral (5,))`` offsets, m.

    Every search is a joint depth x lateral grid (:func:`_grid_offsets`; near focus depth
    and lateral position trade off along a slanted valley): the first over the full ranges
    with ``depth_steps`` depths, the r-th of the ``rounds`` after it over ranges halved r
    times with ``round_depth_steps``.
    """
    out = [(np.linspace(-depth_range, depth_range, depth_steps),
            np.linspace(-lateral_range, lateral_range, 5))]
    for r in range(1, rounds + 1):
        h = 0.5 ** r
        out.append((np.linspace(-depth_range * h, depth_range * h, round_depth_steps),
                    np.linspace(-lateral_range * h, lateral_range * h, 5)))
    return out


def _grid_offsets(depth, lateral):
    """Offsets (K, 3), metres, of the joint grid: row ``(iz n_l + ix) n_l + iy``.

    ``(lateral[ix], lateral[iy], depth[iz])``; with odd lengths the zero offset is row K // 2.
    """
    gz, gx, gy = np.meshgrid(depth, lateral, lateral, indexing="ij")
    return np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])


def _best_offset(ptr, u, xf, v, amp, pos, depth, lateral, geom, excess):
    """Return the offset of least misfit of each particle on a joint grid (:func:`_grid_offsets`).

    NumPy twin of :func:`plenopiv.tracking._kernels.best_grid_offsets`. Misfit:
    ``sum_i rho(v_i - A f_i)`` with ``rho(r) = r^2`` for r <= 0 (predicted light missing)
    and ``min(r, excess A)^2`` for r > 0 (unexplained light, capped); the zero offset
    (row K // 2) is tried first and kept on ties.
    """
    offsets = _grid_offsets(depth, lateral)
    n = len(pos)
    pid = np.repeat(np.arange(n), np.diff(ptr))
    best = np.full(n, np.inf)
    choice = np.zeros((n, 3))
    centre = offsets.shape[0] // 2
    cap = excess * amp[pid]
    for i in [centre] + [i for i in range(offsets.shape[0]) if i != centre]:
        res = v - amp[pid] * beam_fraction(u, xf, pos[pid] + offsets[i], **geom)
        cost = np.bincount(pid, np.where(res > 0, np.minimum(res, cap), res) ** 2, n)
        better = cost < best
        best = np.where(better, cost, best)
        choice[better] = offsets[i]
    return choice


def _best_offset_numba(ptr, u, xf, v, amp, pos, depth, lateral, geom, excess):
    """Return :func:`_best_offset` by the compiled kernel."""
    from plenopiv.tracking import _kernels as _k

    choice = np.zeros((len(pos), 3))
    c = [np.ascontiguousarray(a, np.float64) for a in (u, xf, v, amp, pos, depth, lateral)]
    _k.best_grid_offsets(ptr, *c, float(geom["object_distance"]), float(geom["cell"]),
                         float(geom["footprint"]), float(excess), choice)
    return choice


def _robust_amplitude(pid, f, v, n):
    """Median of value / fraction over the pixels a particle lights at least half (>= 0)."""
    use = f >= 0.5
    p, ratio = pid[use], v[use] / f[use]
    o = np.lexsort((ratio, p))
    p, ratio = p[o], ratio[o]
    cnt = np.bincount(p, minlength=n)
    first = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    med = np.zeros(n)
    has = cnt > 0
    med[has] = ratio[first[has] + cnt[has] // 2]
    return np.maximum(med, 0.0)


def _lenslet_index(lf: LightField):
    """Rays by lenslet: order, ptr, lenslet ids, KD-tree, X_f, u and X_f sorted by lenslet.

    ``(order, ptr, lenslet ids with rays, KD-tree of their X_f, X_f, u sorted, X_f sorted)``;
    X_f is every ray's focal-plane point (P, 2), metres; the last two are u and X_f in
    lenslet order.
    """
    order, ptr, conj, has = lenslet_table(lf)
    xf = lf.focal_plane_position
    return (order, ptr, np.flatnonzero(has), cKDTree(conj[has]), xf,
            np.ascontiguousarray(lf.u[order], np.float64),
            np.ascontiguousarray(xf[order], np.float64))


def _reach(lf: LightField, start, margin: float, depth_range: float):
    """Return ``(t, radius, reach)`` of each particle's pixel selection (metres).

    A pixel is taken when its chief ray passes within ``radius`` of the start at its depth;
    its lenslet's conjugate then lies within ``reach`` of ``start / t`` on the focal plane.
    """
    so, ap = lf.object_distance, lf.aperture_radius
    t = (so + start[:, 2]) / so
    half = 0.5 * (lf.footprint * np.abs(t) + lf.cell * np.abs(1.0 - t))
    radius = margin * half + ap / so * depth_range
    return t, radius, (ap * np.abs(1.0 - t) + radius) / np.abs(t)


def _chunks(lf: LightField, index, start, margin: float, depth_range: float,
            budget: int) -> list[slice]:
    """Split the particles into runs whose candidate pixels stay near ``budget``.

    A particle's candidates are all pixels of the lenslets within its reach (before the
    per-pixel test of :func:`_pixels`); a run holds at least one particle.
    """
    ptr, lens_ids, tree = index[1:4]
    t, _, reach = _reach(lf, start, margin, depth_range)
    per_lens = float(np.diff(ptr)[lens_ids].mean()) if len(lens_ids) else 0.0
    cost = tree.query_ball_point(start[:, :2] / t[:, None], reach, return_length=True)
    run = np.floor_divide(np.cumsum(np.asarray(cost, float) * per_lens), max(budget, 1))
    edges = np.flatnonzero(np.diff(run)) + 1
    bounds = np.concatenate([[0], edges, [len(start)]]).astype(int)
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


def _pixels(lf: LightField, index, start, margin: float, depth_range: float,
            engine: str = "numba"):
    """(particle, ray) of every pixel whose chief ray passes near a particle's beam.

    ``engine="numba"`` runs the compiled selection (no per-candidate temporaries: at 16 MP a
    far-from-focus particle has ~10^5 candidate pixels); ``"numpy"`` its plain twin.
    """
    if engine == "numpy":
        return _pixels_numpy(lf, index, start, margin, depth_range)
    from plenopiv.tracking import _kernels as _k

    order, ptr, lens_ids, tree, _, u_s, xf_s = index
    t, radius, reach = _reach(lf, start, margin, depth_range)
    lists = tree.query_ball_point(start[:, :2] / t[:, None], reach)
    counts = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    if counts.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    cand = lens_ids[np.concatenate([np.asarray(x, np.int64) for x in lists])].astype(np.int64)
    args = (cptr, cand, ptr.astype(np.int64), u_s, xf_s, np.ascontiguousarray(start[:, :2]),
            np.ascontiguousarray(t), np.ascontiguousarray(radius))
    n = np.zeros(len(start), np.int64)
    _k.near_pixels(*args, True, n, np.zeros(0, np.int64))
    out_ptr = np.concatenate([[0], np.cumsum(n)]).astype(np.int64)
    out = np.empty(out_ptr[-1], np.int64)
    _k.near_pixels(*args, False, out_ptr, out)
    return np.repeat(np.arange(len(start)), n), order[out]


def _pixels_numpy(lf: LightField, index, start, margin: float, depth_range: float):
    """NumPy twin of :func:`_pixels`."""
    order, ptr, lens_ids, tree, xf_all = index[:5]
    t, radius, reach = _reach(lf, start, margin, depth_range)
    lists = tree.query_ball_point(start[:, :2] / t[:, None], reach)
    counts = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    if counts.sum() == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pid = np.repeat(np.arange(len(lists)), counts)
    lens = lens_ids[np.concatenate([np.asarray(x, np.int64) for x in lists])]
    n_r = ptr[lens + 1] - ptr[lens]
    pid = np.repeat(pid, n_r)
    first = np.repeat(ptr[lens] - (np.cumsum(n_r) - n_r), n_r)
    ray = order[first + np.arange(len(first))]
    xy = lf.u[ray] * (1.0 - t[pid, None]) + xf_all[ray] * t[pid, None]
    # a square beam: the larger of the two lateral misses
    miss = np.abs(xy - start[pid, :2]).max(axis=1)
    keep = miss <= radius[pid]
    return pid[keep], ray[keep]
