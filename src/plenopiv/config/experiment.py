"""Experiment configuration (TOML, DESIGN.md §7): camera, volume and the processing options.

A minimal file holds just the camera and the volume::

    camera = "cameras/auburn_135mm.toml"     # relative to this file, or a preset name

    [volume]
    x_mm = [-5, 5]
    y_mm = [-4, 4]
    z_mm = [-6, 6]
    voxel_mm = 0.25                           # or shape = [nz, ny, nx]

Every other table is optional, every key has a default, a unit and a meaning (README). Unknown
keys are errors that name the key and list the valid ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, StrictInt, ValidationError, field_validator

from plenopiv.camera.grid import VolumeGrid, volume_from_dict
from plenopiv.camera.model import (
    CameraModel,
    camera_from_dict,
    format_validation_error,
    load_camera,
    read_toml,
)
from plenopiv.errors import ConfigError
from plenopiv.piv.response import RESPONSE_PARTICLES_PER_LENSLET
from plenopiv.piv.settings import (
    DEFORMATION_ORDERS,
    MIN_WINDOW_VOX,
    REPLACEMENT_METHODS,
    SUBPIXEL_METHODS,
    PIVSettings,
)

#: More MART sweeps than this is refused: 10 is the default, a few hundred already converge.
MAX_ITERATIONS = 10_000
#: The largest PIV window edge, voxels (a 1024³ float32 window pair is 8 GB).
MAX_WINDOW_VOX = 1024
#: Largest lateral subdivision of the reconstruction grid (``lateral_subdivision``).
MAX_SUBDIVISION = 4


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class ReconstructionSettings(_Strict):
    """``[reconstruction]``: MART options.

    method : "smart" (simultaneous multiplicative, default: independent of pixel order, so
        the two exposures of a pair reconstruct consistently) | "mart" (row action, Elsinga
        2006) | "block" (one block per perspective view).
    iterations : sweeps after the MLOS first guess (10; see docs/validation/field_quality.md).
    relaxation : μ, dimensionless; default by method: 2.0 for "smart", 0.03 for "mart" and
        "block" (in a plenoptic W every voxel is seen by ~200 pixels, so one row-action sweep
        at μ = 1 over-relaxes ~200-fold: Q 0.43 against 0.81 at μ = 0.03, 0.3 particles per
        lenslet).
    pixel_threshold : pixels at or below this fraction of the image's maximum are dark.
    dark_tolerance : a voxel is emptied before MART when, in every one of its lateral
        sub-cells (≤ half a footprint), more than this fraction of the weight falls on dark
        pixels (a soft line-of-sight mask, :mod:`plenopiv.reconstruction.sightline`; 0 is the hard
        rule).
    f_number : aperture of the recording (default: the camera's).
    min_lit : pixels whose aperture cell is less than this fraction inside the aperture are
        not used.
    projector : "auto" (explicit weights while they fit in max_weights_gb, else matrix-free)
        | "sparse" (explicit CSR weights, cached) | "lattice" (matrix-free, axis-aligned
        square lattices; method "smart" only). See :mod:`plenopiv.reconstruction.lattice`.
    max_weights_gb : memory allowed for the explicit weights, and for a matrix-free
        reconstruction, GB (default: 40 % of the machine's memory).
    lateral_subdivision : "auto" (default) | an int k >= 1. The reconstruction runs on voxels
        k times finer in x and y than the [volume] grid and is then summed back onto it.
        "auto" subdivides each lateral axis so that a working voxel is at most a third of a
        lenslet footprint (k = 3 for voxels of one footprint, 2 for half-footprint voxels, at
        most 4):
        the depth of a particle is told by beams shifting sideways by a fraction of a
        footprint, which voxels a footprint wide cannot represent, so with them a particle
        is reconstructed 10-20 voxels long and moves in depth by a third of its true
        displacement (docs/validation/vortex.md). Costs k² in weights and MART time.
    subdivision_kernel : how the working voxels return to the [volume] grid: "gaussian"
        (default): each voxel takes the working volume weighted by a Gaussian of σ = half a
        voxel about its centre, which keeps where a particle lies inside the voxel in the
        ratio of neighbouring voxels (anti-aliasing; against the peak locking of voxels as
        wide as a footprint) | "box": the sum of the voxel's own working voxels.
    """

    method: Literal["mart", "block", "smart"] = "smart"
    iterations: int = Field(10, ge=0, le=MAX_ITERATIONS)
    relaxation: float | None = Field(None, gt=0, allow_inf_nan=False)

    @property
    def relaxation_used(self) -> float:
        """μ: the given relaxation, or the method's default."""
        if self.relaxation is not None:
            return self.relaxation
        return 2.0 if self.method == "smart" else 0.03
    pixel_threshold: float = Field(0.003, ge=0, lt=1)
    dark_tolerance: float = Field(0.5, ge=0, le=1)
    f_number: float | None = Field(None, gt=0)
    min_lit: float = Field(0.5, gt=0, le=1)
    projector: Literal["auto", "sparse", "lattice"] = "auto"
    max_weights_gb: float | None = Field(None, gt=0, allow_inf_nan=False)
    lateral_subdivision: Literal["auto"] | StrictInt = Field("auto", union_mode="left_to_right")
    subdivision_kernel: Literal["gaussian", "box"] = "gaussian"

    @field_validator("lateral_subdivision")
    @classmethod
    def _subdivision(cls, v):
        if v != "auto" and not (isinstance(v, int) and not isinstance(v, bool)
                                and 1 <= v <= MAX_SUBDIVISION):
            raise ValueError(f"expected \"auto\" or an int from 1 to {MAX_SUBDIVISION}")
        return v


class ParticleSettings(_Strict):
    """``[particles]``: 3-D peak detection.

    threshold : a particle's peak must exceed this fraction of the reference intensity.
    threshold_reference : "bright" (default: the 99.9th percentile of the positive voxels,
        which a few hot voxels cannot move; at 16 MP the maximum was 21 times it and a
        threshold on the maximum found 1 % of the particles) | "maximum" (the volume's maximum).
    method : sub-voxel estimator, "centroid" (intensity-weighted over box_vox; the better one
        for the depth-elongated particles of plenoptic reconstructions) | "gaussian" (3-point
        per axis).
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
        voxel edges by up to 0.7 voxel, docs/validation/grid_independence.md).

    These are the only defaults: :func:`plenopiv.particles.peaks.find_particles` takes those of
    ``method`` and ``fit_spacing_vox`` from here, and has none for ``min_separation_vox``
    and ``box_vox``, which follow from the camera.
    """

    threshold: float = Field(0.1, ge=0, lt=1)
    threshold_reference: Literal["bright", "maximum"] = "bright"
    method: Literal["gaussian", "centroid"] = "centroid"
    min_separation_vox: tuple[float, float, float] | None = None
    box_vox: tuple[int, int, int] | None = None
    fit_spacing_vox: tuple[int, int, int] = (2, 1, 1)
    internal_correction: Literal["auto", "none", "plate"] = "auto"
    position: Literal["light_field", "volume"] = "light_field"


_PIV = PIVSettings()
"""The PIV defaults, which live in :class:`plenopiv.piv.PIVSettings` alone."""


class PIVConfig(_Strict):
    """``[piv]``: cross-correlation (windows in voxels ``[z, y, x]`` per pass).

    Every field of :class:`plenopiv.piv.PIVSettings` (which holds the defaults and the
    meaning of each) plus ``uncertainty``; :func:`plenopiv.workflow.pair.piv_settings` converts.

    deformation_order : interpolation of the window deformation, 1 (trilinear) to 5
        (B-spline; 3, cubic, is the default).
    median_epsilon_vox : noise level of the normalised median test, voxels (>= 0).
    median_iterations : detection rounds of the normalised median test (>= 1).
    smooth_predictor : low-pass the predictor of each pass with a [1, 2, 1]/4 filter.
    subpixel : sub-voxel peak estimator, "gaussian" (3-point Gaussian) | "parabolic".
    replacement : what becomes of the vectors rejected by the normalised median test (or
        with empty windows) after the last pass: "median" (default: the median of their
        3x3x3 neighbours), "mean" (their mean) or "none" (left NaN; ``valid`` is false).
    uncertainty : "response" (default: correlation statistics plus the chain's measured
        response to known displacements, once per experiment: two more reconstructions per
        test displacement) | "correlation" (correlation statistics only, faster,
        under-estimates the depth uncertainty near focus; see docs/validation/uncertainty.md).
    response_particles_per_lenslet : seeding of the ``"response"`` uncertainty's test pairs,
        particles per lenslet of the field of view (0.15, the validated density): set it to
        the experiment's nominal seeding. The response is measured once per experiment and
        shared by all its pairs, so it follows the experiment's settings, not a pair's count:
        the test pairs seed ``response_particles_per_lenslet`` × lenslets × (box area / field
        of view at the focal plane) particles through the whole box.
    response_displacements : test displacements of the ``"response"`` uncertainty, 3
        (default: 0.5, 1.25 and 1.75 lenslet footprints laterally with 0.1, 0.25 and 0.5
        depth resolution cells, plus 1.25 footprints along x alone and 0.5 depth cells
        alone, and three pairs moved as a sine of four vector spacings for the curvature
        term: sixteen reconstructions) or 1 (the middle one alone: two reconstructions, the
        gain probed at one fraction of the resolution cell, the motion along the axes not
        told apart, the curvature term unscaled).
    overlap_correction, broad_peaks : sub-voxel peak fit on the correlation divided by the
        windows' overlap fraction, and by a 5-point least-squares Gaussian along axes where
        the peak is broad, 7-point where it is wide (:class:`plenopiv.piv.PIVSettings`).
    """

    windows: list[tuple[int, int, int]] = Field(list(_PIV.windows), min_length=1)
    overlap: float = Field(_PIV.overlap, ge=0, lt=1)
    passes: int | None = Field(_PIV.passes, ge=1, le=100)
    deformation: bool = _PIV.deformation
    deformation_order: StrictInt = Field(_PIV.deformation_order, ge=min(DEFORMATION_ORDERS),
                                         le=max(DEFORMATION_ORDERS))
    median_threshold: float = Field(_PIV.median_threshold, gt=0)
    median_epsilon_vox: float = Field(_PIV.median_epsilon_vox, ge=0)
    median_iterations: int = Field(_PIV.median_iterations, ge=1)
    smooth_predictor: bool = _PIV.smooth_predictor
    subpixel: Literal[*SUBPIXEL_METHODS] = _PIV.subpixel
    replacement: Literal[*REPLACEMENT_METHODS] = _PIV.replacement
    uncertainty: Literal["response", "correlation"] = "response"
    response_displacements: Literal[1, 3] = 3
    response_particles_per_lenslet: float = Field(RESPONSE_PARTICLES_PER_LENSLET, gt=0,
                                                  le=10, allow_inf_nan=False)
    overlap_correction: bool = _PIV.overlap_correction
    broad_peaks: bool = _PIV.broad_peaks

    def settings(self) -> PIVSettings:
        """The :class:`plenopiv.piv.PIVSettings` of this table (every key but the uncertainty's)."""
        return PIVSettings(**self.model_dump(exclude={"uncertainty", "response_displacements",
                                                      "response_particles_per_lenslet"}))

    @field_validator("windows")
    @classmethod
    def _window_edges(cls, v):
        for w in v:
            if min(w) < MIN_WINDOW_VOX or max(w) > MAX_WINDOW_VOX:
                raise ValueError(f"window {list(w)}: expected edges of {MIN_WINDOW_VOX} to "
                                 f"{MAX_WINDOW_VOX} voxels [wz, wy, wx]")
        return v


class BoxMask(_Strict):
    """One ``[[mask.box]]``: a box in volume coordinates (mm, those of ``[volume]``).

    masked : "inside" (default: the box is a body in the flow) | "outside" (the flow is
        inside the box; everything else is masked).
    """

    x_mm: tuple[float, float]
    y_mm: tuple[float, float]
    z_mm: tuple[float, float]
    masked: Literal["inside", "outside"] = "inside"


class CylinderMask(_Strict):
    """One ``[[mask.cylinder]]``: a circular cylinder along a volume axis (mm).

    axis : "x" | "y" | "z", the cylinder's axis.
    centre_mm : position of the axis in the two other coordinates, in x, y, z order
        (axis "y": ``[x, z]``; axis "x": ``[y, z]``; axis "z": ``[x, y]``).
    radius_mm : radius (> 0).
    length_mm : ``[lo, hi]`` extent along the axis (default: unbounded).
    masked : "inside" (default: a cylinder in the flow) | "outside" (a pipe: the flow is
        inside).
    """

    axis: Literal["x", "y", "z"]
    centre_mm: tuple[float, float]
    radius_mm: float = Field(gt=0, allow_inf_nan=False)
    length_mm: tuple[float, float] | None = None
    masked: Literal["inside", "outside"] = "inside"


class MaskConfig(_Strict):
    """``[mask]``: what to leave out.

    image : a boolean image of the sensor's shape (TIFF, PNG, ``.npy`` or ``file.h5:/path``,
        relative to the experiment file): non-zero pixels (reflections, a model in the view)
        are left out of the reconstruction (their rows of the system are dropped; they are
        not taken as dark).
    volume : a boolean array of the ``[volume]`` grid's shape ``[nz, ny, nx]`` (``.npy`` or
        ``file.h5:/path``): true voxels are outside the flow.
    box, cylinder : geometric volume masks (``[[mask.box]]``, ``[[mask.cylinder]]``), added
        to ``volume``. Masked voxels are zeroed before the PIV; a vector whose window centre
        is masked is NaN, not valid and flagged (``/flag`` bit 4).
    """

    image: str | None = None
    volume: str | None = None
    box: list[BoxMask] = []
    cylinder: list[CylinderMask] = []


class ImagesConfig(_Strict):
    """``[images]``: the image pairs of ``plenopiv run``.

    a, b : glob patterns of the first and second exposures, or
    pairs : glob pattern of HDF5 files each holding ``/image_a`` and ``/image_b``.
    pair_by : how a and b pair up: "auto" (default), "stem" (the parts matched by the
        wildcards agree) or "order" (sorted order); see :func:`plenopiv.batch.discover_pairs`.
    dt_s : time between the exposures, seconds (velocity in m/s when given).
    calibration : the calibration product (.h5), relative to the experiment file.
    """

    a: str | None = None
    b: str | None = None
    pairs: str | None = None
    pair_by: Literal["auto", "stem", "order"] = "auto"
    dt_s: float | None = Field(None, gt=0)
    calibration: str | None = None


class BatchConfig(_Strict):
    """``[batch]``: where the pairs run.

    cluster : "local" | "slurm" | a scheduler address ("tcp://host:8786").
    workers, threads_per_worker : local cluster size (default: cores, one thread each).
    queue, cores, memory, walltime, jobs : SLURM job settings (dask-jobqueue).
    """

    cluster: str = "local"
    workers: int | None = Field(None, ge=1)
    threads_per_worker: int | None = Field(None, ge=1)
    retries: int = Field(2, ge=0)
    queue: str | None = None
    cores: int | None = Field(None, ge=1)
    memory: str | None = None
    walltime: str | None = None
    jobs: int | None = Field(None, ge=1)


class OutputConfig(_Strict):
    """``[output]``: products.

    directory : output folder (relative to the experiment file).
    vtk : also write .vti volumes/vectors for ParaView.
    png : also write PNG figures.
    weights_cache : folder of the voxel-pixel weight cache ("" to disable).
    """

    directory: str = "out"
    vtk: bool = True
    png: bool = True
    weights_cache: str = ".plenopiv-cache"


class TrackingConfig(_Strict):
    """``[tracking]``: particle tracks from the light field (:mod:`plenopiv.tracking`).

    enabled : also track the particles of every pair in ``plenopiv run`` (``NAME_tracks.h5``).
    search_radius_cells : largest distance of a partner from its PIV-predicted position, in
        resolution cells (lateral footprint, depth cell) (1.0).
    median_threshold : normalised median test of a track's deviation from its prediction
        against its neighbouring tracks (2.0, as Westerweel & Scarano 2005 for PIV).
    median_epsilon_cells : noise floor of that test, resolution cells (0.1).
    bundle_radius : a ray belongs to a particle when it passes within this many half beam
        widths of it (1.5).
    bundle_iterations : ray selections and solves per particle, the first around the volume
        centroid (4).
    forward_refine : move each bundle position to the one whose predicted pixel values fit
        the image best (:mod:`plenopiv.particles.forward`) (true).
    min_lenslets : a track is kept when both its ends were seen through at least this many
        lenslets (6: a particle seen through one lenslet is lit at any depth within its depth
        of field; through up to 2 x 2 lenslets the edges of its lit patches fix the ratio of
        lateral offset to depth only, so the image holds no depth for it; 1 keeps every
        track).
    """

    enabled: bool = False
    search_radius_cells: float = Field(1.0, gt=0, allow_inf_nan=False)
    median_threshold: float = Field(2.0, gt=0, allow_inf_nan=False)
    median_epsilon_cells: float = Field(0.1, gt=0, allow_inf_nan=False)
    bundle_radius: float = Field(1.5, gt=0, allow_inf_nan=False)
    bundle_iterations: int = Field(4, ge=1)
    forward_refine: bool = True
    min_lenslets: int = Field(6, ge=1)


class _ExperimentCfg(_Strict):
    camera: str | dict
    volume: dict
    reconstruction: ReconstructionSettings = ReconstructionSettings()
    particles: ParticleSettings = ParticleSettings()
    piv: PIVConfig = PIVConfig()
    images: ImagesConfig = ImagesConfig()
    batch: BatchConfig = BatchConfig()
    output: OutputConfig = OutputConfig()
    tracking: TrackingConfig = TrackingConfig()
    mask: MaskConfig = MaskConfig()


@dataclass(frozen=True)
class Experiment:
    """A resolved experiment configuration."""

    camera: CameraModel
    volume: VolumeGrid
    reconstruction: ReconstructionSettings = ReconstructionSettings()
    particles: ParticleSettings = ParticleSettings()
    piv: PIVConfig = PIVConfig()
    images: ImagesConfig = ImagesConfig()
    batch: BatchConfig = BatchConfig()
    output: OutputConfig = OutputConfig()
    base_dir: Path = Path(".")
    source: dict = field(default_factory=dict, compare=False, repr=False)
    tracking: TrackingConfig = TrackingConfig()
    mask: MaskConfig = MaskConfig()

    def path(self, relative: str | None) -> Path | None:
        """Return a path of the config, resolved against the experiment file's folder."""
        if relative is None:
            return None
        p = Path(relative)
        return p if p.is_absolute() else self.base_dir / p

    def to_dict(self) -> dict:
        """Return the resolved configuration (camera in full), for product attributes."""
        return {"camera": self.camera.to_dict(), "volume": self.volume.to_dict(),
                "reconstruction": self.reconstruction.model_dump(),
                "particles": self.particles.model_dump(), "piv": self.piv.model_dump(),
                "images": self.images.model_dump(), "batch": self.batch.model_dump(),
                "output": self.output.model_dump(), "tracking": self.tracking.model_dump(),
                "mask": self.mask.model_dump()}


def experiment_from_dict(cfg: dict, *, base_dir: Path = Path("."),
                         source: str = "experiment config") -> Experiment:
    """Validate an experiment config dictionary and resolve the camera and the grid."""
    try:
        c = _ExperimentCfg.model_validate(cfg)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, source, _ExperimentCfg)) from None
    if isinstance(c.camera, dict):
        camera = camera_from_dict(c.camera, source=f"{source} [camera]")
    else:
        p = Path(c.camera)
        cand = p if p.is_absolute() else base_dir / p
        camera = load_camera(cand if cand.exists() else c.camera)
    grid = volume_from_dict(c.volume, source=source)
    return Experiment(camera, grid, c.reconstruction, c.particles, c.piv, c.images, c.batch,
                      c.output, base_dir, cfg, tracking=c.tracking, mask=c.mask)


def load_experiment(path: str | Path) -> Experiment:
    """Load an experiment TOML file (relative paths inside resolve against its folder)."""
    p = Path(path)
    return experiment_from_dict(read_toml(p, "experiment"), base_dir=p.parent, source=str(p))
