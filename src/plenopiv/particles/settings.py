"""The particle finder's settings: the ``[particles]`` table of an experiment file."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from plenopiv.settings import settings

__all__ = ["ParticleSettings"]


@settings
class ParticleSettings:
    """``[particles]``: 3-D peak detection.

    threshold : a particle's peak must exceed this fraction of the reference intensity.
    noise_sigmas : and it must exceed the volume's background level by this many standard
        deviations of its noise, both estimated from the volume
        (:func:`plenopiv.particles.threshold.background_noise`); 0 turns it off. The default 5
        lets white Gaussian noise make at most 2.9e-7 false peaks per voxel (the share of its
        voxels above 5 sigma), three in a 10-million-voxel volume.
    threshold_reference : "bright" (default: the 99.9th percentile of the positive voxels,
        which a few hot voxels cannot move, while they can put the maximum many times above
        the particles' peaks) | "maximum" (the volume's maximum).
    method : sub-voxel estimator, "gaussian" (default: the 3-point Gaussian per axis with
        samples fit_spacing_vox apart; on reconstructed volumes its errors are below the
        centroid's on every axis, docs/validation/particle_noise.md) | "centroid"
        (intensity-weighted over box_vox; less noisy in depth where white noise is above
        about 0.03 of the peak and the blobs are 3 voxels deep or more).
    min_separation_vox, box_vox, fit_spacing_vox : ``[z, y, x]`` voxels (see
        :func:`plenopiv.particles.peaks.find_particles`). ``None`` (default): from the camera's
        resolution cell (:func:`plenopiv.workflow.volume.particle_options`): peaks within one cell
        are one particle, the centroid box is ±1 cell.
    internal_correction : "auto" | "none" | "plate" (see :mod:`plenopiv.camera.corrections`).
    position : "light_field" (default: each volume peak seeds the ray-bundle fit of
        :func:`plenopiv.particles.bundle.bundle_positions` with
        :data:`~plenopiv.particles.bundle.PARTICLE_BUNDLE`, the point nearest the rays of the
        lit pixels that saw the particle; it does not depend on the voxel grid, and the
        volume centroid is kept where fewer than ``min_rays`` rays are found) | "volume"
        (the ``method`` estimate on the voxels: an in-focus particle's centroid moves with the
        voxel edges, docs/validation/grid_independence.md).
    split_brighter : with ``position = "light_field"``, a peak whose rays carry at least this
        many times the median particle's light near its depth is fitted as two particles
        from the rays, and kept as two where they part by 0.5-2.0 resolution cells
        (:func:`plenopiv.particles.split.split_bright`): two particles within about a cell
        of each other make one peak in the volume. 0 turns it off; otherwise > 1
        (dimensionless; default 1.3, docs/methods.md#merged-particles).

    These are the only defaults: :func:`plenopiv.particles.peaks.find_particles` takes those of
    ``method`` and ``fit_spacing_vox`` from here, and has none for ``min_separation_vox``
    and ``box_vox``, which follow from the camera.
    """

    threshold: float = Field(0.1, ge=0, lt=1)
    noise_sigmas: float = Field(5.0, ge=0)
    threshold_reference: Literal["bright", "maximum"] = "bright"
    method: Literal["gaussian", "centroid"] = "gaussian"
    min_separation_vox: tuple[float, float, float] | None = None
    box_vox: tuple[int, int, int] | None = None
    fit_spacing_vox: tuple[int, int, int] = (2, 1, 1)
    internal_correction: Literal["auto", "none", "plate"] = "auto"
    position: Literal["light_field", "volume"] = "light_field"
    split_brighter: float = Field(1.3, ge=0)

    @field_validator("split_brighter")
    @classmethod
    def _off_or_above_one(cls, v):
        if 0 < v <= 1:
            raise ValueError("expected 0 (off) or a factor above 1: a peak whose rays carry "
                             "this many times the median particle's light is tried as two")
        return v
