"""The chain's measured response to known displacements (the type-B part of the uncertainty).

Ray-traced test pairs of random particles, moved by known uniform displacements, reconstructed
and correlated as the real pair is: per layer of vectors their gain, the error both
reconstructions share, and where the reconstruction places the particles. How these complete
the correlation statistics of each vector is :mod:`plenopiv.piv.uncertainty` (module notes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plenopiv.piv.settings import RESPONSE_DISPLACEMENTS, RESPONSE_PARTICLES_PER_LENSLET

__all__ = [
    "DEPTH_SHIFTS",
    "EXCESS_MOTION_LEVELS",
    "LATERAL_SHIFTS",
    "RESPONSE_DISPLACEMENTS",
    "RESPONSE_PARTICLES_PER_LENSLET",
    "RESPONSE_VERSION",
    "SEPARATING_SHIFTS",
    "Response",
    "lateral_edge",
    "cell_blob_vox",
    "modulation_displacement",
    "rejected_disagreements",
    "response_shifts",
    "spurious_disagreement",
    "vector_spacing",
]


LATERAL_SHIFTS = (0.5, 1.25, 1.75)
"""Test displacements along x and y, lenslet footprints (different fractions of a footprint)."""


DEPTH_SHIFTS = (0.1, 0.25, 0.5)
"""Test displacements along z, depth resolution cells."""


SEPARATING_SHIFTS = ((1.25, 0.0, 0.0), (0.0, 0.0, 0.5))
"""Two more test displacements ``(x, y, z)`` (lenslet footprints along x and y, depth
resolution cells along z): one along x only, one along depth only, so that the shared error
of the motion along each axis can be told apart (:meth:`Response.excess`)."""


MODULATION_PERIOD = 4
"""Wavelength of the modulation test pairs, vector spacings: two windows at 50 % overlap, the
shortest wavelength whose sampling on the vector grid shows a curvature (at two spacings,
the grid's Nyquist limit, a top-hat window's response is zero)."""


MODULATION_GRADIENT = 0.125
"""Largest displacement gradient of the modulation test pairs, voxel per voxel (a window
deformation follows it; particle images stay matched)."""


MODULATION_AXES = ((1, 2, 0), (2, 0, 1), (0, 1, 2))
"""Per modulation test pair, the axis ``(x, y, z)`` = ``(0, 1, 2)`` along which ``u``, ``v``
and ``w`` vary: three pairs give every component along every axis."""


EXCESS_MOTION_LEVELS = (3, 3, 2)
"""Per component ``(u, v, w)``, the motion its shared error is fitted in
(:meth:`Response.excess`): 3, the motion along x, y and z apart; 2, the lateral motion's
magnitude and the depth motion. A lateral component's error follows the motion along its own
axis more than across it, so ``u`` and ``v`` take the three axes apart; the depth component
has no lateral direction of its own, and a lattice symmetric in x and y gives it the same
error for the same lateral motion whichever way it goes."""


RESPONSE_VERSION = 10



def lateral_edge(shape) -> np.ndarray:
    """Vectors on a layer's lateral edge (first or last row or column), bool ``(nz, ny, nx)``.

    Their windows hold the volume's lateral boundary: particles cross it between the
    exposures and its voxels are seen by fewer lines of sight, so their errors differ from
    the interior's (:class:`Response` keeps the two apart).
    """
    nz, ny, nx = shape
    iy = np.arange(ny)[:, None]
    ix = np.arange(nx)[None, :]
    edge = (iy == 0) | (iy == ny - 1) | (ix == 0) | (ix == nx - 1)
    return np.broadcast_to(edge, (nz, ny, nx)).copy()


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
        Random error of ``u``, ``v``, ``w`` per test displacement and layer, metres: the rms
        deviation from the layer's mean of the layer's interior vectors (of all its vectors
        when ``edge_random`` is None).
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
    edge_random, edge_statistics : ndarray, shape (n, 3, nz), optional
        As ``random`` and ``statistics`` for the vectors on the layer's lateral edge
        (:func:`lateral_edge`); None: one set for every vector of a layer.
    modulation : ndarray, shape (3, 3), optional
        Gain of ``u``, ``v``, ``w`` (rows) for a displacement that varies sinusoidally along
        ``x``, ``y``, ``z`` (columns) with a wavelength of ``MODULATION_PERIOD`` vector
        spacings (:func:`modulation_gain`; the chain's spatial response at the shortest
        wavelength the vectors resolve); NaN where not measured, None: not measured.
    spurious : ndarray, shape (3,), optional
        Median over the uniform test pairs' rejected vectors of how far each one's own
        measurement lay from its neighbours' median, per component, metres (0 where no
        test vector was rejected): what a spurious correlation peak makes the median test
        see where no flow is left unresolved (:func:`spurious_disagreement`); None: not
        measured.
    """

    z: np.ndarray
    shifts: np.ndarray
    gain: np.ndarray
    random: np.ndarray
    statistics: np.ndarray
    n_particles: int
    cell: np.ndarray | None = None
    placement: np.ndarray | None = None
    edge_random: np.ndarray | None = None
    edge_statistics: np.ndarray | None = None
    modulation: np.ndarray | None = None
    spurious: np.ndarray | None = None

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

    def gain_error(self, z, min_gain: float = 0.1) -> np.ndarray:
        r"""Relative error of a displacement measured at the chain's gain, ``(3, len(z))``.

        Per component and layer, :math:`\sqrt{\langle ((1 - g_j) / g_j)^2 \rangle_j}` over
        the test pairs ``j`` that move along its axis, each :math:`g_j` held at ``min_gain``
        or more (dimensionless; 0 where no test pair moves along it), linear between the
        layers. A displacement measured at gain :math:`g` errs by :math:`(g - 1) / g` of the
        measured value. The gain depends on the displacement (near focus a tenth of a depth
        cell may be measured twice over and half a cell at its size), and which test
        displacement a vector's gain is nearest is not known: the error at the mean gain,
        :math:`|1 - \bar g| / \bar g`, vanishes where the test pairs' gains lie either side
        of 1 although each of them errs; the rms over the test pairs does not
        (docs/validation/uncertainty_loo.md).
        """
        z = np.asarray(z, float)
        moved = np.isfinite(self.gain)
        g = np.maximum(np.where(moved, self.gain, 1.0), min_gain)
        rel2 = np.where(moved, ((1.0 - g) / g) ** 2, 0.0)
        rms = np.sqrt(rel2.sum(axis=0) / np.maximum(moved.sum(axis=0), 1))
        return np.stack([np.interp(z, self.z, r) for r in rms])

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
        the axes apart from the diagonal ones. The depth component has no lateral direction
        of its own: on a lattice symmetric in x and y a lateral motion changes its error by
        as much whichever way it goes, so ``w`` is fitted in the lateral motion's magnitude
        :math:`|(t_x, t_y)|` and the depth motion (``EXCESS_MOTION_LEVELS``). Fitted along x
        and y apart, the test pairs, whose lateral motion is along x alone or diagonal, gave
        ``w`` the whole lateral error along x and none along y (its diagonal pairs' error is
        no larger than the pair's along x alone), and a flow moving across y had its depth
        error under-covered (docs/validation/uncertainty_loo.md). Motions beyond the test
        pairs' largest are
        held there. Test pairs that cannot tell the three apart fall back to the lateral
        motion :math:`|(u, v)|` and the depth motion, and a single test pair to the whole
        motion :math:`|(t_x, t_y, t_z)|` through it. Scaling each component by its own
        displacement alone under-covers a component that does not move while the others do;
        a lateral motion counted whatever its direction over-covers one where the test pairs'
        diagonal motion gives it an error that the real flow's motion does not
        (docs/validation/uncertainty.md). Without ``cell`` it is :meth:`at`'s excess, the
        same for every vector of a layer.

        With ``edge_random``, the vectors on a layer's lateral edge (:func:`lateral_edge`)
        get the fit to the test pairs' edge vectors, the others the fit to their interior
        ones: the windows that hold the volume's lateral boundary err more (particles cross
        it between the exposures, fewer lines of sight see its voxels), and a layer's mean
        would give the interior vectors the edge's error and the edge vectors too little
        (docs/validation/uncertainty.md).
        """
        from scipy.optimize import nnls

        z = np.asarray(z, float)
        disp = np.asarray(disp, float)
        if self.cell is None:
            return np.broadcast_to(self.at(z)[1][:, :, None, None], disp.shape).copy()
        cell = np.asarray(self.cell, float)
        models = []                      # per component: its test pairs' and vectors' motion
        for finest in EXCESS_MOTION_LEVELS:
            for level in range(finest, 0, -1):   # the finest model the test pairs determine
                test = _motion_in_cells(self.shifts.T, cell, level).T        # (n, terms)
                if np.linalg.matrix_rank(test) == level:
                    break
            motion = np.nan_to_num(_motion_in_cells(disp, cell, level))
            models.append((test, np.minimum(motion, test.max(axis=0)[:, None, None, None])))

        def fitted(random, statistics):
            excess2 = np.maximum(random**2 - statistics**2, 0.0)            # (n, 3, layers)
            out = np.zeros_like(disp)
            for k, (test, motion) in enumerate(models):
                coef = np.stack([nnls(test, excess2[:, k, layer])[0]
                                 for layer in range(self.z.size)], axis=1)  # (terms, layers)
                at_z = np.stack([np.interp(z, self.z, c) for c in coef])      # (terms, nz)
                out[k] = np.einsum("tz,tz...->z...", at_z, motion)
            return out

        variance = fitted(self.random, self.statistics)
        if self.edge_random is not None:
            edge = lateral_edge(disp.shape[1:])[None]
            variance = np.where(edge, fitted(self.edge_random, self.edge_statistics), variance)
        return np.sqrt(variance)

    def to_dict(self) -> dict:
        """JSON-ready form (metres)."""
        return {"version": RESPONSE_VERSION, "z_m": self.z.tolist(),
                "shifts_m": self.shifts.tolist(), "gain": self.gain.tolist(),
                "random_m": self.random.tolist(), "statistics_m": self.statistics.tolist(),
                "n_particles": self.n_particles,
                "cell_m": None if self.cell is None else np.asarray(self.cell).tolist(),
                "placement_m": (None if self.placement is None
                                else np.asarray(self.placement).tolist()),
                "edge_random_m": (None if self.edge_random is None
                                  else np.asarray(self.edge_random).tolist()),
                "edge_statistics_m": (None if self.edge_statistics is None
                                      else np.asarray(self.edge_statistics).tolist()),
                "modulation": (None if self.modulation is None
                               else np.asarray(self.modulation).tolist()),
                "spurious_m": (None if self.spurious is None
                               else np.asarray(self.spurious).tolist())}

    @classmethod
    def from_dict(cls, d: dict) -> Response:
        """Inverse of :meth:`to_dict`."""
        if d.get("version") != RESPONSE_VERSION:
            raise ValueError(f"response version {d.get('version')!r}")
        def array(key):
            value = d.get(key)
            return None if value is None else np.asarray(value, float)

        return cls(array("z_m"), array("shifts_m"), array("gain"), array("random_m"),
                   array("statistics_m"), int(d["n_particles"]), array("cell_m"),
                   array("placement_m"), array("edge_random_m"), array("edge_statistics_m"),
                   array("modulation"), array("spurious_m"))


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




def response_shifts(camera, f_number=None, displacements: int = 3) -> np.ndarray:
    """The test displacements ``(n, 3)``, metres.

    ``LATERAL_SHIFTS`` lenslet footprints along x and y with ``DEPTH_SHIFTS`` depth resolution
    cells along z, at once (``camera``: the effective camera,
    :func:`plenopiv.camera.resolution.resolution_cell`), then the ``SEPARATING_SHIFTS`` (lateral
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
    from plenopiv.camera.resolution import resolution_cell

    lateral, depth = resolution_cell(camera, f_number)
    return np.array([lateral, lateral, depth])


def modulation_displacement(points, wavelength, amplitude, axes, phase) -> np.ndarray:
    """A sinusoidal displacement field ``(n, 3)`` at ``points`` ``(n, 3)``, metres.

    Component ``k`` is ``amplitude[k] sin(2 pi x_a / wavelength[a] + phase[k])`` with
    ``a = axes[k]`` (points, wavelengths and amplitudes in metres, effective coordinates;
    phases in radians); 0 where ``wavelength[a]`` is not positive.
    """
    points = np.asarray(points, float)
    out = np.zeros_like(points)
    for k, a in enumerate(axes):
        if wavelength[a] > 0:
            out[:, k] = amplitude[k] * np.sin(2.0 * np.pi * points[:, a] / wavelength[a]
                                              + phase[k])
    return out


def modulation_gain(field, wavelength, amplitude, axes, phase) -> np.ndarray:
    """Gain ``(3,)`` of each component of a field measured on a sinusoidal displacement.

    Per component ``k``, the least-squares coefficient of ``sin(theta)`` in
    ``m_k = H A_k sin(theta) + b cos(theta) + c`` over the valid vectors, ``theta`` the phase
    of :func:`modulation_displacement` at the vectors' centres, divided by the amplitude
    ``A_k``: the in-phase part of the measured wave, a shift of the wave (where the
    reconstruction places particles off their positions) going to ``b``. NaN where the
    component's wavelength is not positive or fewer than four vectors are valid.
    """
    comps = np.stack([field.u, field.v, field.w])
    ok = np.asarray(field.valid) & np.all(np.isfinite(comps), axis=0)
    zz, yy, xx = np.meshgrid(field.z, field.y, field.x, indexing="ij")
    centres = np.stack([xx[ok], yy[ok], zz[ok]], axis=1)
    out = np.full(3, np.nan)
    for k, a in enumerate(axes):
        if not (wavelength[a] > 0 and amplitude[k] > 0) or ok.sum() < 4:
            continue
        theta = 2.0 * np.pi * centres[:, a] / wavelength[a] + phase[k]
        design = np.stack([np.sin(theta), np.cos(theta), np.ones_like(theta)], axis=1)
        coef = np.linalg.lstsq(design, comps[k][ok], rcond=None)[0]
        out[k] = coef[0] / amplitude[k]
    return out


def vector_spacing(field) -> np.ndarray:
    """Spacing of a field's vectors along ``(x, y, z)``, metres (0 along an axis with one)."""
    return np.array([abs(float(c[1] - c[0])) if c.size > 1 else 0.0
                     for c in (np.asarray(field.x), np.asarray(field.y), np.asarray(field.z))])


def _modulation(field, voxel, pair) -> np.ndarray:
    """The chain's gain ``(3, 3)`` at ``MODULATION_PERIOD`` vector spacings (module notes).

    ``field``: any test pair's field (its vector grid is the real pair's); ``voxel``: the
    grid's voxel ``(x, y, z)``, metres; ``pair(displacement) -> VectorField or None`` renders,
    reconstructs and correlates a test pair whose particles move by ``displacement(points)``.
    Rows: ``u``, ``v``, ``w``; columns: the axis of variation ``x``, ``y``, ``z``; NaN where
    an axis has fewer than three vectors or a pair gave no field.
    """
    counts = np.array([np.size(field.x), np.size(field.y), np.size(field.z)])
    wavelength = np.where(counts >= 3, MODULATION_PERIOD * vector_spacing(field), 0.0)
    voxel = np.asarray(voxel, float)
    out = np.full((3, 3), np.nan)
    for i, axes in enumerate(MODULATION_AXES):
        # in voxels of its own component, each wave's gradient is MODULATION_GRADIENT
        amplitude = np.array([MODULATION_GRADIENT * wavelength[a] / (2.0 * np.pi)
                              * voxel[k] / voxel[a] for k, a in enumerate(axes)])
        phase = 2.0 * np.pi * (np.arange(3) + i) / 9.0 + 0.3
        measured = pair(lambda p, amplitude=amplitude, axes=axes, phase=phase:
                        modulation_displacement(p, wavelength, amplitude, axes, phase))
        if measured is not None:
            gain = modulation_gain(measured, wavelength, amplitude, axes, phase)
            for k, a in enumerate(axes):
                out[k, a] = gain[k]
    return out


def rejected_disagreements(field) -> np.ndarray:
    """How far each rejected vector's measurement lay from its neighbours' median, ``(n, 3)``.

    Metres ``(u, v, w)``, one row per vector the median test rejected (the field's
    ``uncertainty_parts["rejected_disagreement"]``, nonzero there); no rows when none was or
    the field carries no disagreements.
    """
    jump = (field.uncertainty_parts or {}).get("rejected_disagreement")
    if jump is None:
        return np.zeros((0, 3))
    jump = np.nan_to_num(np.asarray(jump, float)).reshape(3, -1)
    return jump[:, np.any(jump > 0.0, axis=0)].T


def spurious_disagreement(rejected) -> np.ndarray:
    r"""Median per component of the uniform test pairs' rejected disagreements, ``(3,)``, metres.

    Parameters
    ----------
    rejected : sequence of ndarray, shape (n_i, 3)
        Per test pair, :func:`rejected_disagreements` of its field.

    Returns
    -------
    ndarray, shape (3,)
        The median of :math:`D_k` over every rejected vector of every pair; 0 where none
        was rejected.

    Notes
    -----
    A test pair moves its particles uniformly: the vectors resolve its flow exactly, so
    every vector the median test rejects there is a spurious correlation peak (a ghost
    particle, an unmatched particle pair, the elongated depth peak's neighbour), and its
    disagreement with its neighbours is that peak's reach. The error such a peak leaves in
    the vectors around it is in the test vectors' spread already (the response's random
    error); :func:`plenopiv.piv.uncertainty.rejected_neighbour_uncertainty` counts only
    what a real field's rejections hold beyond it, the flow the vectors do not resolve.

    The reach is the median, not the rms: the disagreements are heavy-tailed. A few peaks
    on ghost particles several voxels off dominate an rms, which would then discount a real
    field's lateral disagreements where a vortex reverses within a window as if they were
    such peaks (docs/validation/uncertainty.md).
    """
    rows = np.concatenate([np.zeros((0, 3))]
                          + [np.asarray(r, float).reshape(-1, 3) for r in rejected])
    return np.median(rows, axis=0) if len(rows) else np.zeros(3)


FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))
"""Full width at half maximum of a Gaussian per standard deviation."""


def cell_blob_vox(camera, grid, f_number=None) -> np.ndarray:
    """The true image of a particle: a Gaussian's standard deviation ``(z, y, x)``, voxels.

    As wide (full width at half maximum) as the effective ``camera``'s resolution cell, in
    voxels of ``grid``.
    """
    return _cell(camera, f_number)[::-1] / FWHM_PER_SIGMA / np.asarray(grid.voxel, float)[::-1]


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

