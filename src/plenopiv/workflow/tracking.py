"""One pair's particle tracks: bundle positions in A and B, PIV-guided matching (orchestration).

::

    volume centroids (A, B) --ray bundles of the raw images--> effective positions
        --depth corrections--> physical positions --PIV prediction + matching--> tracks
        --residuals against the field--> corrected field (corrected_by_tracks)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera.resolution import resolution_cell
from plenopiv.lightfield import LightField, light_field
from plenopiv.particles.bundle import (
    BundlePositions,
    BundleSettings,
    RayTable,
    bundle_positions,
    ray_table,
)
from plenopiv.particles.forward import ForwardSettings, near_focus, refine_positions
from plenopiv.products.vectors import VectorResult
from plenopiv.products.volume import VolumeResult
from plenopiv.tracking.matching import match_particles, predict_positions
from plenopiv.tracking.settings import TrackingSettings
from plenopiv.tracking.tracks import TrackResult

__all__ = ["TrackEnds", "corrected_by_tracks", "match_ends", "physical_bundle", "track_ends",
           "track_images", "track_pair"]


#: The forward refinement's default settings.
FORWARD = ForwardSettings()


def physical_bundle(lf: LightField, image, volume: VolumeResult,
                    settings: BundleSettings, depth_cell: float,
                    forward: ForwardSettings | None = FORWARD, min_lenslets: int = 2,
                    table: RayTable | None = None
                    ) -> tuple[np.ndarray, np.ndarray, BundlePositions]:
    """Bundle positions of a volume's particles, corrected to physical coordinates.

    Returns ``(position (N, 3) m, uncertainty (N, 3) m, raw BundlePositions)``; the depth
    and its uncertainty are scaled by the volume's depth correction like the centroids.
    With ``forward`` (default), the converged bundle positions seen through at least
    ``min_lenslets`` lenslets (and more than one) are refined by
    :func:`plenopiv.particles.forward.refine_positions` (the uncertainty stays the bundle
    fit's); ``None`` keeps the bundle positions. The others keep their bundle position:
    :func:`track_pair` drops the tracks they end. ``table``: the light field's
    :func:`~plenopiv.particles.bundle.ray_table`, when already built.
    """
    table = ray_table(lf) if table is None else table
    # seeded by the volume's own centroids, also where the particle table's positions came
    # from the light field (that fit has a selection margin this one has not; the tracking
    # was validated from the centroids: docs/validation/tracking.md)
    seeds, brightness = volume.volume_peaks()    # a split particle's peak is tracked once
    b = bundle_positions(lf, image, seeds, settings=settings, depth_cell=depth_cell,
                         brightness=brightness, table=table)
    eff = b.position
    # a particle seen through one lenslet lights all its pixels at any depth within the depth
    # of field: the pixel values hold no position to refine
    sel = b.converged & (b.n_lenslets >= max(2, min_lenslets))
    if forward is not None and sel.any():
        eff = eff.copy()
        eff[sel] = refine_positions(lf, image, eff[sel], depth_cell=depth_cell,
                                    settings=forward, table=table)[0]
    corr = volume.correction
    pos = corr.points(eff) if len(b) else b.position.reshape(0, 3)
    unc = b.uncertainty * np.array([1.0, 1.0, corr.scale])
    return pos, unc, b


def _refined(b: BundlePositions, forward: ForwardSettings | None, min_lenslets: int,
             depth_cell: float) -> tuple[int, int]:
    """Particles :func:`physical_bundle` refined: ``(by the grid searches, by local steps)``."""
    if forward is None:
        return 0, 0
    sel = b.converged & (b.n_lenslets >= max(2, min_lenslets))
    grid = near_focus(b.position[sel, 2], depth_cell=depth_cell, settings=forward)
    return int(grid.sum()), int((~grid).sum())


@dataclass(frozen=True, eq=False)
class TrackEnds:
    """The particles of both exposures, ready to be matched (:func:`track_ends`).

    ``position_*`` (N, 3) physical positions and ``uncertainty_*`` (N, 3) their standard
    uncertainties, metres; ``bundle_*`` the raw fits; ``scale`` the resolution cell
    ``(lat, lat, depth)`` in physical metres; ``brightness_*`` (N,) the volumes' particle
    intensities; ``counts`` the particles and fits.
    """

    position_a: np.ndarray
    uncertainty_a: np.ndarray
    bundle_a: BundlePositions
    position_b: np.ndarray
    uncertainty_b: np.ndarray
    bundle_b: BundlePositions
    scale: np.ndarray
    counts: dict
    brightness_a: np.ndarray | None = None
    brightness_b: np.ndarray | None = None


def track_ends(calibration: Calibration, image_a, image_b, volume_a: VolumeResult,
               volume_b: VolumeResult, *, settings: TrackingSettings | None = None,
               f_number: float | None = None, min_lit: float = 0.5,
               lf: LightField | None = None) -> TrackEnds:
    """Bundle (and refined) positions of both exposures' particles.

    Arguments as :func:`track_pair`; :func:`match_ends` matches them.
    """
    settings = TrackingSettings() if settings is None else settings
    if lf is None:
        lf = light_field(calibration, f_number=f_number, min_lit=min_lit)
    lat, dep = resolution_cell(calibration.effective_camera, f_number)
    bs = settings.bundle_settings()
    fs = FORWARD if settings.forward_refine else None
    table = ray_table(lf)
    pa, ua, ba = physical_bundle(lf, image_a, volume_a, bs, dep, fs, settings.min_lenslets,
                                 table)
    pb, ub, bb = physical_bundle(lf, image_b, volume_b, bs, dep, fs, settings.min_lenslets,
                                 table)
    counts = {"particles_a": len(pa), "particles_b": len(pb),
              "bundle_failed_a": int((~ba.converged).sum()),
              "bundle_failed_b": int((~bb.converged).sum())}
    for name, b in (("a", ba), ("b", bb)):
        grid, local = _refined(b, fs, settings.min_lenslets, dep)
        counts[f"refined_grid_{name}"], counts[f"refined_local_{name}"] = grid, local
    scale = np.array([lat, lat, dep * volume_a.correction.scale])
    return TrackEnds(pa, ua, ba, pb, ub, bb, scale, counts,
                     volume_a.volume_peaks()[1], volume_b.volume_peaks()[1])


def match_ends(ends: TrackEnds, vectors: VectorResult, *,
               settings: TrackingSettings | None = None) -> TrackResult:
    """Match the ends of :func:`track_ends` with the correlation field as predictor."""
    settings = TrackingSettings() if settings is None else settings
    pa, pb, ba, bb = ends.position_a, ends.position_b, ends.bundle_a, ends.bundle_b
    # only converged fits take part (the others keep their seed and are left out)
    ia_ok, ib_ok = np.flatnonzero(ba.converged), np.flatnonzero(bb.converged)
    pred = predict_positions(vectors, pa[ia_ok])
    m = match_particles(pa[ia_ok], pb[ib_ok], pred, ends.scale,
                        settings=settings.match_settings())
    ia, ib = ia_ok[m.index_a], ib_ok[m.index_b]
    # an end seen through fewer lenslets has no depth in the image: one lenslet is lit
    # whatever the depth within its depth of field; through up to 2 x 2 lenslets the lit
    # patch has one edge per axis, which fixes the ratio of lateral offset to depth only
    seen = ((ba.n_lenslets[ia] >= settings.min_lenslets)
            & (bb.n_lenslets[ib] >= settings.min_lenslets))
    merged = _merged(ends, ia, ib, settings) & seen
    counts = dict(ends.counts)
    counts.update({"rejected_two_way": m.rejected_mutual,
                   "rejected_ambiguous": m.rejected_ambiguous,
                   "rejected_median": m.rejected_median,
                   "rejected_few_lenslets": int((~seen).sum()),
                   "rejected_merged": int(merged.sum())})
    seen &= ~merged
    counts["tracks"] = int(seen.sum())
    ia, ib = ia[seen], ib[seen]
    return TrackResult(pa[ia], pb[ib], ends.uncertainty_a[ia], ends.uncertainty_b[ib],
                       m.quality[seen], m.residual[seen], ia, ib, ba.n_lenslets[ia],
                       bb.n_lenslets[ib], vectors.dt, counts)


#: A single particle is taken for two merged ones only beyond this many robust standard
#: deviations of the exposure's log brightness above its median (one-sided 0.6 %): with a
#: spread of brightness (a laser profile, particle sizes) the gate follows it.
MERGED_SPREAD_SIGMAS = 2.5


def _merged(ends: TrackEnds, ia, ib, settings: TrackingSettings) -> np.ndarray:
    """Tracks whose two ends are both brighter than the merged-particle limit.

    The limit is the median brightness of the exposure's measurable particles (converged,
    seen through ``min_lenslets``) times ``merged_brightness``, or times
    exp(:data:`MERGED_SPREAD_SIGMAS` s) where their log brightness spreads by s (robust
    standard deviation), whichever is larger: such a track is two particles closer than a
    resolution cell, seen as one in both exposures, about twice as bright as one.
    """
    limit = settings.merged_brightness
    if not limit or ends.brightness_a is None or ends.brightness_b is None:
        return np.zeros(len(ia), bool)
    out = np.ones(len(ia), bool)
    for b, i, fit in ((ends.brightness_a, ia, ends.bundle_a), (ends.brightness_b, ib,
                                                              ends.bundle_b)):
        ok = fit.converged & (fit.n_lenslets >= settings.min_lenslets) & (b > 0)
        if not ok.any():
            return np.zeros(len(ia), bool)
        log_b = np.log(b[ok])
        spread = 1.4826 * float(np.median(np.abs(log_b - np.median(log_b))))
        factor = max(limit, float(np.exp(MERGED_SPREAD_SIGMAS * spread)))
        out &= b[i] > factor * float(np.exp(np.median(log_b)))
    return out


def track_pair(calibration: Calibration, image_a, image_b, volume_a: VolumeResult,
               volume_b: VolumeResult, vectors: VectorResult, *,
               settings: TrackingSettings | None = None, f_number: float | None = None,
               min_lit: float = 0.5, lf: LightField | None = None) -> TrackResult:
    """Track the particles of a pair with the correlation field as predictor.

    Parameters
    ----------
    calibration : Calibration
    image_a, image_b : ndarray
        The raw images of the two exposures.
    volume_a, volume_b : VolumeResult
        Their reconstructions (particle centroids seed the bundle fits).
    vectors : VectorResult
        The pair's correlation field (physical coordinates), the predictor.
    settings : TrackingSettings, optional
        ``[tracking]`` options (default: the defaults).
    f_number, min_lit : optional
        Aperture and pixel selection of the light field (as in ``[reconstruction]``).
    lf : LightField, optional
        The light field of this calibration with ``f_number`` and ``min_lit``, when already
        built (the reconstruction's: ``weights.geometry.light_field``); built here otherwise.
    """
    ends = track_ends(calibration, image_a, image_b, volume_a, volume_b, settings=settings,
                      f_number=f_number, min_lit=min_lit, lf=lf)
    return match_ends(ends, vectors, settings=settings)


def track_images(calibration: Calibration, image_a, image_b, experiment, *,
                 volume_a: VolumeResult | None = None, volume_b: VolumeResult | None = None,
                 vectors: VectorResult | None = None, progress=None,
                 names=("image A", "image B")) -> tuple:
    """Tracks of one pair with an experiment's settings, reusing what is given.

    The images (as recorded) are preprocessed first (``[preprocess]``,
    :class:`~plenopiv.workflow.preprocess.ImagePreparation`, which also judges them); volumes
    not given are reconstructed from them (weights built once, the ``[mask] image`` and the
    preprocessing's mask left out), vectors not given are correlated. ``names``: how warnings
    about the images name them. Returns ``(TrackResult,
    volume_a, volume_b, vectors, timings, preprocess)``, the last what was applied (the
    products' ``preprocess`` attribute).
    """
    import time

    from plenopiv.reconstruction.build import weights_for
    from plenopiv.workflow.correlation import correlate
    from plenopiv.workflow.masks import image_mask
    from plenopiv.workflow.preprocess import ImagePreparation, union
    from plenopiv.workflow.volume import check_lattice, reconstruct_volume

    t = {}
    t0 = time.perf_counter()
    rec = experiment.reconstruction
    preparation = ImagePreparation(experiment, calibration)
    pa, pb, norm = preparation.pair(image_a, image_b, names=names)
    record = preparation.record({"A": pa.figures, "B": pb.figures}, norm)
    image_a, image_b = pa.image, pb.image
    lf = None
    # volumes given are checked when correlated; those made here come from checked images
    given = volume_a is not None and volume_b is not None
    if volume_a is None or volume_b is None:
        # the pair's micro-images against the calibration's, before the weights are made
        calibration = check_lattice(calibration, [image_a, image_b], rec)
        cache = experiment.output.weights_cache
        weights, _ = weights_for(calibration, experiment.volume, rec,
                                 cache_dir=experiment.path(cache) if cache else None)
        lf = _light_field_of(weights)
        kw = dict(settings=rec, particles=experiment.particles, weights=weights,
                  progress=progress, checked=True)
        own = image_mask(experiment.mask, calibration.camera.sensor.shape, experiment.base_dir)
        if volume_a is None:
            volume_a = reconstruct_volume(calibration, image_a, experiment.volume, **kw,
                                          image_mask=union(own, pa.mask))
        if volume_b is None:
            volume_b = reconstruct_volume(calibration, image_b, experiment.volume, **kw,
                                          image_mask=union(own, pb.mask))
    t["reconstruct_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    if vectors is None:
        vectors = correlate(volume_a, volume_b, experiment.piv, dt=experiment.images.dt_s,
                            names=("volume A", "volume B") if given else None)
    t["piv_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    tracks = track_pair(calibration, image_a, image_b, volume_a, volume_b, vectors,
                        settings=experiment.tracking, f_number=rec.f_number,
                        min_lit=rec.min_lit, lf=lf)
    t["track_s"] = time.perf_counter() - t2
    return tracks, volume_a, volume_b, vectors, t, record


def _light_field_of(weights) -> LightField | None:
    """The light field the weights were built from (None when they carry no geometry)."""
    geometry = getattr(weights, "geometry", None)
    return None if geometry is None else geometry.light_field


def track_and_save(calibration: Calibration, image_a, image_b, result, experiment,
                   out_dir, name: str, *, weights=None, inputs=None,
                   judgement: dict | None = None) -> dict:
    """Batch hook (``[tracking] enabled``): track a processed pair, write ``NAME_tracks.h5``.

    ``result`` is the pair's :class:`plenopiv.workflow.pair.PairResult` (its ``preprocess``
    record goes into the tracks product; ``image_a``, ``image_b`` are the images it was
    reconstructed from); ``weights`` the reconstruction's
    (:class:`plenopiv.reconstruction.weights.Weights`), whose light field the tracking reuses
    (built again without them); ``inputs``: the content hashes of ``image_a``, ``image_b``
    and ``calibration``, recorded in its provenance; ``judgement``: the settings' and the
    seeding's judgement for tracking (its ``judgement`` attribute, as ``plenopiv track``
    writes it); returns a small summary.
    """
    import time
    from pathlib import Path

    from plenopiv.products.jsonio import dumps
    from plenopiv.products.tracks import save_track_products
    from plenopiv.workflow.preprocess import ATTRIBUTE
    from plenopiv.workflow.provenance import tracks_provenance

    t0 = time.perf_counter()
    rec = experiment.reconstruction
    tracks = getattr(result, "tracks", None)     # tracked already to correct the vectors
    if tracks is None:
        tracks = track_pair(calibration, image_a, image_b, result.volume_a, result.volume_b,
                            result.vectors, settings=experiment.tracking,
                            f_number=rec.f_number, min_lit=rec.min_lit,
                            lf=_light_field_of(weights))
    pre = {} if result.preprocess is None else {ATTRIBUTE: dumps(result.preprocess)}
    if judgement is not None:
        pre["judgement"] = dumps(judgement)
    paths = save_track_products(tracks, result.vectors, Path(out_dir) / f"{name}_tracks.h5",
                                config=experiment.to_dict(), vtk=experiment.output.vtk,
                                extra_attrs=pre, provenance=tracks_provenance(
                                    experiment, inputs={k: v for k, v in (inputs or {}).items()
                                                        if not k.startswith("mask_")},
                                    record=result.preprocess))
    return {"tracks": paths["tracks"], "n_tracks": len(tracks),
            "track_s": round(time.perf_counter() - t0, 3)}


def corrected_by_tracks(calibration: Calibration, images, volumes, vectors: VectorResult,
                        experiment, weights=None) -> tuple:
    """The pair's tracks and its correlation field corrected by them.

    ``images``: the exposures the volumes came from; ``weights``: the reconstruction's, whose
    light field the tracking reuses. Returns ``(vectors, tracks or None, record)``; where
    the tracking fails (no particle to fit, say) the field is kept as correlated, with a
    warning, and the record says why. See :mod:`plenopiv.tracking.correction`.
    """
    import warnings

    from plenopiv.errors import PlenopivError, PlenopivWarning
    from plenopiv.tracking.correction import correct_with_tracks

    rec, settings = experiment.reconstruction, experiment.tracking
    try:
        tracks = track_pair(calibration, images[0], images[1], volumes[0], volumes[1],
                            vectors, settings=settings, f_number=rec.f_number,
                            min_lit=rec.min_lit, lf=_light_field_of(weights))
    except PlenopivError as exc:
        warnings.warn(f"the pair's particles could not be tracked ({exc}): its vectors are "
                      "the correlation's, not corrected by tracks ([tracking] "
                      "correct_vectors)", PlenopivWarning, stacklevel=3)
        return vectors, None, {"applied": False, "reason": str(exc)}
    out, done = correct_with_tracks(vectors, tracks, prior_tracks=settings.prior_tracks)
    return out, tracks, {"applied": True, **done.record()}
