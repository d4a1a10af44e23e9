"""The reconstruction's settings: the ``[reconstruction]`` table of an experiment file."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, StrictInt, field_validator

from plenopiv.settings import settings

__all__ = ["MAX_DEPTH_BINNING", "MAX_ITERATIONS", "MAX_SUBDIVISION", "ReconstructionSettings"]

#: More MART sweeps than this is refused: 10 is the default, a few hundred already converge.
MAX_ITERATIONS = 10_000
#: Largest lateral subdivision of the reconstruction grid (``lateral_subdivision``).
MAX_SUBDIVISION = 4
#: Most depth slices of the [volume] grid merged into one working slice (``depth_binning``).
MAX_DEPTH_BINNING = 16


@settings
class ReconstructionSettings:
    """``[reconstruction]``: MART options.

    method : "smart" (simultaneous multiplicative, default: independent of pixel order, so
        the two exposures of a pair reconstruct consistently) | "mart" (row action, Elsinga
        2006) | "block" (one block per perspective view).
    iterations : sweeps after the MLOS first guess (10; see docs/validation/field_quality.md).
    relaxation : μ, dimensionless; default by method: 2.0 for "smart", 0.03 for "mart" and
        "block" (in a plenoptic W every voxel is seen by ~200 pixels, so one row-action sweep
        at μ = 1 over-relaxes ~200-fold).
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
        is reconstructed far too long in depth and its depth motion is under-measured
        (docs/validation/vortex.md). Costs k² in explicit weights and working voxels and
        about k in the time of a sweep, so "auto" takes a coarser k (down to 1) where the
        working grid would hold more than 50 million voxels, or on a turned or hexagonal
        lattice more than 16.7 million on its binned depth slices (the 16 MP camera's full
        volume: 2 x 2, 16 s a volume on an aligned array, 60-66 s on a turned or hexagonal
        one, 3.5-3.9 GB, on 2 cores), and says so. A k that leaves working voxels of 0.75
        footprint or wider is warned before a run (docs/methods.md#settings-judgement).
    depth_binning : "auto" (default) | an int k >= 1. The reconstruction runs on depth slices
        k times as deep as the [volume] grid's (centred on its depth range), and its volume
        is resampled onto the grid's slices (a cubic interpolating spline in depth, the total
        kept). "auto" takes the largest k whose working slice is at most a third of the depth
        resolution cell (b S_o N / f_m; 5 % slack): a reconstructed particle is about one
        cell long, so finer slices resolve nothing more and cost time and memory in
        proportion (1 where the grid's slices are that deep already, 2-3 for cubic voxels a
        footprint wide on the 16 MP camera; docs/methods.md#depth-binning).
    subdivision_kernel : how the working voxels return to the [volume] grid: "gaussian"
        (default): each voxel takes the working volume weighted by a Gaussian of σ = half a
        voxel about its centre, which keeps where a particle lies inside the voxel in the
        ratio of neighbouring voxels (anti-aliasing; against the peak locking of voxels as
        wide as a footprint) | "box": the sum of the voxel's own working voxels.
    lattice_check : the recording's micro-images checked against the calibration's before the
        reconstruction (:func:`plenopiv.calibration.recording.check_recording`, on the pair's
        mean): "refuse" (default): a shift or rotation that moves a micro-image more than
        lattice_tolerance_px is an error with the figure | "correct": the calibration's
        lenslet centres and focal spots are moved onto the recording, with a warning |
        "off": no check.
    lattice_tolerance_px : the largest displacement of a micro-image accepted, px (0.25).
    """

    method: Literal["mart", "block", "smart"] = "smart"
    iterations: int = Field(10, ge=0, le=MAX_ITERATIONS)
    relaxation: float | None = Field(None, gt=0, allow_inf_nan=False)
    pixel_threshold: float = Field(0.003, ge=0, lt=1)
    dark_tolerance: float = Field(0.5, ge=0, le=1)
    f_number: float | None = Field(None, gt=0)
    min_lit: float = Field(0.5, gt=0, le=1)
    projector: Literal["auto", "sparse", "lattice"] = "auto"
    max_weights_gb: float | None = Field(None, gt=0, allow_inf_nan=False)
    lateral_subdivision: Literal["auto"] | StrictInt = Field("auto", union_mode="left_to_right")
    depth_binning: Literal["auto"] | StrictInt = Field("auto", union_mode="left_to_right")
    subdivision_kernel: Literal["gaussian", "box"] = "gaussian"
    lattice_check: Literal["refuse", "correct", "off"] = "refuse"
    lattice_tolerance_px: float = Field(0.25, gt=0, allow_inf_nan=False)

    @field_validator("lateral_subdivision", "depth_binning")
    @classmethod
    def _auto_or_count(cls, v, info):
        most = MAX_SUBDIVISION if info.field_name == "lateral_subdivision" else MAX_DEPTH_BINNING
        if v != "auto" and not (isinstance(v, int) and not isinstance(v, bool)
                                and 1 <= v <= most):
            raise ValueError(f"expected \"auto\" or an int from 1 to {most}")
        return v

    @property
    def relaxation_used(self) -> float:
        """μ: the given relaxation, or the method's default."""
        if self.relaxation is not None:
            return self.relaxation
        return 2.0 if self.method == "smart" else 0.03
