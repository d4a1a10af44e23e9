"""Analytic flows for synthetic particle fields, and particle advection.

Every flow maps volume points ``(N, 3)`` ``(X, Y, Z)`` in metres to velocities ``(N, 3)`` in
m/s (components along X, Y, Z). :func:`advect` moves particles with a fourth-order
Runge-Kutta integration, so pairs carry an exact ground-truth displacement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from plenopiv.errors import ConfigError


def _unit(v, name):
    a = np.asarray(v, dtype=float)
    n = np.linalg.norm(a)
    if a.shape != (3,) or not n > 0:
        raise ConfigError(f"{name} = {v!r}: expected a non-zero 3-vector (x, y, z)")
    return a / n


@dataclass(frozen=True)
class Uniform:
    """Uniform translation with velocity ``velocity`` (3,), m/s."""

    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __call__(self, points, t: float = 0.0):
        """Velocity (N, 3), m/s, at volume points (N, 3), metres."""
        p = np.asarray(points, dtype=float)
        return np.broadcast_to(np.asarray(self.velocity, dtype=float), p.shape).copy()


@dataclass(frozen=True)
class LambOseen:
    """Lamb-Oseen vortex: v_θ(r) = Γ/(2π r) (1 - exp(-r²/r_c²)) about an axis.

    Attributes
    ----------
    circulation : float
        Γ, m²/s.
    core_radius : float
        r_c, metres.
    centre : (3,) metres
        A point on the vortex axis.
    axis : (3,)
        Axis direction (normalised here); e.g. (0, 1, 0) puts the axis along Y so that the
        flow has a depth (Z) component.
    """

    circulation: float = 1e-3
    core_radius: float = 2e-3
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)

    def __post_init__(self):
        if not self.core_radius > 0:
            raise ConfigError(f"core_radius = {self.core_radius!r} m: expected > 0")
        _unit(self.axis, "axis")

    def __call__(self, points, t: float = 0.0):
        """Velocity (N, 3), m/s, at volume points (N, 3), metres."""
        a = _unit(self.axis, "axis")
        r_vec = np.asarray(points, dtype=float) - np.asarray(self.centre, dtype=float)
        r_perp = r_vec - np.outer(r_vec @ a, a)
        r2 = np.einsum("ij,ij->i", r_perp, r_perp)
        # v = Γ/(2π r²)(1 - e^{-r²/rc²}) (a × r_perp); the factor tends to Γ/(2π rc²) at r = 0
        with np.errstate(invalid="ignore", divide="ignore"):
            factor = np.where(r2 > 0, -np.expm1(-r2 / self.core_radius ** 2) / r2,
                              1.0 / self.core_radius ** 2)
        factor *= self.circulation / (2 * math.pi)
        return factor[:, None] * np.cross(a, r_perp)


@dataclass(frozen=True)
class HillVortex:
    """Hill's spherical vortex of radius a (Stokes stream functions, inviscid).

    In the frame of the vortex (``frame="vortex"``) the outer fluid streams past at -U along
    the axis; in the lab frame (``frame="lab"``) the fluid far away is at rest and the vortex
    travels at +U along the axis, its centre at ``centre + U t axis``.

    Notes
    -----
    With ρ the distance from the axis, z along it and r² = ρ² + z² (vortex frame):
    inside, u_z = (3U/2)(1 - (2ρ² + z²)/a²), u_ρ = (3U/2) ρ z/a²;
    outside, u_z = -U(1 - a³/r³) - (3U/2) ρ² a³/r⁵, u_ρ = (3U/2) ρ z a³/r⁵.
    Both are continuous on the sphere r = a.
    """

    radius: float = 3e-3
    speed: float = 0.1
    centre: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    frame: str = "vortex"

    def __post_init__(self):
        if not self.radius > 0:
            raise ConfigError(f"radius = {self.radius!r} m: expected > 0")
        if self.frame not in ("vortex", "lab"):
            raise ConfigError(f"frame = {self.frame!r}: expected 'vortex' or 'lab'")
        _unit(self.axis, "axis")

    def __call__(self, points, t: float = 0.0):
        """Velocity (N, 3), m/s, at volume points (N, 3), metres, at time t (s)."""
        ax = _unit(self.axis, "axis")
        u, a = self.speed, self.radius
        centre = np.asarray(self.centre, dtype=float)
        if self.frame == "lab":
            centre = centre + u * t * ax
        r_vec = np.asarray(points, dtype=float) - centre
        z = r_vec @ ax
        rho_vec = r_vec - np.outer(z, ax)
        rho2 = np.einsum("ij,ij->i", rho_vec, rho_vec)
        r2 = rho2 + z * z
        inside = r2 < a * a
        r = np.sqrt(r2)
        with np.errstate(invalid="ignore", divide="ignore"):
            a3r3 = np.where(inside, 0.0, a ** 3 / np.where(r > 0, r, 1.0) ** 3)
            uz = np.where(inside, 1.5 * u * (1 - (2 * rho2 + z * z) / a ** 2),
                          -u * (1 - a3r3) - 1.5 * u * rho2 * a3r3 / np.where(r2 > 0, r2, 1.0))
            # u_ρ ρ̂ = (3U/2) z (ρ_vec) / a² inside, (3U/2) z ρ_vec a³/r⁵ outside
            k = np.where(inside, 1.5 * u * z / a ** 2,
                         1.5 * u * z * a3r3 / np.where(r2 > 0, r2, 1.0))
        vel = uz[:, None] * ax[None, :] + k[:, None] * rho_vec
        if self.frame == "lab":
            vel = vel + u * ax
        return vel


FLOWS = {"uniform": Uniform, "oseen": LambOseen, "hill": HillVortex}


def advect(flow, points, dt: float, *, steps: int = 8, t0: float = 0.0) -> np.ndarray:
    """Positions after ``dt`` seconds, by classical Runge-Kutta (RK4) in ``steps`` sub-steps.

    Parameters
    ----------
    flow : callable
        ``flow(points (N, 3) m, t s) -> velocity (N, 3) m/s``.
    points : array_like, shape (N, 3)
        Start positions, metres.
    dt : float
        Time interval, seconds.
    """
    p = np.array(points, dtype=float)
    h = dt / steps
    t = t0
    for _ in range(steps):
        k1 = flow(p, t)
        k2 = flow(p + 0.5 * h * k1, t + 0.5 * h)
        k3 = flow(p + 0.5 * h * k2, t + 0.5 * h)
        k4 = flow(p + h * k3, t + h)
        p = p + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        t += h
    return p
