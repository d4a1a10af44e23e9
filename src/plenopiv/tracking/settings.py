"""The tracking's settings: the ``[tracking]`` table of an experiment file."""

from __future__ import annotations

from pydantic import Field

from plenopiv.particles.bundle import BundleSettings
from plenopiv.settings import settings
from plenopiv.tracking.matching import MatchSettings

__all__ = ["AMBIGUITY", "PRIOR_TRACKS", "TrackingSettings"]

#: Default ``ambiguity_ratio`` (docs/validation/tracking.md, the ratio-test curve).
AMBIGUITY = 0.7
#: Default ``prior_tracks``: one track on a vector weighs as much as its window's correlation
#: (docs/methods.md#track-correction).
PRIOR_TRACKS = 1.0


@settings
class TrackingSettings:
    """``[tracking]``: particle tracks from the light field (:mod:`plenopiv.tracking`).

    enabled : also track the particles of every pair in ``plenopiv run`` (``NAME_tracks.h5``).
    search_radius_cells : largest distance of a partner from its PIV-predicted position, in
        resolution cells (lateral footprint, depth cell) (1.0).
    median_threshold : normalised median test of a track's deviation from its prediction
        against its neighbouring tracks (2.0, as Westerweel & Scarano 2005 for PIV).
    median_epsilon_cells : noise floor of that test, resolution cells (0.1).
    ambiguity_ratio : ratio test of a match, in (0, 1]: refused when its distance from the
        prediction exceeds this fraction of the runner-up's, in either direction (another
        particle of B near the prediction, or another particle's prediction near the B
        particle); smaller refuses more; 1 keeps every mutual nearest pair (0.7).
    merged_brightness : a track is refused when both its ends are brighter than this many
        times the median particle of their volume (two particles closer than a resolution
        cell, seen as one in both exposures: the track joins two particles); raised to
        exp(2.5 s) where the particles' log brightness spreads by s (a real recording's
        spread: s 0.3 makes it 2.1); 0 keeps them (1.45).
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
    correct_vectors : correct each pair's correlation field by its tracks in ``plenopiv run``
        and ``demo`` (``process_pair``): each track's residual (its displacement less the
        field at its mid-point) spread over the vectors within about a window of it
        (:mod:`plenopiv.tracking.correction`, docs/methods.md#track-correction) (true).
    prior_tracks : the correction's shrinkage, in tracks: a vector with one track on it takes
        1 / (1 + prior_tracks) of that track's residual, one far from every track keeps its
        value (1.0).
    """

    enabled: bool = False
    search_radius_cells: float = Field(1.0, gt=0, allow_inf_nan=False)
    median_threshold: float = Field(2.0, gt=0, allow_inf_nan=False)
    median_epsilon_cells: float = Field(0.1, gt=0, allow_inf_nan=False)
    ambiguity_ratio: float = Field(AMBIGUITY, gt=0, le=1, allow_inf_nan=False)
    merged_brightness: float = Field(1.45, ge=0, allow_inf_nan=False)
    bundle_radius: float = Field(1.5, gt=0, allow_inf_nan=False)
    bundle_iterations: int = Field(4, ge=1)
    forward_refine: bool = True
    min_lenslets: int = Field(6, ge=1)
    correct_vectors: bool = True
    prior_tracks: float = Field(PRIOR_TRACKS, gt=0, allow_inf_nan=False)

    def match_settings(self) -> MatchSettings:
        """The matcher's options of this table (the same names, in resolution cells)."""
        return MatchSettings(search_radius_cells=self.search_radius_cells,
                             median_threshold=self.median_threshold,
                             median_epsilon_cells=self.median_epsilon_cells,
                             ambiguity_ratio=self.ambiguity_ratio)

    def bundle_settings(self) -> BundleSettings:
        """The ray-bundle fit's options of this table (``bundle_radius``, ``bundle_iterations``)."""
        return BundleSettings(radius=self.bundle_radius, iterations=self.bundle_iterations)
