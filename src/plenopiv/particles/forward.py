"""Forward-model refinement of particle positions: the pixel values a position predicts.

Near the focal plane the ray bundle's chief rays lose the depth: the information is in which
pixels are lit and how much. A pixel is a beam from its aperture cell to its lenslet
footprint; the fraction of a particle's light it receives is a trapezoid in the particle's
lateral miss, whose widths change with depth. :func:`refine_positions` moves each particle
from its ray-bundle position to the position whose predicted pixel values fit the image best
(a one-sided misfit): joint depth x lateral grids near focus, Levenberg-Marquardt steps on the
analytic Jacobian beyond. :func:`beam_fraction` is the model. Effective (air-equivalent)
coordinates, metres, as in :mod:`plenopiv.particles.bundle`.

See docs/methods.md#forward-model-positions.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plenopiv.lightfield import LightField
from plenopiv.particles.bundle import (
    ENGINES,
    RayTable,
    checked_image,
    flat_lists,
    ray_table,
    spatial_order,
)

__all__ = ["ENGINES", "ForwardSettings", "beam_fraction", "near_focus", "refine_positions"]

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
    near_focus : float
        Starts within ``near_focus`` depth resolution cells of the focal plane are refined
        by the grid searches (>= 0; ``inf``: all), the others by ``local_iterations``
        Levenberg-Marquardt steps on the same misfit (:func:`near_focus`): farther out the
        particle lights many lenslets, each with its edge pixels at another place on their
        ramps, and the misfit is smooth enough to follow its slope.
    local_iterations : int
        Most Levenberg-Marquardt steps of a particle beyond ``near_focus`` per round (>= 1).
    local_rounds : int
        Rounds of those steps, each after the amplitude is estimated again at the current
        position and within the ranges around it (>= 1).
    local_starts : int
        Descents per round, from the position and from depths ``+-k / (m + 1)`` of the depth
        range around it (k = 1 ... m, m = (local_starts - 1) / 2; odd, >= 1); the end of
        least misfit is kept (the misfit of a particle seen through few lenslets has
        local minima: two starts on either side in depth find the deeper one).
    local_starts_within : float
        Only starts within this many depth cells of the focal plane take ``local_starts``
        descents (>= 0); farther out one descent, from the position (its many lenslets
        make the misfit smooth).
    """

    depth_range: float = 0.6
    depth_steps: int = 13
    lateral_range: float = 0.25
    margin: float = 1.5
    excess: float = 0.2
    rounds: int = 3
    round_depth_steps: int = 7
    near_focus: float = 1.0
    local_iterations: int = 20
    local_rounds: int = 2
    local_starts: int = 3
    local_starts_within: float = 3.0

    def __post_init__(self):
        if not (self.near_focus >= 0):
            raise ValueError(f"forward near_focus = {self.near_focus!r}: expected a number "
                             ">= 0 (depth cells; inf: grid searches for all)")
        for name in ("local_iterations", "local_rounds"):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise ValueError(f"forward {name} = {v!r}: expected an int >= 1")
        if not (self.local_starts_within >= 0):
            raise ValueError(f"forward local_starts_within = {self.local_starts_within!r}: "
                             "expected a number >= 0 (depth cells)")
        if int(self.local_starts) != self.local_starts or self.local_starts % 2 == 0:
            raise ValueError(f"forward local_starts = {self.local_starts!r}: expected an odd "
                             "int >= 1")
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


