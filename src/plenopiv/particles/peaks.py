"""3-D particle extraction from a reconstructed volume: peaks, sub-voxel centroids, sizes.

:func:`find_particles` finds the local maxima above a threshold, keeps the brightest of any
that lie closer than a minimum separation, and refines each to sub-voxel precision by the
3-point Gaussian per axis (the default) or the intensity-weighted centroid. The result,
:class:`Particles`, holds positions as fractional voxel indices ``(z, y, x)`` and converts them
to world ``(x, y, z)`` metres through :func:`plenopiv.conventions.voxel_to_world`.

See docs/methods.md#peaks for the estimators, their bias and the reference.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from plenopiv.conventions import voxel_to_world
from plenopiv.errors import ReconstructionError
from plenopiv.particles import _kernels as _k
from plenopiv.particles.settings import ParticleSettings

__all__ = ["CENTROID_METHODS", "DEFAULT_FIT_SPACING_VOX", "DEFAULT_METHOD", "Particles",
           "find_particles"]

#: Valid values of ``find_particles(method=...)``.
CENTROID_METHODS = ("gaussian", "centroid")
#: Default sub-voxel estimator: that of ``[particles] method``
#: (:class:`plenopiv.particles.settings.ParticleSettings`, the one set of defaults).
DEFAULT_METHOD = ParticleSettings().method
#: Default sample spacing ``(z, y, x)`` of the Gaussian fit, voxels: that of
#: ``[particles] fit_spacing_vox``.
DEFAULT_FIT_SPACING_VOX = ParticleSettings().fit_spacing_vox


@dataclass(frozen=True, eq=False)
class Particles:
    """Particles found in a volume (N of them), brightest first.

    Attributes
    ----------
    position_vox : ndarray of float64, shape (N, 3)
        Sub-voxel positions as fractional voxel indices ``(z, y, x)``; voxel centres sit at
        integers.
    intensity : ndarray of float64, shape (N,)
        Integrated intensity: the sum of the volume over the refinement box (volume units
        times voxels).
    size_vox : ndarray of float64, shape (N, 3)
        Standard deviation sigma of the blob along ``(z, y, x)``, voxels (see
        :func:`find_particles` for how each method measures it); ``size_vox[:, 0]`` over the
        lateral sizes is the depth elongation.
    peak : ndarray of float64, shape (N,)
        Value of the peak voxel (volume units).
    method : str
        The sub-voxel method used, one of :data:`CENTROID_METHODS`.
    """

    position_vox: np.ndarray
    intensity: np.ndarray
    size_vox: np.ndarray
    peak: np.ndarray
    method: str

    def __len__(self) -> int:
        """Return the number of particles."""
        return int(self.position_vox.shape[0])

    @property
    def elongation(self) -> np.ndarray:
        """Depth elongation ``sigma_z / sqrt(sigma_y * sigma_x)`` per particle (dimensionless)."""
        return self.size_vox[:, 0] / np.sqrt(self.size_vox[:, 1] * self.size_vox[:, 2])

    def position_world(self, origin, voxel_size) -> np.ndarray:
        """Particle positions in world coordinates.

        Parameters
        ----------
        origin : array_like, shape (3,)
            ``(x, y, z)`` of the centre of voxel ``[0, 0, 0]``, metres.
        voxel_size : float or array_like, shape (3,)
            Voxel edge ``(dx, dy, dz)``, metres.

        Returns
        -------
        ndarray, shape (N, 3)
            ``(x, y, z)`` in metres, via :func:`plenopiv.conventions.voxel_to_world`.
        """
        return voxel_to_world(self.position_vox, origin, voxel_size)

    def size_world(self, voxel_size) -> np.ndarray:
        """Blob sigma along ``(x, y, z)`` in metres (``voxel_size`` as ``(dx, dy, dz)``, m)."""
        return self.size_vox[:, ::-1] * np.asarray(voxel_size, dtype=float)


def find_particles(
    volume,
    *,
    threshold: float,
    min_separation_vox,
    box_vox,
    method: str = DEFAULT_METHOD,
    fit_spacing_vox=DEFAULT_FIT_SPACING_VOX,
    exclude_border: bool = True,
) -> Particles:
    r"""Find particles in a volume: local maxima above a threshold, refined to sub-voxel.

    Parameters
    ----------
    volume : array_like, shape (nz, ny, nx)
        Reconstructed intensities, indexed ``[z, y, x]``, finite.
    threshold : float
        A peak must be strictly brighter than this (volume units, >= 0).
    min_separation_vox : float or sequence of 3 floats
        Peaks closer than this, as an ellipsoid with these semi-axes ``(z, y, x)`` in voxels
        (``sum_a (d_a / s_a)**2 < 1``), are merged into the brightest one. Use a larger z
        value for depth-elongated blobs. Must be > 0. No default: it follows from the
        camera's resolution cell and the voxel size
        (:func:`plenopiv.workflow.volume.particle_options`, ``[particles] min_separation_vox``).
    box_vox : int or sequence of 3 ints
        Half-widths ``(z, y, x)`` of the box around the peak, voxels (>= 1): the window of the
        centroid and of the integrated intensity. For depth-elongated blobs give z about
        2 sigma_z (e.g. ``(6, 2, 2)`` for sigma_z = 3), or the box cuts the blob. No default,
        for the same reason (``[particles] box_vox``).
    method : {"gaussian", "centroid"}
        Sub-voxel estimator: ``"gaussian"`` (default, :data:`DEFAULT_METHOD`), the 3-point
        Gaussian fit per axis through the peak voxel and its two samples ``fit_spacing_vox``
        away (exact for a sampled Gaussian blob, see Notes); ``"centroid"``, the
        intensity-weighted centroid over the box.
    fit_spacing_vox : int or sequence of 3 ints
        Spacing m ``(z, y, x)``, voxels (>= 1), of the samples the Gaussian fit uses on each
        side of the peak. 1 is the classical 3-point fit; on a blob of width s the noise of
        the fitted offset falls like ``s**2 / m``, so for depth-elongated blobs a z spacing
        near sigma_z (e.g. ``(3, 1, 1)``) is much less noisy (see Notes). Default
        :data:`DEFAULT_FIT_SPACING_VOX`.
    exclude_border : bool
        Drop peaks on the outermost voxel layer (their blob is cut by the volume's edge).
        If False they are kept; the Gaussian fit then gives offset 0 and size NaN along the
        axis on which the peak touches the edge.

    Returns
    -------
    Particles
        Brightest first.

    Raises
    ------
    ReconstructionError
        The volume is not 3-D or holds NaN/inf.
    ValueError
        An option is out of its valid range or set.

    Notes
    -----
    Peaks are voxels equal to the maximum of their 3x3x3 neighbourhood and above
    ``threshold``; ties and close pairs are resolved by greedy non-maximum suppression in
    order of decreasing peak value. The two sub-voxel estimators, their exactness and
    their bias are derived in :mod:`plenopiv.particles.peaks` (*Sub-voxel estimators*).
    """
    if method not in CENTROID_METHODS:
        raise ValueError(f"method must be one of {CENTROID_METHODS}; got {method!r}")
    vol = _checked_volume(volume)
    threshold = _checked_threshold(threshold)
    separation = _triple(min_separation_vox, "min_separation_vox", float)
    if np.any(separation <= 0):
        raise ValueError(f"min_separation_vox must be > 0; got {min_separation_vox!r}")
    half_box = _triple(box_vox, "box_vox", int)
    if np.any(half_box < 1):
        raise ValueError(f"box_vox half-widths must be integers >= 1; got {box_vox!r}")
    spacing = _triple(fit_spacing_vox, "fit_spacing_vox", int)
    if np.any(spacing < 1):
        raise ValueError(f"fit_spacing_vox must be integers >= 1; got {fit_spacing_vox!r}")

    peaks, values = _local_maxima(vol, threshold, exclude_border)
    keep = _k.suppress_close(peaks, np.array(vol.shape, np.int64), separation)
    peaks, values = np.ascontiguousarray(peaks[keep]), values[keep]
    n = peaks.shape[0]
    position = np.empty((n, 3), np.float64)
    size = np.empty((n, 3), np.float64)
    intensity = np.empty(n, np.float64)
    _k.refine_peaks(vol, peaks, half_box, spacing, method == "gaussian", position, size,
                    intensity)
    return Particles(position, intensity, size, values, method)


def _checked_volume(volume) -> np.ndarray:
    """The volume as a C-contiguous float32 (if it is float32) or float64 array, checked."""
    vol = np.asarray(volume)
    if vol.ndim != 3 or not np.issubdtype(vol.dtype, np.number):
        raise ReconstructionError(
            f"volume must be a 3-D numeric array indexed [z, y, x]; got shape {vol.shape}, "
            f"dtype {vol.dtype}"
        )
    vol = np.ascontiguousarray(vol, dtype=np.float32 if vol.dtype == np.float32 else np.float64)
    if not np.all(np.isfinite(vol)):
        raise ReconstructionError(
            f"volume has {int(np.count_nonzero(~np.isfinite(vol)))} NaN or infinite voxels"
        )
    return vol


def _checked_threshold(threshold) -> float:
    """The peak threshold as a finite float >= 0 (volume units)."""
    try:
        threshold = float(threshold)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"threshold must be a number (volume units); got {threshold!r}") from exc
    if not np.isfinite(threshold) or threshold < 0:
        raise ValueError(f"threshold must be finite and >= 0; got {threshold!r}")
    return threshold


def _local_maxima(vol, threshold, exclude_border):
    """Voxels ``(N, 3)`` equal to their 3x3x3 maximum and above ``threshold``, brightest first.

    Returns the peaks (int64 ``(z, y, x)`` indices) and their values (float64); ties stay in
    raster order.
    """
    local_max = scipy.ndimage.maximum_filter(vol, size=3, mode="constant", cval=-np.inf)
    candidate = (vol == local_max) & (vol > threshold)
    if exclude_border:
        candidate[[0, -1], :, :] = False
        candidate[:, [0, -1], :] = False
        candidate[:, :, [0, -1]] = False
    peaks = np.argwhere(candidate).astype(np.int64)
    values = vol[candidate].astype(np.float64)
    order = np.argsort(-values, kind="stable")  # brightest first; ties in raster order
    return peaks[order], values[order]


def _triple(value, name: str, kind) -> np.ndarray:
    """Return a scalar or a 3-sequence as a (3,) array of ``kind`` (float64 or int64)."""
    a = np.asarray(value, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(3, float(a))
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a number or 3 numbers (z, y, x); got {value!r}")
    if kind is int:
        if np.any(a != np.round(a)):
            raise ValueError(f"{name} must be integers; got {value!r}")
        return a.astype(np.int64)
    return a
