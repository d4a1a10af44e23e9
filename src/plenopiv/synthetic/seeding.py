"""Random particle seeding and synthetic image pairs with ground truth."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from plenopiv.camera.model import CameraModel
from plenopiv.errors import ConfigError
from plenopiv.synthetic.flows import advect
from plenopiv.synthetic.images import field_of_view, particle_image
from plenopiv.synthetic.sensor import CameraInstance, particle_brightness
from plenopiv.synthetic.tracer import Progress


@dataclass(frozen=True)
class SeedingBox:
    """An axis-aligned box of the volume, metres: ``x = (lo, hi)``, ``y``, ``z`` (Z depth)."""

    x: tuple[float, float]
    y: tuple[float, float]
    z: tuple[float, float]

    def __post_init__(self):
        for name in ("x", "y", "z"):
            lo, hi = getattr(self, name)
            if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
                raise ConfigError(f"seeding box {name} = ({lo!r}, {hi!r}) m: expected lo < hi")

    @property
    def volume(self) -> float:
        """Box volume, m³."""
        return (self.x[1] - self.x[0]) * (self.y[1] - self.y[0]) * (self.z[1] - self.z[0])

    @classmethod
    def field_of_view(cls, camera: CameraModel, depth: tuple[float, float],
                      fill: float = 1.0) -> SeedingBox:
        """The box seen by the whole lenslet array at the focal plane, ``fill`` of it laterally."""
        hx, hy = field_of_view(camera, 0.0)
        return cls((-fill * hx, fill * hx), (-fill * hy, fill * hy), tuple(depth))


def particle_count(camera: CameraModel, box: SeedingBox, *, per_lenslet: float | None = None,
                   per_mm3: float | None = None) -> int:
    """Number of particles for a seeding density given per lenslet or per mm³ (exactly one)."""
    if (per_lenslet is None) == (per_mm3 is None):
        raise ConfigError("give exactly one seeding density: per_lenslet or per_mm3")
    if per_lenslet is not None:
        if not per_lenslet > 0:
            raise ConfigError(f"particles per lenslet = {per_lenslet!r}: expected > 0")
        return int(round(per_lenslet * camera.microlens_array.count))
    if not per_mm3 > 0:
        raise ConfigError(f"particles per mm³ = {per_mm3!r}: expected > 0")
    return int(round(per_mm3 * box.volume * 1e9))


def random_particles(box: SeedingBox, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` particle positions (N, 3) ``(X, Y, Z)``, metres, uniform in ``box``."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise ConfigError(f"particle count = {n!r}: expected an integer >= 0")
    lo = np.array([box.x[0], box.y[0], box.z[0]])
    hi = np.array([box.x[1], box.y[1], box.z[1]])
    return lo + (hi - lo) * rng.random((int(n), 3))


@dataclass(frozen=True)
class SyntheticPair:
    """Two particle images and their ground truth.

    Attributes
    ----------
    image_a, image_b : ndarray
        Irradiance images (float64, sensor shape).
    positions_a, positions_b : ndarray, shape (N, 3)
        True particle positions (X, Y, Z) in metres at the two exposures.
    dt : float
        Time between the exposures, seconds.
    """

    image_a: np.ndarray
    image_b: np.ndarray
    positions_a: np.ndarray
    positions_b: np.ndarray
    intensities: np.ndarray
    dt: float
    meta: dict = field(default_factory=dict)

    @property
    def displacement(self) -> np.ndarray:
        """True displacement of each particle (N, 3), metres."""
        return self.positions_b - self.positions_a


def simulate_pair(camera: CameraModel, flow, *, dt: float, box: SeedingBox, n_particles: int,
                  rng: np.random.Generator, rays_per_particle: int = 2048,
                  f_number: float | None = None, intensity_spread: float = 0.0,
                  progress: Progress = None,
                  instance: CameraInstance | None = None) -> SyntheticPair:
    """Seed ``box``, move the particles with ``flow`` over ``dt`` and render both exposures.

    ``intensity_spread`` is the standard deviation of the logarithm of particle brightness
    (log-normal, median 1); 0 makes every particle equally bright. ``instance``: a real
    camera and its light (:mod:`plenopiv.synthetic.sensor`): the brightness spread of its
    settings (when ``intensity_spread`` is 0), its depth profile and glow, the second
    exposure lit by ``pulse_ratio`` times the first's energy, its lenslets' throughputs and
    vignetting.
    """
    if not (np.isfinite(dt) and dt > 0):
        raise ConfigError(f"dt = {dt!r} s: expected a finite time > 0")
    pa = random_particles(box, n_particles, rng)
    pb = advect(flow, pa, dt)
    w = None
    if intensity_spread > 0:
        w = rng.lognormal(0.0, intensity_spread, len(pa))
    elif instance is not None:
        w = particle_brightness(len(pa), instance.settings, rng)
    if w is None:
        w = np.ones(len(pa))
    seed = int(rng.integers(2 ** 31))
    pulse = 1.0 if instance is None else instance.settings.pulse_ratio
    ia = particle_image(camera, pa, w, rays_per_particle=rays_per_particle, f_number=f_number,
                        seed=seed, progress=progress, instance=instance)
    ib = particle_image(camera, pb, w, rays_per_particle=rays_per_particle, f_number=f_number,
                        seed=seed + 1, progress=progress, instance=instance,
                        pulse_energy=pulse)
    return SyntheticPair(ia, ib, pa, pb, w, dt)
