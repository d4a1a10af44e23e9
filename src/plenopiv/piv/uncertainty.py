r"""Per-vector standard uncertainty of a plenoptic PIV field: statistics plus the chain's response.

The uncertainty is the correlation statistics plus the measured response of the whole chain to
known displacements.

The correlation statistics of :func:`plenopiv.piv.correlate_volumes` (Wieneke 2015) see what
makes the two reconstructed volumes differ: image noise, particles leaving a window,
unresolved motion. They cannot see an error that both reconstructions share, and a plenoptic
camera has one: a particle near the focal plane lights about one lenslet wherever it lies
inside the lenslet's footprint and inside about one depth resolution cell, so its
reconstruction does not follow it there, and the measured displacement is pulled towards
zero (docs/validation/uncertainty.md: depth displacements near focus are measured at 0.0-0.5
of their true value). Both exposures are reconstructed the same way, the deformed windows
match, and the correlation statistics stay small: on the vortex validations only 40-66 % of
the true depth errors lie within their ±2σ (67-96 % with the last correction added).

This module measures that error of the chain instead (:func:`measure_response`, a type-B
evaluation from a calibration of the measuring system). With the calibrated camera, the
experiment's grid and every processing setting, it renders (ray tracing,
:func:`plenopiv.synthetic.images.particle_image`) pairs of random particles moved by known
uniform displacements ``s`` along the three axes at once, reconstructs and correlates them
as it does the real pair, and tabulates for each layer of vectors (window-centre depth):

- the gain ``g_k = mean(measured_k) / s_k`` per component ``k`` (averaged over the
  layer's vectors and over the test displacements along that axis: 0.5, 1.25 and 1.75
  lenslet footprints laterally with 0.1, 0.25 and 0.5 depth resolution cells in depth, so
  that every fraction of the resolution cell is probed, and two more, 1.25 footprints
  along x alone and 0.5 depth cells alone, that tell the shared error of the motion along
  each axis apart);
- the random error ``r_k``: the rms over the test displacements of the spread (standard
  deviation) of the layer's vectors;
- the rms uncertainty ``s_k`` the correlation statistics with the error the iteration left
  (:func:`iteration_uncertainty`) gave those same test vectors;
- where the reconstruction places the test particles relative to where they are, per axis
  (:func:`placement_offset`).

:func:`combine` then gives each vector of the real field, per component, the standard
uncertainty

.. math:: \sigma_k^2 = \sigma_{CS,k}^2 + r_{ex,k}^2
          + \Big(\frac{|1 - g_k|}{\max(g_k, g_{min})}\, |d_k|\Big)^2 + b_k^2
          + q_k^2 + l_k^2

with :math:`\sigma_{CS}` the correlation statistics of :func:`plenopiv.piv.correlate_volumes`
with the error the passes left (:func:`iteration_uncertainty`: the geometric tail
:math:`\rho / (1 - \rho)` of the last correction, the predictor filter's offset
:func:`filter_offset` and the correlation's own noise removed), ``d_k`` the vector's
displacement and:

- :math:`r_{ex,k}^2`, the part :math:`\max(0, r_k^2 - s_k^2)` of the test vectors' spread
  the correlation statistics did not see, per test displacement, fitted per layer as
  :math:`a_x t_x + a_y t_y + a_z t_z` in the motion along each axis measured in resolution
  cells (0 at rest) and taken at the vector's own motion (:meth:`Response.excess`). The spread of
  the test vectors holds their random
  error, which their own correlation statistics already estimate; adding all of ``r`` to
  :math:`\sigma_{CS}` would count that part twice. What is left is the error both
  reconstructions share (the plenoptic lock-in above), invisible to the statistics by
  construction, and absent where nothing moved.
- the error of a displacement measured with gain ``g_k`` (its true value is ``d_k / g_k``);
  :math:`g_{min} = 0.1` bounds a vector the chain barely sees at nine times its own
  magnitude.
- :math:`b_k` the bias of a window average where the displacement curves inside the window
  (:func:`unresolved_gradient_bias`), which a uniform test displacement cannot reproduce;
  the last correction no longer counts it (its filter offset is removed), so it is added in
  full, less the part the vectors' random errors give a curvature estimated from them
  (:func:`curvature_noise_factor`: the second differences of noise alone are as large as
  the noise, which the other terms count already).
- :math:`q_k` the range a rejected vector beside it leaves open
  (:func:`rejected_neighbour_uncertainty`): where the median test rejected a measurement,
  the displacement there lies somewhere between that measurement and its neighbours'
  median, a rectangular distribution of standard deviation (range) / sqrt(12).
- :math:`l_k` the error of the vector's position (:func:`location_uncertainty`): the
  reconstruction places particles off their true positions (by about 1 % of the distance
  from the focal plane in depth on the Auburn optics), so a window reports the displacement
  of particles from elsewhere; the offset per layer is measured on the test pairs
  (:func:`placement_offset`), the error is it times the measured field's gradient.

The response depends on the camera, the grid, the seeding and the settings, not on the
flow, so it is computed once per experiment and kept in the weights cache (a few more
pairs' worth of work the first time).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from plenopiv.errors import PlenopivError

__all__ = [
    "UNCERTAINTY_METHODS",
    "Response",
    "combine",
    "location_uncertainty",
    "measure_response",
    "placement_offset",
    "rejected_neighbour_uncertainty",
    "response_key",
    "unresolved_gradient_bias",
]

UNCERTAINTY_METHODS = ("response", "correlation")
"""Valid values of ``[piv] uncertainty``: correlation statistics with the chain's measured
response (default), or correlation statistics alone."""

MIN_GAIN = 0.1
"""Smallest gain the systematic term divides by (dimensionless)."""

DEFAULT_RATIO = 0.5
"""Convergence ratio of the passes where it cannot be measured (remaining error = last
correction)."""

MAX_CONVERGENCE_RATIO = 0.9
"""Largest convergence ratio counted: a ratio of 1 or more (no convergence) is held here, the
remaining error then nine times the last correction."""

LATERAL_SHIFTS = (0.5, 1.25, 1.75)
"""Test displacements along x and y, lenslet footprints (different fractions of a footprint)."""

DEPTH_SHIFTS = (0.1, 0.25, 0.5)
"""Test displacements along z, depth resolution cells."""

SEPARATING_SHIFTS = ((1.25, 0.0, 0.0), (0.0, 0.0, 0.5))
"""Two more test displacements ``(x, y, z)`` (lenslet footprints along x and y, depth
resolution cells along z): one along x only, one along depth only, so that the shared error
of the motion along each axis can be told apart (:meth:`Response.excess`)."""

RESPONSE_VERSION = 8


@dataclass(frozen=True)
class Response:
    """The chain's measured response per layer of vectors and test displacement.

    Attributes
    ----------
    z : ndarray, shape (nz,)
        Window-centre depth of each layer, metres (effective coordinates of the grid).
    shifts : ndarray, shape (n, 3)
        The test displacements ``(dx, dy, dz)``, metres (effective coordinates), in the
        order of :func:`response_shifts`.
    gain : ndarray, shape (n, 3, nz)
        Gain of ``u``, ``v``, ``w`` per test displacement and layer (1 = exact; NaN along an
        axis the test displacement does not move along).
    random : ndarray, shape (n, 3, nz)
        Random error of ``u``, ``v``, ``w`` per test displacement and layer, metres (the
        spread of the layer's vectors).
    statistics : ndarray, shape (n, 3, nz)
        Rms of the uncertainty the correlation statistics and the iteration tail gave
        the same vectors, metres.
    n_particles : int
        Particles per test pair.
    cell : ndarray, shape (3,), optional
        The resolution cell ``(lateral, lateral, depth)``, metres, in which the motion of a
        vector is measured (:meth:`excess`); None: the excess is the mean over the test
        displacements whatever a vector's motion.
    placement : ndarray, shape (n, 3, nz), optional
        Where the reconstruction puts the particles relative to where they are, per test
        pair, axis ``(x, y, z)`` and layer, metres (:func:`placement_offset`); None: not
        measured (no location term).
    """

    z: np.ndarray
    shifts: np.ndarray
    gain: np.ndarray
    random: np.ndarray
    statistics: np.ndarray
    n_particles: int
    cell: np.ndarray | None = None
    placement: np.ndarray | None = None

    def location(self, z) -> np.ndarray:
        """Placement offset of the reconstruction ``(3, len(z))``, metres, at depths ``z``.

        Per axis and layer, the mean offset ``m`` over the ``n`` test pairs with the
        uncertainty of that mean, ``sqrt(m² + s² / n)`` (``s`` their standard deviation), linear
        between the layers; zeros where the response carries no placement.
        """
        z = np.asarray(z, float)
        if self.placement is None:
            return np.zeros((3, z.size))
        p = np.asarray(self.placement, float)
        n = p.shape[0]
        spread2 = p.var(axis=0, ddof=1) / n if n > 1 else 0.0
        offset = np.sqrt(p.mean(axis=0) ** 2 + spread2)
        return np.stack([np.interp(z, self.z, r) for r in offset])

    def at(self, z) -> tuple[np.ndarray, np.ndarray]:
        """Gain and excess random error, each ``(3, len(z))``, at depths ``z`` (metres).

        The gain is the mean over the test displacements that move along its axis; the
        excess random error is
        ``sqrt(max(0, <r^2> - <s^2>))``, the test vectors' spread less what their correlation
        statistics saw (module notes), means over the test displacements. Both are linear
        between the layers.
        """
        z = np.asarray(z, float)
        moved = np.isfinite(self.gain)
        gain = np.where(moved.any(axis=0),
                        np.nansum(self.gain, axis=0) / np.maximum(moved.sum(axis=0), 1), 1.0)
        excess = np.sqrt(np.maximum((self.random**2).mean(axis=0)
                                    - (self.statistics**2).mean(axis=0), 0.0))
        return (np.stack([np.interp(z, self.z, g) for g in gain]),
                np.stack([np.interp(z, self.z, r) for r in excess]))

    def excess(self, z, disp) -> np.ndarray:
        r"""Excess random error of vectors by their motion, ``(3, nz, ny, nx)``, metres.

        Parameters
        ----------
        z : ndarray, shape (nz,)
            Depth of each layer of vectors, metres.
        disp : ndarray, shape (3, nz, ny, nx)
            The vectors' displacement ``(u, v, w)``, metres.

        Notes
        -----
        The excess is the error both reconstructions share: a particle near focus is
        reconstructed where its lenslet and depth cell put it, not where it is. At rest the
        two exposures hold the same particles at the same places and share it exactly, so a
        displacement computed from them has none of it; it appears as particles move across
        lenslets (lateral motion) and depth cells (depth motion), the more of them the
        farther they move, and in other components than the one that moves (a particle that
        moves along x alone changes the lenslets that see it, and with them its
        reconstructed depth). So per component and layer the excess variance is modelled as
        linear in the motion along each axis, :math:`r_{ex}^2 = a_x t_x + a_y t_y + a_z t_z`,
        with :math:`t_x = |u| / c_l`, :math:`t_y = |v| / c_l`, :math:`t_z = |w| / c_d` the
        motion in lateral and depth resolution cells (``cell``), the :math:`a \ge 0` fitted
        by non-negative least squares to the test pairs' excess :math:`\max(0, r^2 - s^2)`;
        the test pairs moving along x only and along depth only (``SEPARATING_SHIFTS``) tell
        the axes apart from the diagonal ones. Motions beyond the test pairs' largest are
        held there. Test pairs that cannot tell the three apart fall back to the lateral
        motion :math:`|(u, v)|` and the depth motion, and a single test pair to the whole
        motion :math:`|(t_x, t_y, t_z)|` through it. Scaling each component by its own
        displacement alone under-covers a component that does not move while the others do
        (Oseen's v: 80-88 %); a lateral motion counted whatever its direction over-covers it
        (99 % on the patch, where the test pairs' diagonal motion along y gave v an error
        that Oseen's motion along x does not, docs/validation/uncertainty.md). Without
        ``cell`` it is :meth:`at`'s excess, the same for every vector of a layer.
        """
        from scipy.optimize import nnls

        z = np.asarray(z, float)
        disp = np.asarray(disp, float)
        if self.cell is None:
            return np.broadcast_to(self.at(z)[1][:, :, None, None], disp.shape).copy()
        cell = np.asarray(self.cell, float)
        for level in (3, 2, 1):          # the finest motion model the test pairs determine
            test = _motion_in_cells(self.shifts.T, cell, level).T            # (n, terms)
            if np.linalg.matrix_rank(test) == level:
                break
        motion = np.nan_to_num(_motion_in_cells(disp, cell, level))
        motion = np.minimum(motion, test.max(axis=0)[:, None, None, None])
        excess2 = np.maximum(self.random**2 - self.statistics**2, 0.0)       # (n, 3, layers)
        out = np.zeros_like(disp)
        for k in range(3):
            coef = np.stack([nnls(test, excess2[:, k, layer])[0]
                             for layer in range(self.z.size)], axis=1)      # (terms, layers)
            at_z = np.stack([np.interp(z, self.z, c) for c in coef])          # (terms, nz)
            out[k] = np.einsum("tz,tz...->z...", at_z, motion)
        return np.sqrt(out)

    def to_dict(self) -> dict:
        """JSON-ready form (metres)."""
        return {"version": RESPONSE_VERSION, "z_m": self.z.tolist(),
                "shifts_m": self.shifts.tolist(), "gain": self.gain.tolist(),
                "random_m": self.random.tolist(), "statistics_m": self.statistics.tolist(),
                "n_particles": self.n_particles,
                "cell_m": None if self.cell is None else np.asarray(self.cell).tolist(),
                "placement_m": (None if self.placement is None
                                else np.asarray(self.placement).tolist())}

    @classmethod
    def from_dict(cls, d: dict) -> Response:
        """Inverse of :meth:`to_dict`."""
        if d.get("version") != RESPONSE_VERSION:
            raise ValueError(f"response version {d.get('version')!r}")
        cell, placement = d.get("cell_m"), d.get("placement_m")
        return cls(np.asarray(d["z_m"], float), np.asarray(d["shifts_m"], float),
                   np.asarray(d["gain"], float), np.asarray(d["random_m"], float),
                   np.asarray(d["statistics_m"], float), int(d["n_particles"]),
                   None if cell is None else np.asarray(cell, float),
                   None if placement is None else np.asarray(placement, float))


def _motion_in_cells(disp, cell, level: int) -> np.ndarray:
    """A motion ``(u, v, w, ...)`` in resolution cells, as ``level`` terms (first axis).

    3: along x, y and z apart; 2: lateral ``|(u, v)|`` and depth; 1: the whole motion.
    """
    t = np.abs(np.asarray(disp, float)) / np.asarray(cell, float).reshape(
        (3,) + (1,) * (np.ndim(disp) - 1))
    if level == 3:
        return t
    lateral = np.hypot(t[0], t[1])
    return np.stack([lateral, t[2]]) if level == 2 else np.hypot(lateral, t[2])[None]


RESPONSE_DISPLACEMENTS = (1, 3)
"""Valid numbers of test displacements: all three, or the middle one alone."""


def response_shifts(camera, f_number=None, displacements: int = 3) -> np.ndarray:
    """The test displacements ``(n, 3)``, metres.

    ``LATERAL_SHIFTS`` lenslet footprints along x and y with ``DEPTH_SHIFTS`` depth resolution
    cells along z, at once (``camera``: the effective camera,
    :func:`plenopiv.pipeline.resolution_cell`), then the ``SEPARATING_SHIFTS`` (lateral
    only, depth only). ``displacements`` 3 gives these five, 1 the middle one of the three
    alone (1.25 footprints, 0.25 depth resolution cells).
    """
    if displacements not in RESPONSE_DISPLACEMENTS:
        raise ValueError(f"displacements = {displacements!r}: expected one of "
                         f"{RESPONSE_DISPLACEMENTS}")
    pairs = [(a, a, b) for a, b in zip(LATERAL_SHIFTS, DEPTH_SHIFTS, strict=True)]
    if displacements == 1:
        pairs = pairs[len(pairs) // 2:len(pairs) // 2 + 1]
    else:
        pairs += list(SEPARATING_SHIFTS)
    return np.array(pairs) * _cell(camera, f_number)


def _cell(camera, f_number=None) -> np.ndarray:
    """The resolution cell ``(lateral, lateral, depth)``, metres, of the effective ``camera``."""
    from plenopiv.pipeline import resolution_cell

    lateral, depth = resolution_cell(camera, f_number)
    return np.array([lateral, lateral, depth])


def response_key(*parts) -> str:
    """A stable hash of what a response depends on (any JSON-able parts)."""
    h = hashlib.sha256()
    h.update(json.dumps([RESPONSE_VERSION, *parts], sort_keys=True, default=str).encode())
    return h.hexdigest()


def measure_response(calibration, grid, correction, *, reconstruct, correlate, n_particles: int,
                     f_number=None, rays_per_particle: int = 1024, seed: int = 0,
                     displacements: int = 3) -> Response:
    """Measure the chain's response to known uniform displacements (module notes).

    Parameters
    ----------
    calibration : Calibration
        The calibration of the experiment: its camera, with the calibrated S_i, renders the
        test images, blurred by the point spread measured on its focal-point image
        (:attr:`~plenopiv.calibration.model.Calibration.point_spread_sigma_px`; none when not
        measured).
    grid : VolumeGrid
        The reconstruction grid (effective coordinates).
    correction : DepthCorrection
        From effective to physical depth (the particles are seeded in physical depth).
    reconstruct : callable
        ``reconstruct(image) -> volume``, the reconstruction of the real images.
    correlate : callable
        ``correlate(volume_a, volume_b) -> VectorField``, the correlation of the real volumes.
    n_particles : int
        Particles per test pair (the real pair's seeding).
    f_number : float, optional
        Aperture of the recording (default: the camera's).
    rays_per_particle : int
        Rays per particle of the ray tracer.
    seed : int
        Seed of the particle positions and the tracer.
    displacements : {3, 1}
        Test displacements (:func:`response_shifts`): two reconstructions each.

    Returns
    -------
    Response or None
        None when no test pair gave a vector field (too few particles).
    """
    from plenopiv.synthetic.images import blurred, particle_image

    rng = np.random.default_rng(seed)
    psf = calibration.point_spread_sigma_px or 0.0
    camera = calibration.camera
    shifts = response_shifts(calibration.effective_camera, f_number, displacements)
    b = grid.bounds
    lo = np.array([b[0, 0], b[1, 0], correction.depth(b[2, 0])])
    hi = np.array([b[0, 1], b[1, 1], correction.depth(b[2, 1])])
    cell = _cell(calibration.effective_camera, f_number)
    blob_vox = cell[::-1] / FWHM_PER_SIGMA / np.asarray(grid.voxel, float)[::-1]   # (z, y, x)
    gains, spreads, stats, places = [], [], [], []
    z = None
    for i, s in enumerate(shifts):
        pos = rng.uniform(lo, hi, size=(max(int(n_particles), 1), 3))
        s_phys = s * np.array([1.0, 1.0, correction.scale])
        ia, ib = (blurred(particle_image(camera, p, rays_per_particle=rays_per_particle,
                                         f_number=f_number, seed=seed + 2 * i + j), psf)
                  for j, p in enumerate((pos, pos + s_phys)))
        try:
            volume_a = reconstruct(ia)
            field = correlate(volume_a, reconstruct(ib))
            place = placement_offset(volume_a, pos * np.array([1.0, 1.0, 1.0 / correction.scale]),
                                     grid, correlate, blob_vox)
        except PlenopivError:   # too few particles for a field: this test pair says nothing
            for out in (gains, spreads, stats, places):
                out.append(None)
            continue
        places.append(place)
        z = np.asarray(field.z)
        comps = np.stack([field.u, field.v, field.w])
        sigma = iteration_uncertainty(field)
        if sigma is None:
            sigma = np.stack([field.u_uncertainty, field.v_uncertainty, field.w_uncertainty])
        ok = np.asarray(field.valid) & np.all(np.isfinite(comps), axis=0)
        g = np.full((3, z.size), np.nan)
        r = np.full((3, z.size), np.nan)
        st = np.full((3, z.size), np.nan)
        for layer in range(z.size):
            sel = ok[layer]
            if sel.sum() < 2:
                continue
            for k in range(3):
                m = comps[k, layer][sel]
                if s[k] != 0.0:     # a gain along the axes the test pair moves along
                    g[k, layer] = m.mean() / s[k]
                r[k, layer] = m.std()
                sk = sigma[k, layer][sel]
                sk = sk[np.isfinite(sk)]
                st[k, layer] = np.sqrt(np.mean(sk**2)) if sk.size else 0.0
        gains.append(g)
        spreads.append(r)
        stats.append(st)
    if all(g is None for g in gains):
        return None
    keep = [i for i, g in enumerate(gains) if g is not None]
    gain = np.stack([gains[i] for i in keep])
    random = np.stack([spreads[i] for i in keep])
    statistics = np.stack([stats[i] for i in keep])
    placement = np.stack([places[i] for i in keep])
    moved = shifts[keep] != 0.0                     # (n, 3): an axis without motion has no gain
    _fill_empty_layers(gain, z, 1.0, moved)
    for values in (random, statistics, placement):
        _fill_empty_layers(values, z, 0.0)
    return Response(z, shifts[keep], gain, random, statistics, int(n_particles), cell,
                    placement)


FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))
"""Full width at half maximum of a Gaussian per standard deviation."""


def placement_offset(volume, positions, grid, correlate, blob_vox) -> np.ndarray:
    """Where a reconstruction puts its particles relative to where they are, ``(3, nz)``.

    Parameters
    ----------
    volume : ndarray, shape (nz, ny, nx)
        A reconstruction of particles at ``positions``.
    positions : ndarray, shape (n, 3)
        Their true positions ``(x, y, z)``, metres, in the grid's effective coordinates.
    grid : VolumeGrid
        The grid of ``volume``.
    correlate : callable
        ``correlate(volume_a, volume_b) -> VectorField``, as the real pair is correlated.
    blob_vox : sequence of 3 floats
        Standard deviation ``(z, y, x)``, voxels, of the Gaussian drawn at each true
        position (the resolution cell's).

    Returns
    -------
    ndarray, shape (3, nz)
        Per axis ``(x, y, z)`` and layer of vectors, the mean displacement from the true
        particles' volume to the reconstruction, metres (reconstructed minus true); NaN in
        a layer without a valid vector.

    Notes
    -----
    A vector is reported at its window's centre; if the reconstruction places the particles
    a distance δ from where they are, the window holds particles from around ``centre - δ``
    and the vector measures the flow there. Correlating the true particles' volume with the
    reconstruction measures δ as the windows see it (the correlation peak of each window
    follows the bulk of its particles' reconstructed intensity, elongation and ghosts
    included). On the 61 x 91-lenslet patch of the Auburn camera with its 10.4 mm substrate
    and a volume from Z = 0.5 to 8.5 mm, δz runs from -0.4 to -1.1 depth voxels (-49 to
    -135 µm, about 1.3 % of Z; the particles' own centroids agree), within 15 % whether the
    Gaussians are half or twice the resolution cell (docs/validation/uncertainty.md).
    """
    from plenopiv.pipeline import gaussian_truth_volume

    truth = gaussian_truth_volume(grid, positions, sigma_vox=blob_vox)
    field = correlate(truth, volume)
    comps = np.stack([field.u, field.v, field.w])
    ok = np.asarray(field.valid) & np.all(np.isfinite(comps), axis=0)
    out = np.full((3, ok.shape[0]), np.nan)
    for layer in range(ok.shape[0]):
        if ok[layer].any():
            out[:, layer] = comps[:, layer][:, ok[layer]].mean(axis=1)
    return out


def _fill_empty_layers(values, z, empty, rows=None) -> None:
    """Fill, in place, the layers without vectors (NaN) of ``values`` (n, 3, layers).

    From the nearest layers (linear between them), or ``empty`` where a row has none; rows
    where ``rows`` (n, 3) is false are left as they are.
    """
    for j in range(values.shape[0]):
        for k in range(3):
            if rows is not None and not rows[j, k]:
                continue
            bad = ~np.isfinite(values[j, k])
            if bad.all():
                values[j, k] = empty
            elif bad.any():
                values[j, k, bad] = np.interp(z[bad], z[~bad], values[j, k, ~bad])


def cached_response(path: Path | None, key: str, compute) -> tuple[Response | None, bool]:
    """The response stored at ``path`` under ``key``, else ``compute()`` (saved there).

    ``compute()`` returning None is not saved. Returns ``(response, from_cache)``; ``path``
    None disables the cache.
    """
    if path is not None and path.exists():
        try:
            d = json.loads(path.read_text())
            if d.get("key") == key:
                return Response.from_dict(d), True
        except (OSError, ValueError, KeyError, TypeError):
            pass   # unreadable or another version: measure again
    resp = compute()
    if path is not None and resp is not None:
        from plenopiv.products.files import atomic_path

        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps({"key": key, **resp.to_dict()}))
    return resp, False


def _second_difference(a, axis):
    """Second difference of ``a`` along ``axis`` (same shape, units of ``a``).

    Central ``a[i-1] - 2 a[i] + a[i+1]`` inside; a border point takes its neighbour's (the
    curvature held constant over the last step); zero along an axis of fewer than 3 points.
    """
    a = np.moveaxis(np.asarray(a, float), axis, 0)
    out = np.zeros_like(a)
    if a.shape[0] >= 3:
        out[1:-1] = a[:-2] - 2.0 * a[1:-1] + a[2:]
        out[0] = out[1]
        out[-1] = out[-2]
    return np.moveaxis(out, 0, axis)


def unresolved_gradient_bias(disp, spacing, window):
    r"""Bias of window-averaged displacements where the displacement curves inside a window.

    Parameters
    ----------
    disp : ndarray, shape (3, nz, ny, nx)
        Measured displacement ``(u, v, w)`` on the vector grid, metres (NaN: no vector).
    spacing : sequence of 3 floats
        Vector spacing along ``(x, y, z)``, metres.
    window : sequence of 3 floats
        Window edge along ``(x, y, z)``, metres.

    Returns
    -------
    ndarray, shape (3, nz, ny, nx)
        Magnitude of the estimated bias per component, metres; 0 where a second difference
        involves a missing vector.

    Notes
    -----
    A correlation window of edge :math:`W` weights the displacement in it about evenly (top
    hat), so it measures the window average rather than the value at its centre. Expanding
    the displacement to second order about the centre, the linear terms average out and

    .. math:: \bar u - u(0) = \sum_i \frac{1}{W_i}\int_{-W_i/2}^{W_i/2}
              \frac{x_i^2}{2}\,\partial_i^2 u \;dx_i
              = \sum_i \frac{W_i^2}{24}\, \partial_i^2 u .

    Window deformation removes part of it. A deformation pass moves the particles by the
    predictor :math:`P` (the previous vectors, trilinearly interpolated between vectors
    :math:`h` apart) and measures the window average of what is left, so at the iteration's
    fixed point :math:`d = P + \overline{u - P}`: the window averages of the flow's and of the
    predictor's curvature cancel, and only the mean error of the linear interpolation
    remains, :math:`-\sum_i (h_i^2/12)\, \partial_i^2 u` (half the one-window bias at 50 %
    overlap; ``tests/test_uncertainty.py`` iterates the fixed point). A few passes do not
    reach it for curvature on the scale of the vector spacing (on Hill's vortex the errors
    follow the one-window bias of the true field, docs/validation/uncertainty.md), so the
    one-window bias is kept as the bound.

    The second derivatives are taken from the measured field's second differences on the
    vector grid, :math:`\partial_i^2 u \approx \Delta_i^2 u / h_i^2` (with 50 % overlap,
    :math:`W = 2h` and the term is :math:`\Delta_i^2 u / 6` per axis). A uniform or linear
    field gives zero; a quadratic one gives the exact window-average bias.
    """
    disp = np.asarray(disp, float)
    out = np.zeros_like(disp)
    for axis_xyz in range(3):
        h, w = float(spacing[axis_xyz]), float(window[axis_xyz])
        if not (h > 0 and w > 0):
            continue
        array_axis = 3 - axis_xyz          # (component, z, y, x): x is array axis 3
        out += (w**2 / 24.0) / h**2 * _second_difference(disp, array_axis)
    return np.abs(np.nan_to_num(out, nan=0.0))


def curvature_noise_factor(spacing, window) -> float:
    r"""Variance of :func:`unresolved_gradient_bias` from vectors' random errors, per unit variance.

    Parameters
    ----------
    spacing, window : sequence of 3 floats
        Vector spacing and window edge along ``(x, y, z)``, metres (as for
        :func:`unresolved_gradient_bias`).

    Returns
    -------
    float
        :math:`k = 2 \sum_i a_i^2 + 4 (\sum_i a_i)^2` with :math:`a_i = W_i^2 / (24 h_i^2)`
        (dimensionless; 7/6 at 50 % overlap in 3-D).

    Notes
    -----
    The bias term is :math:`\sum_i a_i (d_{i-} - 2 d_0 + d_{i+})`. Vectors with independent
    random errors of variance :math:`\sigma^2` give it the variance
    :math:`\sigma^2 (2 \sum_i a_i^2 + 4 (\sum_i a_i)^2)` (the six neighbours once each, the
    centre with the sum of the weights): the estimate of a curvature from noisy vectors is
    about as large as their noise where the field does not curve at all. That noise is the
    vectors' random error, already counted; :func:`combine` removes its variance.
    """
    a = np.array([(float(w) ** 2 / 24.0) / float(h) ** 2 if float(h) > 0 and float(w) > 0
                  else 0.0 for h, w in zip(spacing, window, strict=True)])
    return float(2.0 * np.sum(a**2) + 4.0 * np.sum(a) ** 2)


def filter_offset(disp):
    r"""The change a converged pass still makes with the smoothed predictor, units of ``disp``.

    Parameters
    ----------
    disp : ndarray, shape (3, nz, ny, nx)
        Displacement on the vector grid (any unit; NaN counts as 0).

    Returns
    -------
    ndarray, shape (3, nz, ny, nx)
        :math:`d - S(d)`, with :math:`S` the predictor's binomial filter ``[1, 2, 1] / 4``
        per axis (:func:`plenopiv.piv.validation._smooth_predictor`).

    Notes
    -----
    A deformation pass correlates the volumes deformed by the smoothed predictor
    :math:`S(d_{k-1})` and adds the corrector it measures: :math:`d_k = S(d_{k-1}) + c_k`.
    At the iteration's fixed point :math:`d_k = d_{k-1} = d` the corrector is still
    :math:`c = d - S(d) \approx -\sum_i \Delta_i^2 d / 4`, nonzero wherever the field
    curves, although the estimate no longer changes. This part of the last correction is
    the filter's offset, not an error left by the iteration; the window-average bias of
    the same curvature is :func:`unresolved_gradient_bias`.
    """
    from plenopiv.piv.validation import _smooth_predictor

    d = np.nan_to_num(np.asarray(disp, float), nan=0.0)
    return d - _smooth_predictor(d)


def convergence_ratio(last, previous, usable, noise=None) -> np.ndarray:
    r"""Measured ratio of the last two corrections per component, ``(3,)``, dimensionless.

    Parameters
    ----------
    last, previous : ndarray, shape (3, nz, ny, nx)
        The last and the previous pass's corrections, the filter offset removed (metres).
    usable : ndarray of bool, shape (nz, ny, nx)
        Vectors to count (valid, finite in both).
    noise : ndarray, shape (3, nz, ny, nx), optional
        The random error of one pass's correction, metres: the correlation statistics
        (None: no noise, the ratio of the corrections as they are).

    Returns
    -------
    ndarray, shape (3,)
        :math:`\rho_k = \sqrt{(\langle c_{n,k}^2 \rangle - \langle \sigma_k^2 \rangle)
        / (\langle c_{n-1,k}^2 \rangle - \langle \sigma_k^2 \rangle)}` over the usable
        vectors, within ``[0, MAX_CONVERGENCE_RATIO]``: 0 where the last corrections are no
        larger than their noise, ``MAX_CONVERGENCE_RATIO`` where only the last ones exceed
        it; ``DEFAULT_RATIO`` for a component without usable vectors or without a previous
        change.

    Notes
    -----
    The passes converge geometrically when each removes a fraction :math:`1 - \rho` of the
    error it starts from: :math:`e_n = \rho\, e_{n-1}`, so the corrections shrink by the same
    factor, :math:`c_n = e_n - e_{n-1} = \rho\, c_{n-1}`, and what the last pass left is
    :math:`e_n = \rho / (1 - \rho)\; c_n` (:func:`iteration_uncertainty`). The ratio is
    taken over the whole field (a few hundred vectors: a local ratio of two noisy corrections
    would be unstable).

    Each correction also holds the random error of its correlation, which does not shrink
    from pass to pass: once the iteration has converged the corrections are that noise
    alone, and their ratio tends to 1 (a tail of nine times the noise at the cap) although
    nothing is left to correct. The noise adds in quadrature to the systematic change, so
    its variance (the correlation statistics, counted in the uncertainty on their own) is
    removed from both mean squares before the ratio is taken. On the vortex validations the
    offset-free last corrections are 0.3-0.9 times the correlation statistics
    (docs/validation/uncertainty.md): the passes have converged to their noise.
    """
    out = np.full(3, DEFAULT_RATIO)
    if previous is None:
        return out
    for k in range(3):
        a, b = last[k][usable], previous[k][usable]
        n2 = np.zeros_like(a) if noise is None else np.asarray(noise[k], float)[usable] ** 2
        ok = np.isfinite(a) & np.isfinite(b) & np.isfinite(n2)
        if not ok.any():
            continue
        noise2 = float(np.mean(n2[ok]))
        num = float(np.mean(a[ok] ** 2)) - noise2
        den = float(np.mean(b[ok] ** 2)) - noise2
        if num <= 0.0 and (noise is not None or den > 0.0):
            out[k] = 0.0
        elif den > 0.0:
            out[k] = min(np.sqrt(num / den), MAX_CONVERGENCE_RATIO)
        elif num > 0.0:
            out[k] = MAX_CONVERGENCE_RATIO
    return out


def iteration_uncertainty(field) -> np.ndarray | None:
    r"""Correlation statistics and the error the iteration left, ``(3, nz, ny, nx)``, metres.

    :math:`\sqrt{\sigma_{CS}^2 + (\rho / (1 - \rho))^2\, \max(0, (c_n - o)^2 - \sigma_{CS}^2)}`
    per component, with :math:`\sigma_{CS}` the correlation statistics, :math:`c_n` the last
    pass's correction, :math:`o` the filter's offset (:func:`filter_offset`; zero without a
    smoothed predictor) and :math:`\rho` the measured ratio of the last two corrections, their
    noise removed (:func:`convergence_ratio`; 1/2, i.e. the remaining error as large as the
    last correction, when the previous pass had other windows). The random error of the
    last correction is the correlation's, which :math:`\sigma_{CS}` counts already: only the
    part of the correction above it is a change the iteration was still making.
    A rejected vector keeps the uncertainty :func:`plenopiv.piv.correlate_volumes` gave it
    (its neighbours' uncertainty and spread). None when ``field`` carries no signed
    corrections (then its own uncertainty stands).
    """
    parts = field.uncertainty_parts or {}
    if "last_corrector" not in parts or "correlation" not in parts:
        return None
    disp = np.stack([field.u, field.v, field.w])
    smoothed = bool(getattr(field.settings, "smooth_predictor", False))
    offset = filter_offset(disp) if smoothed else np.zeros_like(disp)
    noise = np.asarray(parts["correlation"], float)
    last = np.asarray(parts["last_corrector"], float) - offset
    previous = parts.get("previous_corrector")
    if previous is not None:
        previous = np.asarray(previous, float) - offset
    usable = np.asarray(field.valid, bool) & np.all(np.isfinite(disp), axis=0)
    rho = convergence_ratio(last, previous, usable, noise)
    systematic = np.sqrt(np.maximum(np.nan_to_num(last) ** 2 - np.nan_to_num(noise) ** 2, 0.0))
    remaining = (rho / (1.0 - rho))[:, None, None, None] * systematic
    sigma = np.sqrt(noise**2 + remaining**2)
    own = np.stack([field.u_uncertainty, field.v_uncertainty, field.w_uncertainty])
    return np.where(np.asarray(field.valid, bool)[None], sigma, own)


REJECTED_RANGE_FACTOR = 1.0 / np.sqrt(12.0)
"""Standard deviation of a rectangular distribution over a range, per unit of its width."""


def rejected_neighbour_uncertainty(field) -> np.ndarray:
    r"""Uncertainty of vectors beside a rejected one, ``(3, nz, ny, nx)``, metres.

    Parameters
    ----------
    field : VectorField
        A field of :func:`plenopiv.piv.correlate_volumes`; its ``uncertainty_parts`` hold
        ``"rejected_disagreement"``, how far each rejected vector's own measurement lay from
        the median of its neighbours (0 for vectors that were not rejected).

    Returns
    -------
    ndarray, shape (3, nz, ny, nx)
        :math:`\max_j D_{j,k} / \sqrt{12}` per component ``k`` over the rejected vectors
        ``j`` of the vector's 3 x 3 x 3 neighbourhood (itself included), metres; 0 where none
        was rejected or the field carries no disagreements.

    Notes
    -----
    The median test rejects a vector whose measurement :math:`m_j` disagrees with the median
    :math:`\tilde m_j` of its neighbours by more than their noise allows; it cannot tell a
    spurious correlation peak from a flow that changes faster than the vector spacing
    resolves. On Hill's vortex the sphere's core reverses u within about one window: the
    rejected vectors are mostly the ones that saw the reversal, and their neighbours, whose
    windows overlap theirs by half, carry errors of the same order that no other term sees
    (docs/validation/uncertainty.md). Between the two readings the displacement near the
    rejected vector is known only to lie in the range :math:`D_j = |m_j - \tilde m_j|`; with
    nothing to prefer a value within it, a rectangular distribution over the range (GUM
    4.3.7) has the standard deviation :math:`D_j / \sqrt{12}`, counted for the rejected
    vector and each vector of its 3 x 3 x 3 neighbourhood (the neighbourhood of the median
    test), the largest where several apply. A field without rejected vectors gets 0.
    """
    import scipy.ndimage

    parts = field.uncertainty_parts or {}
    jump = parts.get("rejected_disagreement")
    shape = np.shape(field.u)
    if jump is None:
        return np.zeros((3,) + shape)
    jump = np.nan_to_num(np.asarray(jump, float))
    return REJECTED_RANGE_FACTOR * np.stack([
        scipy.ndimage.maximum_filter(jump[k], size=3, mode="constant", cval=0.0)
        for k in range(3)])


def location_uncertainty(disp, spacing, offset) -> np.ndarray:
    r"""Error of a vector reported at its window's centre while it measured elsewhere.

    Parameters
    ----------
    disp : ndarray, shape (3, nz, ny, nx)
        The measured displacement ``(u, v, w)``, metres (NaN where none).
    spacing : sequence of 3 floats
        Vector spacing along ``(x, y, z)``, metres (0 along an axis with one vector).
    offset : ndarray, shape (3, nz)
        The reconstruction's placement offset per axis ``(x, y, z)`` and layer, metres
        (:meth:`Response.location`).

    Returns
    -------
    ndarray, shape (3, nz, ny, nx)
        :math:`\sqrt{\sum_a (\partial d_k / \partial x_a\, \delta_a)^2}` per component
        ``k``, metres; 0 where a derivative is undefined (beside a NaN vector).

    Notes
    -----
    The window at centre ``c`` holds particles the reconstruction placed there, whose true
    positions lie around ``c - δ``; the vector is the displacement at ``c - δ``, reported at
    ``c``. The error is the change of the displacement over δ, ``-δ · ∇d`` to first order
    (GUM 5.1.3: the sensitivity coefficient of the position, here the measured field's
    gradient, central differences between vectors). The uniform test displacements of the
    response have no gradient and cannot show it; Oseen's u, which changes sign across the
    vortex's depth, was covered at 80 % on a volume 0.5-8.5 mm beyond the focal plane
    without it (docs/validation/uncertainty.md).
    """
    disp = np.asarray(disp, float)
    offset = np.nan_to_num(np.asarray(offset, float))
    out = np.zeros_like(disp)
    for k in range(3):
        for axis, (step, delta) in enumerate(zip(spacing, offset, strict=True)):
            array_axis = 2 - axis                   # x, y, z -> array axes 2, 1, 0
            if step <= 0 or disp.shape[1 + array_axis] < 2:
                continue
            slope = np.gradient(disp[k], step, axis=array_axis)
            out[k] += np.nan_to_num(slope * delta[:, None, None]) ** 2
    return np.sqrt(out)


def _spacing_and_window(field):
    """Vector spacing and last-pass window edge along ``(x, y, z)``, metres."""
    settings = field.settings
    window_vox = settings.window_vox(settings.passes - 1)[::-1]     # (wx, wy, wz)
    spacing = np.zeros(3)
    window = np.zeros(3)
    for i, c in enumerate((field.x, field.y, field.z)):
        if c.size < 2:
            continue
        spacing[i] = abs(float(c[1] - c[0]))
        step_vox = max(1, round(window_vox[i] * (1.0 - settings.overlap)))
        window[i] = window_vox[i] * spacing[i] / step_vox
    return spacing, window


def combine(field, response: Response | None):
    """The field with its uncertainties completed by the chain's response (module notes).

    ``field`` is a :class:`~plenopiv.piv.VectorField` (effective coordinates) whose
    ``u_uncertainty`` etc. hold the correlation statistics; ``response`` None returns it as
    is. Vectors without a displacement (NaN) keep NaN.
    """
    if response is None:
        return field
    disp = np.stack([field.u, field.v, field.w])
    sigma_cs = iteration_uncertainty(field)
    if sigma_cs is None:
        sigma_cs = np.stack([field.u_uncertainty, field.v_uncertainty, field.w_uncertainty])
    gain = response.at(field.z)[0][:, :, None, None]
    excess = response.excess(field.z, disp)
    g = np.maximum(gain, MIN_GAIN)
    sigma_gain = np.abs(1.0 - g) / g * np.abs(disp)
    spacing, window = _spacing_and_window(field)
    parts = dict(field.uncertainty_parts or {})
    # the curvature estimate less the part the vectors' random errors give it (counted by
    # the correlation statistics and the response's excess already)
    random = parts.get("correlation")
    random = (np.zeros_like(disp) if random is None
              else np.nan_to_num(np.asarray(random, float))) ** 2 + excess**2
    sigma_curv = np.sqrt(np.maximum(
        unresolved_gradient_bias(disp, spacing, window) ** 2
        - curvature_noise_factor(spacing, window) * random, 0.0))
    sigma_rejected = rejected_neighbour_uncertainty(field)
    sigma_location = location_uncertainty(disp, spacing, response.location(field.z))
    total = np.sqrt(sigma_cs**2 + excess**2 + sigma_gain**2 + sigma_curv**2
                    + sigma_rejected**2 + sigma_location**2)
    parts["response_random"] = excess
    parts["response_gain"] = sigma_gain
    parts["unresolved_gradient"] = sigma_curv
    parts["rejected_neighbour"] = sigma_rejected
    parts["location"] = sigma_location
    return replace(field, u_uncertainty=total[0], v_uncertainty=total[1],
                   w_uncertainty=total[2], uncertainty_parts=parts)