def near_focus(depth, *, depth_cell: float, settings: ForwardSettings = ForwardSettings()
               ) -> np.ndarray:
    """Which starts the grid searches refine: ``|Z| <= near_focus * depth_cell`` (N,) bool.

    ``depth`` (N,) effective Z of the starts, metres; ``depth_cell`` metres. Near focus a
    particle lights few lenslets and the misfit is a staircase of narrow ramps (one aperture
    cell wide, c |1 - t|) with the slanted valley of the module docstring: the grids search
    it; the others take the local steps.
    """
    return np.abs(np.asarray(depth, float)) <= settings.near_focus * depth_cell


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
                     engine: str = "numba", chunk_pixels: int = 1 << 22,
                     table: RayTable | None = None) -> tuple[np.ndarray, np.ndarray]:
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
    table : RayTable, optional
        :func:`plenopiv.particles.bundle.ray_table` of ``lf``, when already built.

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
    drift ``R/S_o x depth range`` of the steepest ray. Starts within ``settings.near_focus``
    depth cells of the focal plane are searched on joint depth x lateral grids: the last
    depth step is ``2 depth_range / (round_depth_steps - 1) / 2^rounds`` cells (0.025 by
    default, 14 µm at a 0.55 mm cell), the last lateral step ``lateral_range / 2^(rounds +
    1)`` footprints (1/64). The others take ``local_rounds`` rounds of ``local_starts``
    Levenberg-Marquardt descents (one beyond ``local_starts_within`` depth cells; module
    docstring) with parameters scaled to footprints and depth cells, within
    ``lateral_range`` and ``depth_range`` of the round's start.
    """
    img = checked_image(lf, image, engine)
    start = np.asarray(start, float).reshape(-1, 3)
    n = len(start)
    if not n:
        return start.copy(), np.zeros(0)
    if not np.isfinite(start).all():
        raise ValueError("start positions contain NaN or infinity")
    values = lf.values(img).astype(np.float64)
    index = ray_table(lf) if table is None else table
    if engine == "numba":
        # in lenslet order, as the table's u and X_f: a particle's pixels lie in a few runs
        values = values[index.order]
    dz = settings.depth_range * depth_cell
    pos, amp = start.copy(), np.zeros(n)
    grid = near_focus(start[:, 2], depth_cell=depth_cell, settings=settings)
    # the extra starts serve the particles near focus (a misfit with local minima)
    multi = np.abs(start[:, 2]) <= settings.local_starts_within * depth_cell
    # each group in spatial order: neighbours read the same lenslets' pixels (in cache)
    key = spatial_order(lf, start) if engine == "numba" else np.arange(n)
    for rows, local, starts in ((key[grid[key]], False, 1),
                                (key[(~grid & multi)[key]], True, settings.local_starts),
                                (key[(~grid & ~multi)[key]], True, 1)):
        # particles in chunks of a bounded number of candidate pixels (memory only: each
        # particle's search is independent)
        for sl in _chunks(lf, index, start[rows], settings.margin, dz, chunk_pixels):
            r = rows[sl]
            pos[r], amp[r] = _refine_chunk(lf, index, values, start[r], dz, depth_cell,
                                           settings, engine, local, starts)
    return pos, amp


def _refine_chunk(lf, index, values, start, dz, depth_cell, settings, engine, local=False,
                  starts=1):
    """Return :func:`refine_positions` (positions, amplitudes) of some particles.

    ``local``: Levenberg-Marquardt steps (:func:`_local_fit`) in place of the grid searches.
    """
    n = len(start)
    geom = dict(object_distance=lf.object_distance, cell=lf.cell, footprint=lf.footprint)
    if engine == "numba":       # values in lenslet order (refine_positions)
        pid, (v, u, xf) = _pixel_data(lf, index, values, start, settings.margin, dz)
    else:
        pid, ray = _pixels(lf, index, start, settings.margin, dz, engine)
        v, u, xf = values[ray], lf.u[ray], index.focal[ray]
    pos = start.copy()
    dl = settings.lateral_range * lf.footprint
    ptr = np.concatenate([[0], np.cumsum(np.bincount(pid, minlength=n))]).astype(np.int64)
    amplitude = _amplitude_at_numba if engine == "numba" else _amplitude_at
    if local:
        fit = _local_fit_numba if engine == "numba" else _local_fit
        for _ in range(settings.local_rounds):
            amp = amplitude(ptr, pid, u, xf, v, pos, geom)
            pos = fit(ptr, u, xf, v, amp, pos, geom, settings.excess,
                      (lf.footprint, depth_cell), (dl, dz), _starts(dz, starts),
                      settings.local_iterations)
    else:
        search = _best_offset_numba if engine == "numba" else _best_offset
        for depth, lateral in _schedule(dz, dl, settings.depth_steps, settings.rounds,
                                        settings.round_depth_steps):
            amp = amplitude(ptr, pid, u, xf, v, pos, geom)
            pos = pos + search(ptr, u, xf, v, amp, pos, depth, lateral, geom, settings.excess)
    amp = amplitude(ptr, pid, u, xf, v, pos, geom)
    return pos, amp


def _starts(depth_range: float, n: int) -> np.ndarray:
    """Depth offsets (n,) of the local descents, metres.

    0 first, then the pairs ``+-k / (m + 1)`` of ``depth_range`` for k = 1 ... m,
    m = (n - 1) // 2 (n odd).
    """
    k = np.arange(1, (n - 1) // 2 + 1) * depth_range / ((n - 1) // 2 + 1)
    return np.concatenate([[0.0], np.ravel(np.column_stack([-k, k]))])


def _overlap_grad(m, wa, wb):
    """:func:`_overlap` and its derivatives ``(o, do/dm, do/dwa, do/dwb)`` (0 where o = 0)."""
    up = m + 0.5 * wb < 0.5 * wa
    hi = np.where(up, m + 0.5 * wb, 0.5 * wa)
    dn = m - 0.5 * wb > -0.5 * wa
    lo = np.where(dn, m - 0.5 * wb, -0.5 * wa)
    lit = hi - lo > 0.0
    d_m = up.astype(float) - dn.astype(float)
    d_a = np.where(up, 0.0, 0.5) - np.where(dn, 0.0, -0.5)
    d_b = np.where(up, 0.5, 0.0) - np.where(dn, -0.5, 0.0)
    return [np.where(lit, q, 0.0) for q in (hi - lo, d_m, d_a, d_b)]


def _misfit_sums(pid, n, u, xf, v, amp, pos, geom, excess, scale):
    """One-sided misfit (n,), ``J^T J`` (n, 3, 3) and ``J^T r`` (n, 3) of each particle.

    NumPy twin of ``plenopiv.particles._bundle_kernels._misfit_sums``: residuals ``r = v - A f`` of
    the pixels of each particle at ``pos`` (n, 3), Jacobian in the scaled parameters
    ``(x / sx, y / sx, z / sz)`` with ``scale = (sx, sz)`` metres; a capped residual
    (r > excess A) has none.
    """
    so, cell, fp = geom["object_distance"], geom["cell"], geom["footprint"]
    sx, sz = scale
    p = pos[pid]
    a = amp[pid]
    t = (so + p[:, 2]) / so
    s = 1.0 - t
    wa = cell * np.abs(s)
    wide = wa > 1e-9 * cell
    dwa = np.where(wide, np.where(p[:, 2] > 0.0, cell / so, -cell / so), 0.0)
    wa = np.where(wide, wa, 1e-9 * cell)
    wb = fp * np.abs(t)
    dwb = np.where(t > 0.0, fp / so, -fp / so)
    inv = 1.0 / (wa * wa)
    mx = u[:, 0] * s + xf[:, 0] * t - p[:, 0]
    my = u[:, 1] * s + xf[:, 1] * t - p[:, 1]
    ox, oxm, oxa, oxb = _overlap_grad(mx, wa, wb)
    oy, oym, oya, oyb = _overlap_grad(my, wa, wb)
    f = ox * oy * inv
    r = v - a * f
    cap = excess * a
    free = ~(r > cap)
    cost = np.bincount(pid, np.where(free, r * r, cap * cap), n)
    dox = oxm * (xf[:, 0] - u[:, 0]) / so + oxa * dwa + oxb * dwb
    doy = oym * (xf[:, 1] - u[:, 1]) / so + oya * dwa + oyb * dwb
    j = np.stack([a * oxm * oy * inv * sx, a * ox * oym * inv * sx,
                  -a * ((dox * oy + ox * doy) * inv - 2.0 * f * dwa / wa) * sz], axis=1)
    j = np.where(free[:, None], j, 0.0)
    g = np.stack([np.bincount(pid, j[:, e] * r, n) for e in range(3)], axis=1)
    h = np.empty((n, 3, 3))
    for e in range(3):
        for c in range(e, 3):
            h[:, e, c] = h[:, c, e] = np.bincount(pid, j[:, e] * j[:, c], n)
    return cost, h, g


def _damped_steps(h, g, lam):
    """Solve ``(h + lam diag(h)) step = -g`` per particle by Cramer's rule.

    NumPy twin of ``plenopiv.particles._bundle_kernels._damped_step``: returns ``(step (n, 3),
    solved (n,))``, solved False where the system is singular.
    """
    a = h + lam[:, None, None] * h * np.eye(3)
    det = (a[:, 0, 0] * (a[:, 1, 1] * a[:, 2, 2] - a[:, 1, 2] * a[:, 2, 1])
           - a[:, 0, 1] * (a[:, 1, 0] * a[:, 2, 2] - a[:, 1, 2] * a[:, 2, 0])
           + a[:, 0, 2] * (a[:, 1, 0] * a[:, 2, 1] - a[:, 1, 1] * a[:, 2, 0]))
    ok = (np.abs(det) > 0.0) & np.isfinite(det)
    d = np.where(ok, det, 1.0)
    b0, b1, b2 = -g[:, 0], -g[:, 1], -g[:, 2]
    step = np.stack([
        (b0 * (a[:, 1, 1] * a[:, 2, 2] - a[:, 1, 2] * a[:, 2, 1])
         - a[:, 0, 1] * (b1 * a[:, 2, 2] - a[:, 1, 2] * b2)
         + a[:, 0, 2] * (b1 * a[:, 2, 1] - a[:, 1, 1] * b2)) / d,
        (a[:, 0, 0] * (b1 * a[:, 2, 2] - a[:, 1, 2] * b2)
         - b0 * (a[:, 1, 0] * a[:, 2, 2] - a[:, 1, 2] * a[:, 2, 0])
         + a[:, 0, 2] * (a[:, 1, 0] * b2 - b1 * a[:, 2, 0])) / d,
        (a[:, 0, 0] * (a[:, 1, 1] * b2 - b1 * a[:, 2, 1])
         - a[:, 0, 1] * (a[:, 1, 0] * b2 - b1 * a[:, 2, 0])
         + b0 * (a[:, 1, 0] * a[:, 2, 1] - a[:, 1, 1] * a[:, 2, 0])) / d], axis=1)
    return step, ok


def _local_fit(ptr, u, xf, v, amp, start, geom, excess, scale, bounds, offsets, iterations):
    """Levenberg-Marquardt steps on each particle's one-sided misfit (NumPy twin).

    Twin of ``plenopiv.particles._bundle_kernels.local_fit``: from each of
    ``start + (0, 0, offset)`` (``offsets`` metres), in the parameters scaled by
    ``scale = (sx, sz)`` metres, damped Gauss-Newton steps
    ``(J^T J + lam diag J^T J) d = -J^T r`` clipped to one unit per axis,
    the position kept within ``start +- bounds`` (lateral, depth; metres); a step is taken
    when the misfit drops (lam / 3, done once the step is below 1e-3 units), refused
    otherwise (lam x 4, done beyond 1e6), at most ``iterations`` times. Returns the end of
    least misfit of each particle (n, 3), metres.
    """
    n = len(start)
    lo = start - np.array([bounds[0], bounds[0], bounds[1]])
    hi = start + np.array([bounds[0], bounds[0], bounds[1]])
    best, out = np.full(n, np.inf), start.copy()
    for off in offsets:
        first = start.copy()
        first[:, 2] = np.clip(start[:, 2] + off, lo[:, 2], hi[:, 2])
        end, cost = _descend(ptr, u, xf, v, amp, first, lo, hi, geom, excess, scale,
                             iterations)
        better = cost < best
        best = np.where(better, cost, best)
        out[better] = end[better]
    return out


def _descend(ptr, u, xf, v, amp, first, lo, hi, geom, excess, scale, iterations):
    """One Levenberg-Marquardt descent per particle from ``first`` (:func:`_local_fit`).

    Returns ``(end (n, 3), misfit (n,))``.
    """
    n = len(first)
    pid = np.repeat(np.arange(n), np.diff(ptr))
    sx, sz = scale
    unit = np.array([sx, sx, sz])
    pos = first.copy()
    cost, h, g = _misfit_sums(pid, n, u, xf, v, amp, pos, geom, excess, scale)
    lam = np.full(n, 1e-3)
    active = amp > 0.0
    for _ in range(iterations):
        step, ok = _damped_steps(h, g, lam)
        active &= ok
        if not active.any():
            break
        step = np.clip(step, -1.0, 1.0)
        trial = np.where(active[:, None], np.clip(pos + step * unit, lo, hi), pos)
        c, hn, gn = _misfit_sums(pid, n, u, xf, v, amp, trial, geom, excess, scale)
        take = active & (c < cost)
        pos = np.where(take[:, None], trial, pos)
        cost = np.where(take, c, cost)
        h = np.where(take[:, None, None], hn, h)
        g = np.where(take[:, None], gn, g)
        lam = np.where(take, np.maximum(lam / 3.0, 1e-9), np.where(active, lam * 4.0, lam))
        active &= ~(take & (np.abs(step).max(axis=1) < 1e-3)) & ~(~take & (lam > 1e6))
    return pos, cost


def _local_fit_numba(ptr, u, xf, v, amp, start, geom, excess, scale, bounds, offsets,
                     iterations):
    """Return :func:`_local_fit` by the compiled kernel."""
    from plenopiv.particles import _bundle_kernels as _k

    pos = np.empty_like(start)
    c = [np.ascontiguousarray(a, np.float64) for a in (u, xf, v, amp, start)]
    _k.local_fit(ptr, *c, float(geom["object_distance"]), float(geom["cell"]),
                 float(geom["footprint"]), float(excess), float(scale[0]), float(scale[1]),
                 float(bounds[0]), float(bounds[1]),
                 np.ascontiguousarray(offsets, np.float64), int(iterations), pos)
    return pos


def _fractions(ptr, pid, u, xf, pos, geom):
    """:func:`beam_fraction` of every pixel for its particle's position (NumPy twin)."""
    return beam_fraction(u, xf, pos[pid], **geom)


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

    NumPy twin of :func:`plenopiv.particles._bundle_kernels.best_grid_offsets`. Misfit:
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
    from plenopiv.particles import _bundle_kernels as _k

    choice = np.zeros((len(pos), 3))
    c = [np.ascontiguousarray(a, np.float64) for a in (u, xf, v, amp, pos, depth, lateral)]
    _k.best_grid_offsets(ptr, *c, float(geom["object_distance"]), float(geom["cell"]),
                         float(geom["footprint"]), float(excess), choice)
    return choice


