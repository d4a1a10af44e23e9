"""The pair processor a batch worker keeps between pairs, and the weights it builds once."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.reconstruction.build import weights_for
from plenopiv.resources import allocator_environment, own_process_memory
from plenopiv.workflow.experiment import experiment_calibration
from plenopiv.workflow.pair import PairProcessor, save_pair
from plenopiv.workflow.response import ExperimentResponse


@dataclass(frozen=True)
class ExperimentPairProcess:
    """The per-pair work of ``plenopiv run``: picklable, so dask workers can run it.

    A worker keeps one :class:`PairProcessor` per experiment and calibration file (keyed by
    their paths, sizes and modification times, :func:`worker_processor`): its first pair
    loads the experiment and the calibration and builds or loads the projector, its later
    pairs reuse them. Each call reads the pair's images, processes them and writes the
    products; the vectors file is written last, marked complete.

    ``response``: the chain's response measured once before the pairs fan out
    (:func:`prepare_response`); every pair uses it. None: each worker gets it from the
    response cache, or measures it (``[piv] uncertainty = "response"``). ``background``: the
    batch's minimum or mean background (``[preprocess] background = "minimum"`` or
    ``"mean"``), formed once over the batch's images before the pairs fan out, and
    ``background_images`` the number of images it was formed from. ``allocator``: the
    allocator variables the user set where the process is made, by default taken there
    (:func:`plenopiv.resources.allocator_environment`; None: the worker's own environment,
    where a dask nanny puts its own): the worker's memory is set up by them.
    """

    experiment_path: str
    calibration_path: str
    out_dir: str
    response: ExperimentResponse | None = None
    background: str | None = None
    background_images: int = 0
    allocator: tuple | None = field(default_factory=allocator_environment)

    def __call__(self, job) -> dict:
        """Process one :class:`plenopiv.batch.PairJob`; returns a small summary.

        Its warnings (:class:`~plenopiv.errors.PlenopivWarning`: the image check, the
        preprocessing's one per image, the weights' fallbacks on a worker's first pair) are
        returned under ``warnings``; others are given again in this process.
        """
        import warnings

        from plenopiv.errors import PlenopivWarning
        from plenopiv.products.images import read_image
        from plenopiv.products.jsonio import dumps

        processor = worker_processor(self.experiment_path, self.calibration_path,
                                     self.background, self.background_images,
                                     allocator=self.allocator)
        processor.share_response(self.response)
        exp, cal = processor.experiment, processor.calibration
        ia, ib = read_image(job.image_a), read_image(job.image_b)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", PlenopivWarning)
            res = processor(ia, ib, names=(f"image {str(job.image_a)!r}",
                                           f"image {str(job.image_b)!r}"))
            purposes = ("velocimetry", "tracking") if exp.tracking.enabled else ("velocimetry",)
            judged = _pair_judgements(exp, cal, res, purposes)
        said = [str(w.message) for w in caught if issubclass(w.category, PlenopivWarning)]
        for w in caught:
            if not issubclass(w.category, PlenopivWarning):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        extra = {"image_a": str(job.image_a), "image_b": str(job.image_b)}
        identity = getattr(job, "identity", None)
        if identity is not None:
            extra["identity"] = dumps(dict(identity), sort_keys=True)
        inputs = _inputs_of(identity)
        tracked = {}
        if exp.tracking.enabled:  # before the vectors file, which marks the pair complete
            from plenopiv.workflow.tracking import track_and_save

            tracked = track_and_save(cal, res.images[0].image, res.images[1].image, res, exp,
                                     self.out_dir, job.name, weights=processor.weights(),
                                     inputs=inputs, judgement=judged["tracking"].record())
        paths = save_pair(res, self.out_dir, job.name, exp, extra_attrs=extra, inputs=inputs,
                          judgement=judged["velocimetry"].record())
        vec = res.vectors
        return {"vectors": paths["vectors"], "valid_fraction": float(np.mean(vec.valid)),
                "n_particles_a": len(res.volume_a.particle_position),
                **{k: round(v, 3) for k, v in res.timings.items()}, **tracked,
                **({"warnings": said} if said else {})}


def _inputs_of(identity) -> dict | None:
    """The content hashes a pair's products record, from its job's identity (None: none)."""
    if identity is None:
        return None
    return {**{k: identity.get(k) for k in ("image_a", "image_b", "calibration")},
            **(identity.get("mask") or {})}


def _pair_judgements(exp, cal: Calibration, res, purposes) -> dict:
    """The judgement of a pair's settings and seeding per purpose; each seeding finding warned.

    The settings were said by ``plenopiv run`` before the pairs and are judged once here; each
    pair's seeding (the mean of its two particle tables) is its own, judged for each of
    ``purposes`` ("velocimetry": the vectors; "tracking": the tracks, whose seeding range
    differs).
    """
    import warnings

    from plenopiv.errors import PlenopivWarning
    from plenopiv.workflow.judgement import camera_resolution, judge_experiment

    cam = camera_resolution(cal.effective_camera, exp.reconstruction.f_number)
    _, settings = judge_experiment(exp, cam)
    n = 0.5 * (len(res.volume_a.particle_position) + len(res.volume_b.particle_position))
    out = {}
    for purpose in purposes:
        out[purpose], seeding = settings.with_seeding(
            n, purpose=purpose, piv=exp.piv if purpose == "velocimetry" else None)
        if seeding is not None:
            warnings.warn(seeding.text, PlenopivWarning, stacklevel=2)
    return out


#: The :class:`PairProcessor` this process keeps, with its key (:func:`worker_processor`).
_WORKER_PROCESSOR: dict = {}


_WORKER_LOCK = threading.Lock()


def _file_identity(path: str | Path) -> tuple:
    """``(resolved path, size, modification time in ns)`` of a file."""
    p = Path(path).resolve()
    st = p.stat()
    return (str(p), st.st_size, st.st_mtime_ns)


def worker_processor(experiment_path: str | Path, calibration_path: str | Path,
                     background: str | Path | None = None, background_images: int = 0, *,
                     allocator: tuple | None = None) -> PairProcessor:
    """The :class:`PairProcessor` of this process for an experiment file and a calibration.

    Made on first use (the experiment and the calibration loaded, the projector built or read
    from the weights cache on the first pair) and kept for the later pairs of the process;
    a changed file (size or modification time) or another experiment replaces it. One is kept
    at a time, so a worker holds one projector. ``background``: the batch's background image,
    ``allocator``: the allocator variables the user set (:class:`ExperimentPairProcess`).
    """
    key = (_file_identity(experiment_path), _file_identity(calibration_path),
           None if background is None else _file_identity(background))
    with _WORKER_LOCK:
        if _WORKER_PROCESSOR.get("key") != key:
            from plenopiv.config.experiment import load_experiment

            _WORKER_PROCESSOR.clear()
            own_process_memory(allocator)   # a batch worker's process is the batch's own
            from plenopiv.workflow.judgement import camera_resolution, judge_experiment

            exp = load_experiment(experiment_path)
            cal = experiment_calibration(exp, calibration_path)
            # the settings left unset, chosen as plenopiv run chose them
            exp, _ = judge_experiment(exp, camera_resolution(cal.effective_camera,
                                                             exp.reconstruction.f_number))
            batch, record = None, None
            if background is not None:
                from plenopiv.products.files import file_identity
                from plenopiv.products.images import read_image

                batch = read_image(background)
                record = {"file": str(background), "sha256": file_identity(background),
                          "images": int(background_images)}
            _WORKER_PROCESSOR.update(key=key, processor=PairProcessor(
                exp, cal, batch_background=batch, batch_record=record))
        return _WORKER_PROCESSOR["processor"]


def drop_worker_processor() -> None:
    """Forget this process's :class:`PairProcessor`; the next pair builds its projector again.

    Frees the projector's memory; ``benchmarks/bench_batch.py --no-reuse`` times the rebuild.
    """
    with _WORKER_LOCK:
        _WORKER_PROCESSOR.clear()


def prepare_weights(experiment, calibration: Calibration) -> tuple[bool, float]:
    """Put the experiment's explicit weights into its weights cache before a batch starts.

    Returns ``(found in the cache, seconds spent)``. Without ``[output] weights_cache``, or
    where the reconstruction takes the matrix-free projector (never cached), nothing is
    built here: each worker makes its projector once, for all its pairs
    (:func:`worker_processor`).
    """
    cache = experiment.output.weights_cache
    if not cache:
        return False, 0.0
    t0 = time.perf_counter()
    _, hit = weights_for(calibration, experiment.volume, experiment.reconstruction,
                         cache_dir=experiment.path(cache), load=False)
    return hit, time.perf_counter() - t0



def prepare_response(experiment, calibration: Calibration, *,
                     announce=None) -> ExperimentResponse | None:
    """The chain's response of the experiment, once, before a batch's pairs fan out.

    From the response cache, or measured here (``announce(weights)`` is called first) with
    the projector every pair uses, then cached (``[output] weights_cache``). None unless
    ``[piv] uncertainty = "response"``. The projector built for it is dropped on return.
    """
    if experiment.piv.uncertainty != "response":
        return None
    return PairProcessor(experiment, calibration).response(announce=announce)
