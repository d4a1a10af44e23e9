"""One image -> one volume and its particles.

Reconstruction, particle finding, light-field positions and depth corrections.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.calibration.recording import check_recording
from plenopiv.camera.corrections import DepthCorrection
from plenopiv.camera.grid import VolumeGrid
from plenopiv.camera.resolution import footprint, resolution_cell
from plenopiv.errors import ReconstructionError
from plenopiv.particles.bundle import PARTICLE_BUNDLE, bundle_positions, lit_rays, ray_table
from plenopiv.particles.peaks import find_particles
from plenopiv.particles.settings import ParticleSettings
from plenopiv.particles.split import SplitParticles, split_bright
from plenopiv.particles.threshold import peak_threshold
from plenopiv.products.images import check_image
from plenopiv.products.volume import VolumeResult
from plenopiv.reconstruction.build import weights_for
from plenopiv.reconstruction.geometry import ProjectionGeometry
from plenopiv.reconstruction.settings import ReconstructionSettings
from plenopiv.reconstruction.solve import solve_volume
from plenopiv.reconstruction.subdivision import to_volume_grid, working_factors
from plenopiv.reconstruction.weights import Weights

Progress = Callable[[str, float], None] | None


_DEFAULT_RECONSTRUCTION = ReconstructionSettings()


_DEFAULT_PARTICLES = ParticleSettings()


def particle_options(particles: ParticleSettings, grid: VolumeGrid, calibration: Calibration,
                     volume, *, f_number: float | None = None) -> dict:
    """Keywords of :func:`~plenopiv.particles.peaks.find_particles` for ``particles`` and a volume.

    The threshold is ``particles.threshold`` times the reference intensity (the 99.9th
    percentile of the positive voxels, or the maximum), and at least ``particles.noise_sigmas``
    noise deviations above the volume's background
    (:func:`~plenopiv.particles.threshold.peak_threshold`). Unset separation and box follow the
    resolution cell (:func:`resolution_cell`) in voxels of ``grid``: peaks closer than one
    cell (1.5 cells laterally, so that diagonal neighbours merge) are one particle; the
    centroid box is ±1 cell.
    """
    threshold = peak_threshold(volume, fraction=particles.threshold,
                               reference=particles.threshold_reference,
                               noise_sigmas=particles.noise_sigmas)
    lat, dep = resolution_cell(calibration.effective_camera, f_number)
    vx, vy, vz = (float(a) for a in grid.voxel)
    sep = particles.min_separation_vox
    if sep is None:
        sep = (max(dep / vz, 1.0), max(1.5 * lat / vy, 1.0), max(1.5 * lat / vx, 1.0))
    box = particles.box_vox
    if box is None:
        box = tuple(max(1, int(round(c / d))) for c, d in ((dep, vz), (lat, vy), (lat, vx)))
    return {"threshold": threshold, "method": particles.method,
            "min_separation_vox": tuple(sep), "box_vox": tuple(box),
            "fit_spacing_vox": particles.fit_spacing_vox}


def reconstruct_volume(calibration: Calibration, image, grid: VolumeGrid, *,
                       settings: ReconstructionSettings = _DEFAULT_RECONSTRUCTION,
                       particles: ParticleSettings = _DEFAULT_PARTICLES,
                       weights: Weights | None = None, cache_dir: str | Path | None = None,
                       progress: Progress = None, image_mask=None,
                       checked: bool = False, solver: str | None = None,
                       solver_options: dict | None = None) -> VolumeResult:
    """Reconstruct one image into a volume and extract its particles.

    Parameters
    ----------
    calibration : Calibration
    image : ndarray
        Raw plenoptic image of the calibration's sensor shape.
    grid : VolumeGrid
        Effective (air-equivalent) reconstruction grid.
    weights : Weights, optional
        Pre-built weights for this calibration (e.g. shared by a pair): from
        :func:`weights_for`, on the working grid; weights built for ``grid`` itself
        reconstruct on it without subdivision. Default: :func:`weights_for`.
    cache_dir : path, optional
        Weight cache folder (used when ``weights`` is not given).
    progress : callable, optional
        ``progress(stage, fraction)`` for long stages.
    image_mask : (rows, cols) bool array, optional
        Pixels to ignore (True): their rows of the system are dropped, so they count neither
        as light nor as dark (a reflection, a model in the view). The dark threshold is taken
        from the unmasked pixels. See :mod:`plenopiv.workflow.masks`.
    checked : bool
        The image was checked and preprocessed already
        (:class:`plenopiv.workflow.preprocess.ImagePreparation`: counts ≥ 0, the sensor's
        shape), so :func:`~plenopiv.products.images.check_image` is not run again (its
        warnings were given once, for the image as recorded).
    solver, solver_options : optional
        A least-squares solver instead of ``settings.method``
        (:func:`~plenopiv.reconstruction.solve.solve_volume`).

    Notes
    -----
    Without ``weights``, the image's micro-images are first checked against the
    calibration's (``settings.lattice_check``, :func:`check_lattice`); given weights were
    made for a calibration the caller has checked (:class:`~plenopiv.workflow.pair.
    PairProcessor` checks a pair's mean once).
    """
    from plenopiv.resources import check_grid, release_freed_memory

    t, t0 = {}, time.perf_counter()
    check_grid(grid)
    release_freed_memory()          # the holes earlier stages left add nothing to this peak
    if checked:
        img = np.asarray(image, dtype=np.float64)
        if img.shape != tuple(calibration.camera.sensor.shape):
            raise ReconstructionError(f"the prepared image has shape {img.shape}: expected the "
                                      f"sensor's {calibration.camera.sensor.shape}")
    else:
        img = check_image(image, shape=calibration.camera.sensor.shape,
                          name="particle image", particles=True)
    if weights is None:
        calibration = check_lattice(calibration, [img], settings)
        if progress is not None:
            progress("weights", 0.0)
        weights, _ = weights_for(calibration, grid, settings, cache_dir=cache_dir)
    geometry = weights.geometry
    if geometry is None:        # weights made without one: the rays of these settings
        geometry = ProjectionGeometry.for_settings(calibration, weights.grid, settings)
    on_grid = weights.grid == grid
    if not on_grid:
        working_factors(weights.grid, grid)      # refuses weights of another grid
    if weights.matrix_free and settings.method != "smart":
        raise ReconstructionError(
            f"[reconstruction] method = {settings.method!r} walks the rows of explicit weights; "
            "the matrix-free lattice projector supports method = \"smart\" only")
    t["weights_s"] = time.perf_counter() - t0

    def report(iteration, _volume):
        progress("mart", iteration / max(settings.iterations, 1))

    t1 = time.perf_counter()
    vol = solve_volume(weights, img, settings, image_mask=image_mask, geometry=geometry,
                       callback=None if progress is None else report,
                       footprint=footprint(calibration.effective_camera), solver=solver,
                       solver_options=solver_options)
    if not on_grid:            # the working voxels back onto the volume's grid
        vol = to_volume_grid(vol, weights.grid, grid, kernel=settings.subdivision_kernel)
    t["mart_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    if progress is not None:
        progress("particles", 0.0)
    corr, eff, pos, intensity, size, centroid = _particles_and_positions(
        vol, grid, calibration, particles, geometry.light_field, img, image_mask, progress)
    t["particles_s"] = time.perf_counter() - t2
    return VolumeResult(vol, grid, corr, eff, pos, intensity, size, t,
                        particle_centroid_effective=centroid)


def _particles_and_positions(vol, grid: VolumeGrid, calibration: Calibration,
                             particles: ParticleSettings, lf, img, image_mask,
                             progress) -> tuple:
    """``(correction, effective, positions, intensities, sizes, centroids or None)``.

    :func:`_particles_of`, then (``position = "light_field"``) the positions from the rays,
    merged peaks split (:func:`light_field_particles`).
    """
    corr, eff, pos, intensity, size = _particles_of(vol, grid, calibration, particles)
    if particles.position != "light_field" or not len(eff):
        return corr, eff, pos, intensity, size, None
    if progress is not None:
        progress("particles", 0.5)
    found = light_field_particles(lf, img, eff, intensity, calibration, image_mask=image_mask,
                                  volume=vol, grid=grid, split_brighter=particles.split_brighter)
    # the halves of a split particle keep the centroid of the peak they came from
    eff, centroid = found.position, eff[found.source]
    intensity = np.where(found.split, 0.5, 1.0) * np.asarray(intensity)[found.source]
    return (corr, eff, corr.points(eff), intensity, np.asarray(size)[found.source], centroid)


def check_lattice(calibration: Calibration, images, settings: ReconstructionSettings
                  ) -> Calibration:
    """The calibration to reconstruct ``images`` with, after checking their micro-images.

    ``settings.lattice_check``: "refuse" raises
    :class:`~plenopiv.errors.CalibrationError` when their mean's micro-images lie more than
    ``settings.lattice_tolerance_px`` from the calibration's; "correct" returns the
    calibration moved onto them (with a warning); "off" returns it unchecked
    (:func:`plenopiv.calibration.recording.check_recording`). A recording with too little
    light to measure is not refused.
    """
    if settings.lattice_check == "off":
        return calibration
    return check_recording(calibration, images, tolerance_px=settings.lattice_tolerance_px,
                           correct=settings.lattice_check == "correct",
                           f_number=settings.f_number).calibration


def _particles_of(vol: np.ndarray, grid: VolumeGrid, calibration: Calibration,
                  particles: ParticleSettings) -> tuple:
    """``(correction, effective positions, positions, intensities, sizes)`` of the particles.

    Found by :func:`plenopiv.particles.peaks.find_particles`, then depth-corrected.
    """
    if float(vol.max()) <= 0:
        raise ReconstructionError("the reconstructed volume is empty: no particle light in "
                                  "the volume (check [volume] and the image)")
    found = find_particles(vol, **particle_options(particles, grid, calibration, vol))
    eff = found.position_world(grid.origin, grid.voxel)
    corr = DepthCorrection.for_camera(calibration.camera, internal=particles.internal_correction)
    return (corr, eff, corr.points(eff) if len(eff) else eff, found.intensity,
            found.size_world(grid.voxel))


def light_field_positions(lf, image, seeds, intensity, calibration: Calibration, *,
                          image_mask=None) -> np.ndarray:
    """Particle positions from the light field, seeded by the volume's (effective, metres).

    The point nearest the rays of the lit pixels that saw each particle
    (:func:`plenopiv.particles.bundle.bundle_positions` with
    :data:`~plenopiv.particles.bundle.PARTICLE_BUNDLE`, the volume intensities sharing the
    rays that pass several particles). The voxel grid quantises a reconstructed particle:
    an in-focus one fills its lenslet's footprint and its centroid moves with the voxel
    edges; the rays do not depend on the grid. Masked pixels carry no light. A particle
    with fewer than ``min_rays`` rays keeps its seed.
    """
    return light_field_particles(lf, image, seeds, intensity, calibration,
                                 image_mask=image_mask).position


def light_field_particles(lf, image, seeds, intensity, calibration: Calibration, *,
                          image_mask=None, split_brighter: float = 0.0, volume=None,
                          grid: VolumeGrid | None = None) -> SplitParticles:
    """:func:`light_field_positions`, with the peaks that hold two particles split.

    ``split_brighter`` (``[particles]``; 0: none) and the reconstructed ``volume`` on its
    ``grid`` go to :func:`plenopiv.particles.split.split_bright`.
    """
    lateral, cell = resolution_cell(calibration.effective_camera)
    img = np.asarray(image, np.float32)
    if image_mask is not None:
        img = np.where(np.asarray(image_mask, bool), np.float32(0), img)
    lit = lit_rays(lf, img, PARTICLE_BUNDLE.floor)       # the same fit, a fraction of the rays
    table = ray_table(lit)                               # one for every fit of this image
    seeds = np.asarray(seeds, float).reshape(-1, 3)
    fit = bundle_positions(lit, img, seeds, settings=PARTICLE_BUNDLE, depth_cell=cell,
                           brightness=intensity, table=table)
    single = np.where(fit.converged[:, None], fit.position, seeds)
    if not split_brighter or volume is None or len(single) < 2:
        return SplitParticles.unsplit(single)
    return split_bright(lit, img, seeds, single, intensity, fit.light, factor=split_brighter,
                        cell=(lateral, lateral, cell), volume=volume, grid=grid, table=table)