def _amplitude_at(ptr, pid, u, xf, v, pos, geom):
    """Amplitude of each particle at ``pos``: :func:`_robust_amplitude` of :func:`_fractions`."""
    return _robust_amplitude(ptr, pid, _fractions(ptr, pid, u, xf, pos, geom), v)


def _amplitude_at_numba(ptr, pid, u, xf, v, pos, geom):
    """Return :func:`_amplitude_at` by the compiled kernel (one pass, no fraction array)."""
    from plenopiv.particles import _bundle_kernels as _k

    out = np.empty(len(ptr) - 1)
    c = [np.ascontiguousarray(a, np.float64) for a in (u, xf, v, pos)]
    _k.amplitude_at(ptr, *c, float(geom["object_distance"]), float(geom["cell"]),
                    float(geom["footprint"]), out)
    return out


def _robust_amplitude(ptr, pid, f, v):
    """Median of value / fraction over the pixels a particle lights at least half (>= 0)."""
    n = len(ptr) - 1
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


#: Rays by lenslet (:func:`plenopiv.particles.bundle.ray_table`).
_lenslet_index = ray_table


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
            engine: str = "numba", lenslet_order: bool = False):
    """(particle, ray) of every pixel whose chief ray passes near a particle's beam.

    ``engine="numba"`` runs the compiled selection (no per-candidate temporaries: at 16 MP a
    far-from-focus particle has ~10^5 candidate pixels); ``"numpy"`` its plain twin.
    ``lenslet_order`` (numba only): the rays as rows of the lenslet-sorted arrays of
    ``index`` (``ray = index.order[row]``), whose neighbouring rows are gathered together.
    """
    if engine == "numpy":
        return _pixels_numpy(lf, index, start, margin, depth_range)
    pid, out, _ = _near_pixels(lf, index, start, margin, depth_range, None)
    return pid, out if lenslet_order else index.order[out]


