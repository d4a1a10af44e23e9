"""The peak threshold of a volume: a fraction of its bright particles, and clear of its noise.

:func:`background_noise` estimates the level and the standard deviation of a volume's
background from the lower, particle-free part of its voxel distribution (a censored normal
fitted to two quantiles, so that it holds on volumes clipped at zero as on signed ones);
:func:`peak_threshold` accepts a peak only above both a fraction of the volume's bright voxels
and ``noise_sigmas`` such deviations above the background level.

See docs/methods.md#peaks for the estimator, the false-alarm rate that sets the default
``noise_sigmas`` and the measurements behind it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

__all__ = ["BAND_START", "BAND_WIDTH", "Background", "background_noise", "peak_threshold",
           "reference_intensity"]

#: Lowest cumulative probability of the band of voxels the noise is fitted on: one standard
#: deviation below the level, Phi(-1), where nothing holds the lower tail at a floor.
BAND_START = 0.5 * math.erfc(1.0 / math.sqrt(2.0))
#: Width of that band in cumulative probability (0.19: about half a standard deviation at
#: the level). Particle light adds to the voxels it covers, so the higher a quantile lies the
#: more particle voxels it counts; a narrow band low in the distribution counts the fewest.
BAND_WIDTH = 0.19
#: Share of voxels above a floor (the volume's minimum, which a clipped volume holds many
#: times) the band starts after: quantiles right at the floor's edge are the floor's ties.
FLOOR_MARGIN = 0.02


@dataclass(frozen=True)
class Background:
    """A volume's background: ``level`` and noise ``sigma`` (volume units), ``floor_share``.

    ``floor_share`` is the share of voxels at the volume's minimum (a floor such as MART's
    zeros, or one voxel in a volume with a continuous noise); ``sigma`` is 0 where the floor
    holds so many voxels that no band of noise is left above it.
    """

    level: float
    sigma: float
    floor_share: float


def background_noise(volume) -> Background:
    r"""The level and noise standard deviation of a volume's background.

    Parameters
    ----------
    volume : array_like
        Any shape (a reconstructed volume ``[z, y, x]``), finite, volume units.

    Returns
    -------
    Background

    Notes
    -----
    The background is modelled as a normal of mean b and deviation s, censored below at a
    floor that holds a share p0 of the voxels (MART's zeros, or noise clipped at zero); the
    particles only add light. Two quantiles q_a, q_b of the voxels at the cumulative
    probabilities p_a = max(Phi(-1), p0 + 0.02) and p_b = p_a + 0.19 give

        s = (q_b - q_a) / (Phi^-1(p_b) - Phi^-1(p_a)),    b = q_a - s Phi^-1(p_a).

    A signed noise is fitted from -1 to -0.4 deviations, below the level, where particle
    light is rare; a volume clipped at zero (p0 = 1/2) from +0.05 to +0.55. Median and MAD
    fail on the second (the MAD of a half-zero volume is 0), and a band higher up counts more
    of the particles' skirts. Those only add light, so what they do is raise the estimate
    (docs/validation/particle_noise.md). Where p_b > 0.99 no band is left and s = 0.
    """
    v = np.asarray(volume, dtype=np.float64).ravel()
    if v.size == 0:
        return Background(0.0, 0.0, 0.0)
    floor_share = float(np.count_nonzero(v <= v.min()) / v.size)
    p_a = max(BAND_START, floor_share + FLOOR_MARGIN)
    p_b = p_a + BAND_WIDTH
    if p_b > 0.99:
        return Background(float(np.median(v)), 0.0, floor_share)
    q_a, q_b = np.quantile(v, [p_a, p_b])
    z_a, z_b = float(ndtri(p_a)), float(ndtri(p_b))
    sigma = max(float(q_b - q_a) / (z_b - z_a), 0.0)
    return Background(float(q_a - sigma * z_a), sigma, floor_share)


def reference_intensity(volume, reference: str = "bright") -> float:
    """The intensity a relative threshold refers to (volume units).

    ``reference``: "bright", the 99.9th percentile of the positive voxels (a few hot voxels
    cannot move it), or "maximum", the volume's maximum. 0 for a volume without light.
    """
    v = np.asarray(volume)
    if reference == "maximum":
        return float(v.max()) if v.size else 0.0
    if reference != "bright":
        raise ValueError(f"reference must be 'bright' or 'maximum'; got {reference!r}")
    pos = v[v > 0]
    return float(np.percentile(pos, 99.9)) if pos.size else 0.0


def peak_threshold(volume, *, fraction: float, reference: str = "bright",
                   noise_sigmas: float = 0.0) -> float:
    """The value a peak of ``volume`` must exceed to be a particle (volume units).

    ``max(fraction * reference_intensity, level + noise_sigmas * sigma)`` with the
    :func:`background_noise` of the volume; ``noise_sigmas = 0`` leaves the relative
    threshold alone. ``fraction`` and ``noise_sigmas`` must be finite and >= 0.
    """
    for name, value in (("fraction", fraction), ("noise_sigmas", noise_sigmas)):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be finite and >= 0; got {value!r}")
    threshold = fraction * reference_intensity(volume, reference)
    if noise_sigmas > 0:
        bg = background_noise(volume)
        threshold = max(threshold, bg.level + noise_sigmas * bg.sigma)
    return float(threshold)
