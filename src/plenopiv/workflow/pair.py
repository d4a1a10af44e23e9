"""One image pair -> one vector field.

Two volumes, their correlation, the per-vector uncertainty and the pair's products.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.errors import PIVError, ReconstructionError
from plenopiv.products.vectors import VectorResult, check_dt
from plenopiv.products.volume import VolumeResult
from plenopiv.reconstruction.subdivision import weights_for
from plenopiv.reconstruction.weights import Weights
from plenopiv.settings import as_dict
from plenopiv.workflow.volume import Progress, reconstruct_volume

if TYPE_CHECKING:  # imported lazily at run time (scipy.fft, numba kernels)
    pass



def correlate(result_a: VolumeResult, result_b: VolumeResult, settings=None, *, dt=None,
              workers=None, progress=None, mask=None, response=None) -> VectorResult:
    """3-D PIV between two reconstructed volumes of the same grid, in physical coordinates.

    The volumes are on the effective (air-equivalent) grid.

    ``mask``: volume mask (bool ``[z, y, x]``, True outside the flow). ``response``: a
    callable ``response(field) -> Response`` (:func:`plenopiv.workflow.response.measure_response`)
    whose result completes the uncertainties (:func:`plenopiv.piv.uncertainty.combine`); None
    keeps the correlation statistics alone.
    """
    from plenopiv.piv import PIVSettings, correlate_volumes
    from plenopiv.piv.uncertainty import combine

    for name, r in (("result_a", result_a), ("result_b", result_b)):
        if not isinstance(r, VolumeResult):
            raise PIVError(f"correlate: {name} is a {type(r).__name__}: expected a "
                           "VolumeResult (reconstruct_volume or load_volume)")
    if settings is not None and not isinstance(settings, PIVSettings):
        raise PIVError(f"correlate: settings is a {type(settings).__name__}: expected a "
                       "PIVSettings (or None for the defaults)")
    dt = check_dt(dt)
    if result_a.grid != result_b.grid:
        def text(g):
            return (f"{list(g.shape)} voxels of {[round(v * 1e3, 6) for v in g.voxel]} mm from "
                    f"{[round(v * 1e3, 6) for v in g.origin]} mm")
        raise ReconstructionError("the two volumes were reconstructed on different grids "
                                  f"(A: {text(result_a.grid)}; B: {text(result_b.grid)}): "
                                  "expected the same [volume] for both exposures")
    field = correlate_volumes(result_a.volume, result_b.volume, result_a.grid,
                              settings=settings, workers=workers, progress=progress, mask=mask)
    method = "correlation"
    measured = None if response is None else response(field)
    if measured is not None:
        field = combine(field, measured)
        method = "response"
    return VectorResult.from_field(field, result_a.correction, dt, uncertainty_method=method,
                                   grid=result_a.grid)


@dataclass(frozen=True)
class PairResult:
    """Everything one pair produced.

    ``images``: the two exposures as the reconstruction saw them (preprocessed, B on A's
    scale; :class:`~plenopiv.workflow.preprocess.PreparedImage`); ``preprocess``: what was
    applied (the products' ``preprocess`` attribute).
    """

    volume_a: VolumeResult
    volume_b: VolumeResult
    vectors: VectorResult
    timings: dict
    images: tuple | None = None
    preprocess: dict | None = None


class PairProcessor:
    """The per-pair work of one experiment and calibration, its projector built or loaded once.

    ``processor(image_a, image_b)`` reconstructs both exposures, finds their particles,
    corrects the depths and correlates them, with the experiment's settings
    (:class:`~plenopiv.config.experiment.Experiment`). The weights (explicit, from the weights
    cache, or the matrix-free projector), the image and volume masks and the preprocessing's
    frames (``[preprocess]``, :class:`~plenopiv.workflow.preprocess.ImagePreparation`) are made
    on first use and kept for every later pair. ``batch_background``, ``batch_record``: the
    batch's minimum or mean background and what to record of it (``plenopiv run``).
    """

    def __init__(self, experiment, calibration: Calibration, *,
                 weights: Weights | None = None, batch_background=None,
                 batch_record: dict | None = None):
        self.experiment = experiment
        self.calibration = calibration
        self._weights = weights
        self._masks = None
        self._preparation = None
        self._batch = (batch_background, batch_record)

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

    def __call__(self, image_a, image_b, *, progress: Progress = None,
                 workers=None, names=("image A", "image B")) -> PairResult:
        """Images A and B -> preprocessing -> two volumes -> particles -> corrections -> vectors.

        ``image_a``, ``image_b``: the exposures as recorded (counts); ``names``: how
        warnings about them name them.
        """
        from plenopiv.workflow.preprocess import union

        t0 = time.perf_counter()
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
        if progress is not None:
            progress("piv", 0.0)
        settings = exp.piv
        response = None
        if exp.piv.uncertainty == "response":
            # the test pairs leave out what every real image leaves out (the white's mask)
            response = _response_of(calibration, weights, va, exp, settings, workers,
                                    union(img_mask, preparation.static_mask), vol_mask)
        vec = correlate(va, vb, settings, dt=exp.images.dt_s, workers=workers,
                        mask=vol_mask, response=response, progress=_piv_progress(progress))
        t2 = time.perf_counter()
        return PairResult(va, vb, vec, {"reconstruct_s": t1 - t0, "piv_s": t2 - t1},
                          images=(pa, pb), preprocess=record)


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


def _response_of(calibration, weights, volume_a: VolumeResult, experiment, settings, workers,
                 img_mask, vol_mask):
    """``response(field)`` for :func:`correlate`: the chain's measured response.

    :func:`plenopiv.workflow.response.measure_response` for this experiment, kept in the weights
    cache (``[output] weights_cache``) under a key of everything it depends on.
    """
    from plenopiv.piv import correlate_volumes
    from plenopiv.products.caches import cached_response, response_key
    from plenopiv.workflow.response import measure_response

    grid = volume_a.grid
    # the seeding of the real pair, rounded to a power of two so that pairs share a response
    n_found = max(len(volume_a.particle_position), 1)
    n_particles = int(2 ** round(np.log2(n_found)))

    def reconstruct(image):
        return reconstruct_volume(calibration, image, grid, settings=experiment.reconstruction,
                                  particles=experiment.particles, weights=weights,
                                  image_mask=img_mask).volume

    def correlate_pair(a, b):
        return correlate_volumes(a, b, grid, settings=settings, workers=workers, mask=vol_mask)

    def response(field):
        key = response_key(weights.key, grid.key(), as_dict(experiment.reconstruction),
                           as_dict(experiment.piv), n_particles,
                           calibration.point_spread_sigma_px,
                           None if img_mask is None else hashlib_of(img_mask),
                           None if vol_mask is None else hashlib_of(vol_mask))
        cache = experiment.output.weights_cache
        path = experiment.path(cache) / f"response-{key[:24]}.json" if cache else None
        resp, _ = cached_response(path, key, lambda: measure_response(
            calibration, grid, volume_a.correction, reconstruct=reconstruct,
            correlate=correlate_pair, n_particles=n_particles,
            f_number=experiment.reconstruction.f_number,
            displacements=experiment.piv.response_displacements))
        return resp

    return response


def hashlib_of(array) -> str:
    """A short hash of an array's bytes and shape (for cache keys)."""
    import hashlib

    a = np.ascontiguousarray(array)
    return hashlib.sha256(a.tobytes() + str(a.shape).encode()).hexdigest()[:16]


def save_pair(result: PairResult, out_dir: str | Path, name: str, experiment, *,
              extra_attrs=None) -> dict:
    """Write a pair's products: ``NAME_vectors.h5`` (+ ``.vti``), the two volumes, PNGs.

    The vectors file is written last and marked complete, so that a batch can resume.
    """
    from plenopiv.products.jsonio import dumps
    from plenopiv.workflow.preprocess import ATTRIBUTE

    out = Path(out_dir)
    cfg = experiment.to_dict()
    pre = {} if result.preprocess is None else {ATTRIBUTE: dumps(result.preprocess)}
    paths = {}
    for tag, vol in (("A", result.volume_a), ("B", result.volume_b)):
        paths[f"volume_{tag}"] = str(vol.save(out / f"{name}_volume_{tag}.h5", config=cfg,
                                              extra_attrs=pre))
    if experiment.output.png:
        from plenopiv.products.figures import vector_slices, volume_slices

        va = result.volume_a
        paths["png_volume"] = str(volume_slices(va.volume, va.grid.x, va.grid.y, va.grid.z,
                                                out / f"{name}_volume_A.png",
                                                particles=va.particle_position_effective,
                                                title=f"pair {name}: volume A"))
        paths["png_vectors"] = str(vector_slices(result.vectors, out / f"{name}_vectors.png",
                                                 title=f"pair {name}"))
    files = result.vectors.save(out / f"{name}_vectors.h5", config=cfg, vtk=experiment.output.vtk,
                                extra_attrs={"complete": True, **pre,
                                             **(extra_attrs or {})})
    paths["vectors"] = str(files[0])
    if len(files) > 1:
        paths["vtk"] = str(files[1])
    return paths

