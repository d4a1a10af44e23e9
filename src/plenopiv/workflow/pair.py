"""One image pair -> one vector field.

Two volumes, their correlation, the per-vector uncertainty, the field corrected by the pair's
particle tracks (:func:`plenopiv.workflow.tracking.corrected_by_tracks`) and the pair's
products.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from plenopiv.calibration.model import Calibration
from plenopiv.products.vectors import VectorResult
from plenopiv.products.volume import VolumeResult
from plenopiv.reconstruction.build import weights_for
from plenopiv.reconstruction.weights import Weights
from plenopiv.workflow.correlation import correlate, fitted_to_continuity
from plenopiv.workflow.response import ExperimentResponse, experiment_response
from plenopiv.workflow.volume import Progress, check_lattice, reconstruct_volume

if TYPE_CHECKING:  # imported lazily at run time (scipy.fft, numba kernels)
    pass


@dataclass(frozen=True)
class PairResult:
    """Everything one pair produced.

    ``images``: the two exposures as the reconstruction saw them (preprocessed, B on A's
    scale; :class:`~plenopiv.workflow.preprocess.PreparedImage`); ``preprocess``: what was
    applied (the products' ``preprocess`` attribute); ``tracks``: the pair's
    :class:`~plenopiv.tracking.tracks.TrackResult` where ``[tracking] correct_vectors``
    corrected ``vectors`` by them, and ``track_correction`` what that did (the vectors
    product's ``track_correction`` attribute); ``continuity``: what the fit of w to the
    continuity of the flow did (``[piv] continuity``, the product's ``continuity``).
    """

    volume_a: VolumeResult
    volume_b: VolumeResult
    vectors: VectorResult
    timings: dict
    images: tuple | None = None
    preprocess: dict | None = None
    tracks: object | None = None
    track_correction: dict | None = None
    continuity: dict | None = None


class PairProcessor:
    """The per-pair work of one experiment and calibration, its projector built or loaded once.

    ``processor(image_a, image_b)`` reconstructs both exposures, finds their particles,
    corrects the depths and correlates them, with the experiment's settings
    (:class:`~plenopiv.config.experiment.Experiment`). The weights (explicit, from the weights
    cache, or the matrix-free projector), the image and volume masks, the preprocessing's
    frames (``[preprocess]``, :class:`~plenopiv.workflow.preprocess.ImagePreparation`) and the
    chain's response (``[piv] uncertainty = "response"``, :meth:`response`) are made on first
    use and kept for every later pair; a response measured before (``response``) is used as it
    is. ``batch_background``, ``batch_record``: the batch's minimum or mean background and
    what to record of it (``plenopiv run``). Before the weights are made, the first pair's
    mean is checked against the calibration (``[reconstruction] lattice_check``,
    :func:`~plenopiv.workflow.volume.check_lattice`), and a corrected calibration replaces
    :attr:`calibration`.
    """

    def __init__(self, experiment, calibration: Calibration, *,
                 weights: Weights | None = None, response: ExperimentResponse | None = None,
                 batch_background=None, batch_record: dict | None = None):
        self.experiment = experiment
        self.calibration = calibration
        self._weights = weights
        self._masks = None
        self._response = response
        self._preparation = None
        self._batch = (batch_background, batch_record)
        self._checked = False

    def preparation(self):
        """The experiment's :class:`~plenopiv.workflow.preprocess.ImagePreparation` (made once)."""
        if self._preparation is None:
            from plenopiv.workflow.preprocess import ImagePreparation

            background, record = self._batch
            self._preparation = ImagePreparation(self.experiment, self.calibration,
                                                 batch_background=background,
                                                 batch_record=record)
        return self._preparation

    def weights(self, progress: Progress = None) -> Weights:
        """The projector of every pair (built, or loaded from the weights cache, once)."""
        if self._weights is None:
            if progress is not None:
                progress("weights", 0.0)
            exp = self.experiment
            cache = exp.output.weights_cache
            self._weights, _ = weights_for(self.calibration, exp.volume, exp.reconstruction,
                                           cache_dir=exp.path(cache) if cache else None)
        return self._weights

    def masks(self) -> tuple:
        """``(image_mask, volume_mask)`` of the experiment's ``[mask]`` (each may be None)."""
        if self._masks is None:
            from plenopiv.workflow.masks import image_mask, volume_mask

            exp = self.experiment
            self._masks = (image_mask(exp.mask, self.calibration.camera.sensor.shape,
                                      exp.base_dir),
                           volume_mask(exp.mask, exp.volume, exp.base_dir))
        return self._masks

    def response(self, *, workers=None, progress: Progress = None,
                 announce=None) -> ExperimentResponse | None:
        """The chain's response shared by every pair (None unless ``uncertainty = "response"``).

        :func:`plenopiv.workflow.response.experiment_response`: from the response cache, or
        measured once (``announce(weights)`` is called first), then kept.
        """
        if self.experiment.piv.uncertainty != "response":
            return None
        if self._response is None:
            if progress is not None:
                progress("response", 0.0)
            from plenopiv.workflow.preprocess import union

            img_mask, vol_mask = self.masks()
            # the test pairs leave out what every real image leaves out (the white's mask)
            img_mask = union(img_mask, self.preparation().static_mask)
            self._response = experiment_response(
                self.experiment, self.calibration, self.weights(progress),
                self.experiment.piv, image_mask=img_mask, volume_mask=vol_mask,
                workers=workers, announce=announce)
        return self._response

    def share_response(self, response: ExperimentResponse | None) -> None:
        """Use ``response``, measured before (e.g. by the batch), unless one is kept already."""
        if self._response is None:
            self._response = response

    def __call__(self, image_a, image_b, *, progress: Progress = None,
                 workers=None, names=("image A", "image B")) -> PairResult:
        """Images A and B -> preprocessing -> two volumes -> particles -> corrections -> vectors.

        The vectors are corrected by the pair's tracks with ``[tracking] correct_vectors``.
        ``image_a``, ``image_b``: the exposures as recorded (counts); ``names``: how
        warnings about them name them. ``timings``: ``reconstruct_s``, ``piv_s``, ``track_s``
        where the pair was tracked and, when this pair got the chain's response (measured or
        read from the cache), ``response_s``.
        """
        from plenopiv.workflow.preprocess import union

        t0 = time.perf_counter()
        if self._weights is None and not self._checked:
            # the first pair's mean against the calibration, before the weights are made
            self.calibration = check_lattice(self.calibration, [image_a, image_b],
                                             self.experiment.reconstruction)
            self._checked = True
        exp, calibration = self.experiment, self.calibration
        preparation = self.preparation()
        pa, pb, norm = preparation.pair(image_a, image_b, names=names)
        record = preparation.record({"A": pa.figures, "B": pb.figures}, norm)
        weights = self.weights(progress)
        img_mask, vol_mask = self.masks()
        kw = dict(settings=exp.reconstruction, particles=exp.particles, weights=weights,
                  checked=True)
        va = reconstruct_volume(calibration, pa.image, exp.volume, **kw,
                                image_mask=union(img_mask, pa.mask),
                                progress=_volume_progress(progress, "A"))
        vb = reconstruct_volume(calibration, pb.image, exp.volume, **kw,
                                image_mask=union(img_mask, pb.mask),
                                progress=_volume_progress(progress, "B"))
        t1 = time.perf_counter()
        had_response = self._response is not None
        measured = self.response(workers=workers, progress=progress)
        t2 = time.perf_counter()
        if progress is not None:
            progress("piv", 0.0)
        response = None if measured is None else (lambda _field: measured.response)
        vec = correlate(va, vb, exp.piv, dt=exp.images.dt_s, workers=workers,
                        mask=vol_mask, response=response, progress=_piv_progress(progress),
                        names=None)      # the images were checked (ImagePreparation.pair)
        timings = {"reconstruct_s": t1 - t0, "piv_s": time.perf_counter() - t2}
        if measured is not None and not had_response:
            timings["response_s"] = t2 - t1
        tracks = correction = None
        if exp.tracking.correct_vectors:
            t3 = time.perf_counter()
            if progress is not None:
                progress("tracks", 0.0)
            from plenopiv.workflow.tracking import corrected_by_tracks

            vec, tracks, correction = corrected_by_tracks(calibration, (pa.image, pb.image),
                                                          (va, vb), vec, exp, weights)
            timings["track_s"] = time.perf_counter() - t3
        vec, continuity = fitted_to_continuity(vec, exp.piv)
        return PairResult(va, vb, vec, timings, images=(pa, pb), preprocess=record,
                          tracks=tracks, track_correction=correction, continuity=continuity)


def _piv_progress(progress: Progress):
    """``progress`` of the PIV passes as ``"piv pass i/n"``, or None."""
    if progress is None:
        return None
    return lambda info: progress(f"piv pass {info['pass']}/{info['passes']}",
                                 info["pass"] / info["passes"])


def process_pair(calibration: Calibration, image_a, image_b, experiment, *,
                 weights: Weights | None = None, progress: Progress = None,
                 workers=None) -> PairResult:
    """Images A and B -> two volumes -> particles -> corrections -> vectors.

    With the experiment's settings (:class:`~plenopiv.config.experiment.Experiment`), the
    weights built once for both volumes.

    One pair; many pairs of one experiment share a :class:`PairProcessor`.
    """
    return PairProcessor(experiment, calibration, weights=weights)(
        image_a, image_b, progress=progress, workers=workers)


def _volume_progress(progress: Progress, tag: str) -> Progress:
    """The progress of one volume of a pair, reported as ``"volume A: mart"`` etc.

    Its fraction is over the whole volume (MART about 90 % of it).
    """
    if progress is None:
        return None

    def report(stage: str, fraction: float) -> None:
        share = {"mart": 0.9 * fraction, "particles": 0.95}.get(stage, 0.0)
        progress(f"volume {tag}: {stage}", share)
    return report


def save_pair(result: PairResult, out_dir: str | Path, name: str, experiment, *,
              extra_attrs=None, inputs=None, judgement: dict | None = None) -> dict:
    """Write a pair's products: ``NAME_vectors.h5`` (+ ``.vti``), the two volumes, PNGs.

    The vectors file is written last and marked complete, so that a batch can resume.
    ``inputs``: the content hashes of ``image_a``, ``image_b``, ``calibration`` and the
    ``[mask]`` files (``mask_image``, ``mask_volume``), recorded in each product's
    ``provenance`` (:mod:`plenopiv.workflow.provenance`); the masks are hashed here when
    not given. ``judgement``: the settings' and the seeding's judgement
    (:meth:`~plenopiv.workflow.judgement.Judgement.record`), every product's ``judgement``
    attribute.
    """
    from plenopiv.products.jsonio import dumps
    from plenopiv.workflow.preprocess import ATTRIBUTE
    from plenopiv.workflow.provenance import mask_inputs, vectors_provenance, volume_provenance

    out = Path(out_dir)
    cfg = experiment.to_dict()
    pre = {} if result.preprocess is None else {ATTRIBUTE: dumps(result.preprocess)}
    inputs = dict(inputs or {})
    masks = {k: v for k, v in inputs.items() if k.startswith("mask_")} \
        if any(k.startswith("mask_") for k in inputs) else mask_inputs(experiment)
    if judgement is not None:
        pre["judgement"] = dumps(judgement)
    paths, records = {}, {}
    for tag, vol in (("A", result.volume_a), ("B", result.volume_b)):
        records[f"volume_{tag.lower()}"] = volume_provenance(
            experiment, image=inputs.get(f"image_{tag.lower()}"),
            calibration=inputs.get("calibration"), record=result.preprocess, masks=masks)
        paths[f"volume_{tag}"] = str(vol.save(out / f"{name}_volume_{tag}.h5", config=cfg,
                                              extra_attrs=pre,
                                              provenance=records[f"volume_{tag.lower()}"]))
    if experiment.output.png:
        from plenopiv.products.figures import vector_slices, volume_slices

        va = result.volume_a
        paths["png_volume"] = str(volume_slices(va.volume, va.grid.x, va.grid.y, va.grid.z,
                                                out / f"{name}_volume_A.png",
                                                particles=va.particle_position_effective,
                                                title=f"pair {name}: volume A"))
        paths["png_vectors"] = str(vector_slices(result.vectors, out / f"{name}_vectors.png",
                                                 title=f"pair {name}"))
    record = vectors_provenance(paths["volume_A"], paths["volume_B"],
                                piv=experiment.piv, dt=experiment.images.dt_s,
                                sources=records)
    corrected = {key: dumps(value) for key, value in (
        ("track_correction", result.track_correction), ("continuity", result.continuity))
        if value is not None}
    files = result.vectors.save(out / f"{name}_vectors.h5", config=cfg, vtk=experiment.output.vtk,
                                extra_attrs={"complete": True, **pre, **corrected,
                                             **(extra_attrs or {})}, provenance=record)
    paths["vectors"] = str(files[0])
    if len(files) > 1:
        paths["vtk"] = str(files[1])
    return paths
