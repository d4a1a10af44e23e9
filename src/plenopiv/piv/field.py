"""The result of a volumetric cross-correlation: :class:`VectorField` and its flag bits."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from plenopiv.piv.settings import PIVSettings

FLAG_OUTLIER = 1
"""Bit of :attr:`VectorField.flag`: the vector failed the normalised median test."""
FLAG_EMPTY = 2
"""Bit of :attr:`VectorField.flag`: the window had no intensity variation (no particles)."""
FLAG_MASKED = 4
"""Bit of :attr:`VectorField.flag`: the window centre lies in the volume mask."""
FLAG_FEW_PARTICLES = 8
"""Bit of :attr:`VectorField.flag`: a window of the vector held fewer particles than
:attr:`~plenopiv.piv.settings.PIVSettings.min_particles_per_window` (in volume A or B)."""

def _readonly(array, dtype):
    a = np.array(array, dtype=dtype, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class VectorField:
    """A 3-D displacement field on the window-centre grid of the last PIV pass.

    Attributes
    ----------
    x, y, z : ndarray, shape (nx,), (ny,), (nz,)
        Window-centre coordinates in metres (volume coordinates X, Y, Z).
    u, v, w : ndarray, shape (nz, ny, nx)
        Displacement along x, y and z in metres (the volumes' ``[z, y, x]`` order is kept for
        the array axes; ``u`` is the x component).
    valid : ndarray of bool, shape (nz, ny, nx)
        False where the vector was rejected: it failed the normalised median test, its
        window had no particles, or its window centre is masked (``flag`` says which).
    snr : ndarray, shape (nz, ny, nx)
        Primary-to-secondary correlation peak ratio (dimensionless, >= 1; inf where no
        positive secondary peak exists); also available as :attr:`peak_ratio`.
    correlation : ndarray, shape (nz, ny, nx)
        Height of the correlation peak as a correlation coefficient (dimensionless, <= 1);
        0 for a window without particles. ``snr`` and ``correlation`` describe each window's
        own correlation in the last pass, also where its vector was replaced.
    n_replaced : int
        Number of vectors replaced after the last pass (``replaced.sum()``).
    settings : PIVSettings
        The settings that produced the field.
    replaced : ndarray of bool, shape (nz, ny, nx)
        True where a rejected vector was filled from its neighbours (``settings.replacement``
        ``"median"`` or ``"mean"``); rejected vectors that are not replaced are NaN. Default:
        ``~valid`` where ``u`` is finite.
    flag : ndarray of uint8, shape (nz, ny, nx)
        Why a vector was rejected, a sum of the bits ``FLAG_OUTLIER`` (1, normalised median
        test), ``FLAG_EMPTY`` (2, no intensity variation in the window), ``FLAG_MASKED``
        (4, window centre in the volume mask) and ``FLAG_FEW_PARTICLES`` (8, fewer particles
        in a window than ``settings.min_particles_per_window``); 0 for a valid vector.
        Default: ``FLAG_OUTLIER`` where not ``valid``.
    u_uncertainty, v_uncertainty, w_uncertainty : ndarray, shape (nz, ny, nx)
        Standard uncertainty of ``u``, ``v``, ``w`` in metres (see :mod:`plenopiv.piv.multipass`,
        *Uncertainty*); NaN where no vector is given. Default: NaN (not estimated).
    uncertainty_parts : dict
        The terms of the uncertainty, each ``(3, nz, ny, nx)`` metres in ``(u, v, w)`` order:
        ``"correlation"`` (correlation statistics) and ``"last_correction"`` (the last pass's
        change of the estimate), for diagnostics; None if not estimated.
    particles_per_window : ndarray of int32, shape (nz, ny, nx)
        The particles the vector's windows of the last pass held: the fewer of volume A's
        and volume B's (:mod:`plenopiv.piv.evidence`). Default: -1 (not counted).

    All arrays are read-only.
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    u: np.ndarray
    v: np.ndarray
    w: np.ndarray
    valid: np.ndarray
    snr: np.ndarray
    correlation: np.ndarray
    n_replaced: int = 0
    settings: PIVSettings = field(default_factory=PIVSettings)
    replaced: np.ndarray | None = None
    flag: np.ndarray | None = None
    u_uncertainty: np.ndarray | None = None
    v_uncertainty: np.ndarray | None = None
    w_uncertainty: np.ndarray | None = None
    uncertainty_parts: dict | None = field(default=None, compare=False, repr=False)
    particles_per_window: np.ndarray | None = None

    def __post_init__(self):
        for name in ("x", "y", "z"):
            object.__setattr__(self, name, _readonly(getattr(self, name), np.float64))
            if getattr(self, name).ndim != 1:
                raise ValueError(f"{name} has shape {getattr(self, name).shape}: expected 1-D")
        shape = (self.z.size, self.y.size, self.x.size)
        valid = np.asarray(self.valid, dtype=bool)
        if self.replaced is None:
            object.__setattr__(self, "replaced", ~valid & np.isfinite(np.asarray(self.u, float)))
        if self.flag is None:
            object.__setattr__(self, "flag", np.where(valid, 0, FLAG_OUTLIER))
        for name in ("u_uncertainty", "v_uncertainty", "w_uncertainty"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(shape, np.nan))
        if self.particles_per_window is None:
            object.__setattr__(self, "particles_per_window", np.full(shape, -1))
        for name, dtype in (
            ("u", np.float64),
            ("v", np.float64),
            ("w", np.float64),
            ("valid", bool),
            ("snr", np.float64),
            ("correlation", np.float64),
            ("replaced", bool),
            ("flag", np.uint8),
            ("u_uncertainty", np.float64),
            ("v_uncertainty", np.float64),
            ("w_uncertainty", np.float64),
            ("particles_per_window", np.int32),
        ):
            object.__setattr__(self, name, _readonly(getattr(self, name), dtype))
            if getattr(self, name).shape != shape:
                raise ValueError(
                    f"{name} has shape {getattr(self, name).shape}: expected (nz, ny, nx) = {shape}"
                )

    @property
    def shape(self):
        """Number of vectors per axis ``(nz, ny, nx)``."""
        return self.u.shape

    @property
    def peak_ratio(self):
        """Primary-to-secondary correlation peak ratio (the same array as ``snr``)."""
        return self.snr

    @property
    def masked(self):
        """True where the window centre lies in the volume mask (bool, (nz, ny, nx))."""
        return (self.flag & FLAG_MASKED) != 0

    def velocity(self, dt):
        """Velocity components ``(u, v, w) / dt`` in m/s.

        Parameters
        ----------
        dt : float
            Time between the two volumes, seconds (> 0).

        Returns
        -------
        tuple of ndarray
            ``(vx, vy, vz)``, each of shape ``(nz, ny, nx)``, in m/s.
        """
        if not (isinstance(dt, (int, float, np.floating)) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt = {dt!r}: expected a finite time between the volumes > 0 s")
        return self.u / dt, self.v / dt, self.w / dt

