"""One image -> one volume; one image pair -> one vector field (orchestration, no physics).

::

    image --(weights from the calibration's S_i,eff)--> MART volume --> particles
          --> depth corrections (external n1/n2, internal n3/n4) --> products

The stages are the library's stage functions; this module chooses defaults, keeps the weights
(built once per geometry, cached on disk), reports progress and writes products atomically.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.config import ParticleSettings, ReconstructionSettings
from plenopiv.corrections import DepthCorrection
from plenopiv.errors import ReconstructionError
from plenopiv.io import check_image, write_h5
from plenopiv.mart import mlos, reconstruct
from plenopiv.particles import find_particles
from plenopiv.projector import SparseProjector
from plenopiv.volume import VolumeGrid
from plenopiv.weights import Weights, cached_weights

Progress = Callable[[str, float], None] | None


@dataclass(frozen=True)
class VolumeResult:
    """A reconstructed volume and its particles.

    Attributes
    ----------
    volume : (nz, ny, nx) float32
        Reconstructed intensity on ``grid`` (effective coordinates).
    grid : VolumeGrid
        Effective (air-equivalent) grid of the reconstruction.
    correction : DepthCorrection
        From effective to physical depth.
    particle_position_effective : (N, 3)
        Particle (x, y, z) in effective coordinates, metres.
    particle_position : (N, 3)
        The same after the depth corrections, metres.
    particle_intensity, particle_size : (N,), (N, 3)
        Integrated intensity; blob σ along (x, y, z) in metres (effective).
    """

    volume: np.ndarray
    grid: VolumeGrid
    correction: DepthCorrection
    particle_position_effective: np.ndarray
    particle_position: np.ndarray
    particle_intensity: np.ndarray
    particle_size: np.ndarray
    timings: dict = field(default_factory=dict)

    @property
    def z_corrected(self) -> np.ndarray:
        """Physical depth of each voxel layer, metres."""
        return self.correction.depth(self.grid.z)

    def save(self, path: str | Path, *, config: dict | None = None, extra_attrs=None) -> Path:
        """Write the volume product (DESIGN.md §7), atomically."""
        ds = {"/volume": self.volume.astype(np.float32), "/x": self.grid.x, "/y": self.grid.y,
              "/z": self.z_corrected, "/z_effective": self.grid.z,
              "/particles/position_m": self.particle_position,
              "/particles/position_effective_m": self.particle_position_effective,
              "/particles/intensity": self.particle_intensity,
              "/particles/size_m": self.particle_size}
        units = {k: "m" for k in ("/x", "/y", "/z", "/z_effective", "/particles/position_m",
                                  "/particles/position_effective_m", "/particles/size_m")}
        attrs = {"n_particles": len(self.particle_position), "voxel_m": np.array(self.grid.voxel),
                 "depth_correction_scale": self.correction.scale,
                 "depth_correction_external": self.correction.external,
                 "depth_correction_internal": self.correction.internal,
                 "volume_axes": "z, y, x", **(extra_attrs or {})}
        return write_h5(path, ds, attrs=attrs, units=units, config=config, kind="volume")


def normalised_rows(weights: Weights) -> tuple[SparseProjector, np.ndarray]:
    """W with every row scaled to a maximum of 1, and the scale of each row.

    MART raises a voxel's factor to the power μ w_ij; with the physical weights (fractions of
    a particle's light, ~1e-3) the updates would be tiny. Scaling row i and pixel i by the same
    c_i = 1/max_j w_ij leaves the system I = W E and its solution E unchanged.
    """
    p = weights.projector
    counts = np.diff(p.indptr)
    row_max = np.zeros(len(counts), np.float32)
    nz = counts > 0
    row_max[nz] = np.maximum.reduceat(p.data, p.indptr[:-1][nz])
    safe = np.where(row_max > 0, row_max, 1.0).astype(np.float32)
    data = p.data / np.repeat(safe, counts)
    return SparseProjector(p.indptr, p.indices, data.astype(np.float32),
                           n_voxels=p.n_voxels, check=False), safe


def reconstruct_volume(calibration: Calibration, image, grid: VolumeGrid, *,
                       settings: ReconstructionSettings = ReconstructionSettings(),
                       particles: ParticleSettings = ParticleSettings(),
                       weights: Weights | None = None, cache_dir: str | Path | None = None,
                       progress: Progress = None) -> VolumeResult:
    """Reconstruct one image into a volume and extract its particles.

    Parameters
    ----------
    calibration : Calibration
    image : ndarray
        Raw plenoptic image of the calibration's sensor shape.
    grid : VolumeGrid
        Effective (air-equivalent) reconstruction grid.
    weights : Weights, optional
        Pre-built weights for this calibration and grid (e.g. shared by a pair).
    cache_dir : path, optional
        Weight cache folder (used when ``weights`` is not given).
    progress : callable, optional
        ``progress(stage, fraction)`` for long stages.
    """
    t = {}
    t0 = time.perf_counter()
    img = check_image(image, shape=calibration.camera.sensor.shape, name="particle image")
    if weights is None:
        weights, _ = cached_weights(calibration, grid, cache_dir=cache_dir,
                                    f_number=settings.f_number, min_lit=settings.min_lit)
    elif weights.grid != grid:
        raise ReconstructionError("the given weights were built for another volume grid")
    t["weights_s"] = time.perf_counter() - t0
    proj, row_scale = normalised_rows(weights)
    raw = weights.image_vector(img)
    threshold = settings.pixel_threshold * float(img.max())
    bright = raw > threshold
    if not bright.any():
        raise ReconstructionError(f"no pixel seen by the volume is above the threshold "
                                  f"{threshold:g} ([reconstruction] pixel_threshold = "
                                  f"{settings.pixel_threshold}): is the volume in view?")
    values = (raw / row_scale).astype(np.float32)

    def report(iteration, _volume):
        if progress is not None:
            progress("mart", iteration / max(settings.iterations, 1))

    t1 = time.perf_counter()
    # Soft line-of-sight mask: a voxel is empty when most of the light that would reach the
    # sensor from it falls on dark pixels. (A hard "any dark pixel" rule would delete the
    # voxel holding a point particle: the voxel is wider than the particle, so some beams
    # through the voxel miss the particle and stay dark.)
    seen = np.asarray(proj.column_sums())
    dark_weight = np.asarray(proj.back((~bright).astype(np.float32)))
    with np.errstate(invalid="ignore", divide="ignore"):
        keep = (seen > 0) & (dark_weight <= settings.dark_tolerance * seen)
    lit = _rows(proj, bright)
    first = mlos(values[bright], lit) * keep
    blocks = None
    if settings.method == "block":
        blocks = _perspective_blocks(weights, calibration)[bright]
    vol = reconstruct(values[bright], lit, method=settings.method,
                      iterations=settings.iterations, relaxation=settings.relaxation,
                      pixel_threshold=0.0, blocks=blocks, initial=first, shape=grid.shape,
                      callback=report)
    t["mart_s"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    vmax = float(vol.max())
    if vmax <= 0:
        raise ReconstructionError("the reconstructed volume is empty: no particle light in "
                                  "the volume (check [volume] and the image)")
    found = find_particles(vol, threshold=particles.threshold * vmax, method=particles.method,
                           min_separation_vox=particles.min_separation_vox,
                           box_vox=particles.box_vox, fit_spacing_vox=particles.fit_spacing_vox)
    eff = found.position_world(grid.origin, grid.voxel)
    corr = DepthCorrection.for_camera(calibration.camera, internal=particles.internal_correction)
    t["particles_s"] = time.perf_counter() - t2
    return VolumeResult(vol, grid, corr, eff, corr.points(eff) if len(eff) else eff,
                        found.intensity, found.size_world(grid.voxel), t)


def _rows(proj: SparseProjector, rows: np.ndarray) -> SparseProjector:
    """The projector restricted to the selected rows (a boolean mask)."""
    counts = np.diff(proj.indptr)[rows]
    indptr = np.zeros(len(counts) + 1, np.int64)
    np.cumsum(counts, out=indptr[1:])
    take = np.repeat(rows, np.diff(proj.indptr))
    return SparseProjector(indptr, proj.indices[take], proj.data[take], n_voxels=proj.n_voxels,
                           check=False)


def _perspective_blocks(weights: Weights, calibration: Calibration) -> np.ndarray:
    """Block label of each weight row: its perspective view (aperture cell), so that a block
    holds one pixel per lenslet and its pixels share few voxels."""
    from plenopiv.lightfield import light_field

    lf = light_field(calibration)
    pos = {int(p): i for i, p in enumerate(lf.pixel)}
    cell = np.array([np.rint(lf.u[pos[int(p)]] / lf.cell) for p in weights.pixel])
    _, labels = np.unique(cell, axis=0, return_inverse=True)
    return labels.ravel().astype(np.int64)


def reconstruction_quality(volume, volume_true) -> float:
    """Q = Σ E E* / sqrt(Σ E² Σ E*²) (DESIGN.md §5)."""
    from plenopiv.mart import reconstruction_quality as q

    return q(volume, volume_true)


def gaussian_truth_volume(grid: VolumeGrid, positions, intensities=None, *,
                          sigma_vox=(1.0, 1.0, 1.0)) -> np.ndarray:
    """The true volume for Q: a Gaussian blob (σ in voxels, z y x) per particle, float32.

    ``positions`` are (x, y, z) in the grid's (effective) coordinates, metres.
    """
    from plenopiv.conventions import world_to_voxel

    vol = np.zeros(grid.shape, np.float32)
    p = world_to_voxel(np.asarray(positions, float), grid.origin, grid.voxel)
    w = np.ones(len(p)) if intensities is None else np.asarray(intensities, float)
    s = np.asarray(sigma_vox, float)
    r = np.ceil(3 * s).astype(int)
    for (cz, cy, cx), wi in zip(p, w, strict=True):
        lo = np.maximum(np.floor([cz, cy, cx]).astype(int) - r, 0)
        hi = np.minimum(np.floor([cz, cy, cx]).astype(int) + r + 2, grid.shape)
        if np.any(hi <= lo):
            continue
        zz, yy, xx = np.meshgrid(*(np.arange(a, b) for a, b in zip(lo, hi, strict=True)),
                                 indexing="ij")
        g = np.exp(-0.5 * (((zz - cz) / s[0]) ** 2 + ((yy - cy) / s[1]) ** 2
                           + ((xx - cx) / s[2]) ** 2))
        vol[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] += (wi * g).astype(np.float32)
    return vol