def _pixel_data(lf: LightField, index, values, start, margin: float, depth_range: float):
    """``(particle, (value, u, X_f))`` of the pixels of :func:`_pixels` (numba, gathered).

    ``values`` (P,): the image's ray values in the lenslet order of ``index``.
    """
    pid, _, data = _near_pixels(lf, index, start, margin, depth_range, values)
    return pid, data


def _near_pixels(lf: LightField, index, start, margin, depth_range, values):
    """Run :func:`plenopiv.particles._bundle_kernels.near_pixels`: ``(particle, row, gathered)``.

    Rows of the lenslet-sorted arrays; ``gathered`` is ``(value, u, X_f)`` of those rows when
    ``values`` (lenslet order) is given, else None.
    """
    from plenopiv.particles import _bundle_kernels as _k

    _, ptr, lens_ids, tree, _, u_s, xf_s = index
    t, radius, reach = _reach(lf, start, margin, depth_range)
    lists = tree.query_ball_point(start[:, :2] / t[:, None], reach)
    cptr, cand = flat_lists(lists, lens_ids)
    n_pix = np.zeros(len(start), np.int64)
    args = (cptr, cand, ptr.astype(np.int64), u_s, xf_s, np.ascontiguousarray(start[:, :2]),
            np.ascontiguousarray(t), np.ascontiguousarray(radius), lf.cell)
    none = (np.zeros(0), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
    _k.near_pixels(*args, True, n_pix, np.zeros(0, np.int64), *none)
    out_ptr = np.concatenate([[0], np.cumsum(n_pix)]).astype(np.int64)
    out = np.empty(out_ptr[-1], np.int64)
    if values is None:
        gathered, buffers = None, none
    else:
        gathered = (np.empty(len(out)), np.empty((len(out), 2)), np.empty((len(out), 2)))
        buffers = (np.ascontiguousarray(values, np.float64), gathered[1], gathered[2],
                   gathered[0])
    _k.near_pixels(*args, False, out_ptr, out, *buffers)
    return np.repeat(np.arange(len(start)), n_pix), out, gathered


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
