"""The chain's measured response to known displacements (the type-B part of the uncertainty).

Ray-traced test pairs of random particles, moved by known uniform displacements, reconstructed
and correlated as the real pair is: per layer of vectors their gain, the error both
reconstructions share, and where the reconstruction places the particles. How these complete
the correlation statistics of each vector is :mod:`plenopiv.piv.uncertainty` (module notes).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plenopiv.errors import PlenopivError

__all__ = [
    "DEPTH_SHIFTS",
    "LATERAL_SHIFTS",
    "RESPONSE_DISPLACEMENTS",
    "RESPONSE_VERSION",
    "SEPARATING_SHIFTS",
    "Response",
    "cached_response",
    "cell_blob_vox",
    "measure_response",
    "placement_offset",
    "response_key",
    "response_shifts",
]

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
    blob_vox = cell_blob_vox(calibration.effective_camera, grid, f_number)
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
        for out, values in zip((gains, spreads, stats), _layer_statistics(field, s),
                               strict=True):
            out.append(values)
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


def _layer_statistics(field, shift):
    """Gain, spread and rms uncertainty of a test pair's vectors, each ``(3, nz)``.

    Per component and layer of valid vectors: the mean over the true ``shift`` (metres;
    NaN along an axis it does not move), the standard deviation (metres), and the rms of
    the correlation statistics with the iteration tail (metres); NaN in a layer with fewer
    than two vectors.
    """
    from plenopiv.piv.uncertainty import iteration_uncertainty

    comps = np.stack([field.u, field.v, field.w])
    sigma = iteration_uncertainty(field)
    if sigma is None:
        sigma = np.stack([field.u_uncertainty, field.v_uncertainty, field.w_uncertainty])
    ok = np.asarray(field.valid) & np.all(np.isfinite(comps), axis=0)
    nz = comps.shape[1]
    gain, spread, stats = (np.full((3, nz), np.nan) for _ in range(3))
    for layer in range(nz):
        sel = ok[layer]
        if sel.sum() < 2:
            continue
        for k in range(3):
            m = comps[k, layer][sel]
            if shift[k] != 0.0:     # a gain along the axes the test pair moves along
                gain[k, layer] = m.mean() / shift[k]
            spread[k, layer] = m.std()
            sk = sigma[k, layer][sel]
            sk = sk[np.isfinite(sk)]
            stats[k, layer] = np.sqrt(np.mean(sk**2)) if sk.size else 0.0
    return gain, spread, stats


FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))
"""Full width at half maximum of a Gaussian per standard deviation."""


def cell_blob_vox(camera, grid, f_number=None) -> np.ndarray:
    """The true image of a particle: a Gaussian's standard deviation ``(z, y, x)``, voxels.

    As wide (full width at half maximum) as the effective ``camera``'s resolution cell, in
    voxels of ``grid``.
    """
    return _cell(camera, f_number)[::-1] / FWHM_PER_SIGMA / np.asarray(grid.voxel, float)[::-1]


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
