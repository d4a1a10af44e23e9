"""One image -> one volume; one image pair -> one vector field (orchestration, no physics).

::

    image --(weights from the calibration's S_i,eff)--> MART volume --> particles
          --> depth corrections (external n1/n2, internal n3/n4) --> products

The stages are the library's stage functions; this module chooses defaults, keeps the weights
(built once per geometry, cached on disk), reports progress and writes products atomically.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from plenopiv.calibration.model import Calibration
from plenopiv.camera import CameraModel
from plenopiv.config import ParticleSettings, ReconstructionSettings
from plenopiv.corrections import DepthCorrection
from plenopiv.errors import CalibrationError, ConfigError, PIVError, ReconstructionError
from plenopiv.particles import find_particles
from plenopiv.products.images import check_image
from plenopiv.products.vectors import VectorResult, check_dt
from plenopiv.products.volume import VolumeResult
from plenopiv.reconstruction.geometry import ProjectionGeometry
from plenopiv.reconstruction.solve import solve_volume
from plenopiv.reconstruction.subdivision import (  # noqa: F401 - the pipeline's names too
    SUBDIVIDED_VOXEL_FOOTPRINTS,
    footprint,
    lateral_subdivision,
    merge_subdivided,
    reconstruction_grid,
    subdivided_grid,
    subdivision_of,
    weights_for,
)
from plenopiv.reconstruction.weights import Weights
from plenopiv.resources import prefer_small_pages
from plenopiv.tracking.bundle import PARTICLE_BUNDLE, bundle_positions, lit_rays
from plenopiv.volume import VolumeGrid

if TYPE_CHECKING:  # imported lazily at run time (scipy.fft, numba kernels)
    from plenopiv.piv import PIVSettings

Progress = Callable[[str, float], None] | None
_DEFAULT_RECONSTRUCTION = ReconstructionSettings()
_DEFAULT_PARTICLES = ParticleSettings()




def resolution_cell(camera: CameraModel, f_number: float | None = None) -> tuple[float, float]:
    """Lateral and depth resolution of the camera near the focal plane, metres.

    Lateral: one lenslet footprint b = p_m S_o/S_i. Depth: the views at the two edges of the
    aperture (diameter D = f_m/N) see a particle at depth Z displaced by D Z/S_o relative to
    each other, so two depths are told apart when that shift changes by one footprint:
    ΔZ = b S_o/D (0.55 mm for the 50 mm lens at M = -1, f/2.2). The ratio ΔZ/b = S_o/D is the
    depth elongation expected of a reconstructed particle. Give the effective camera
    (``calibration.effective_camera``) for effective coordinates.
    """
    n = camera.main_lens.f_number if f_number is None else f_number
    b = footprint(camera)
    return b, b * camera.object_distance * n / camera.main_lens.focal_length


def particle_options(particles: ParticleSettings, grid: VolumeGrid, calibration: Calibration,
                     volume, *, f_number: float | None = None) -> dict:
    """Keywords of :func:`~plenopiv.particles.find_particles` for ``particles`` and a volume.

    The threshold is ``particles.threshold`` times the reference intensity (the 99.9th
    percentile of the positive voxels, or the maximum). Unset separation and box follow the
    resolution cell (:func:`resolution_cell`) in voxels of ``grid``: peaks closer than one
    cell (1.5 cells laterally, so that diagonal neighbours merge) are one particle; the
    centroid box is ±1 cell.
    """
    v = np.asarray(volume)
    if particles.threshold_reference == "maximum":
        ref = float(v.max())
    else:
        pos = v[v > 0]
        ref = float(np.percentile(pos, 99.9)) if pos.size else 0.0
    lat, dep = resolution_cell(calibration.effective_camera, f_number)
    vx, vy, vz = (float(a) for a in grid.voxel)
    sep = particles.min_separation_vox
    if sep is None:
        sep = (max(dep / vz, 1.0), max(1.5 * lat / vy, 1.0), max(1.5 * lat / vx, 1.0))
    box = particles.box_vox
    if box is None:
        box = tuple(max(1, int(round(c / d))) for c, d in ((dep, vz), (lat, vy), (lat, vx)))
    return {"threshold": particles.threshold * ref, "method": particles.method,
            "min_separation_vox": tuple(sep), "box_vox": tuple(box),
            "fit_spacing_vox": particles.fit_spacing_vox}


def reconstruct_volume(calibration: Calibration, image, grid: VolumeGrid, *,
                       settings: ReconstructionSettings = _DEFAULT_RECONSTRUCTION,
                       particles: ParticleSettings = _DEFAULT_PARTICLES,
                       weights: Weights | None = None, cache_dir: str | Path | None = None,
                       progress: Progress = None, image_mask=None) -> VolumeResult:
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
        from the unmasked pixels. See :mod:`plenopiv.masks`.
    """
    from plenopiv.resources import check_grid

    t = {}
    t0 = time.perf_counter()
    check_grid(grid)
    img = check_image(image, shape=calibration.camera.sensor.shape, name="particle image",
                      particles=True)
    if weights is None:
        if progress is not None:
            progress("weights", 0.0)
        weights, _ = weights_for(calibration, grid, settings, cache_dir=cache_dir)
    geometry = weights.geometry
    if geometry is None:        # weights made without one: the rays of these settings
        geometry = ProjectionGeometry.for_settings(calibration, weights.grid, settings)
    ky, kx = (1, 1) if weights.grid == grid else subdivision_of(weights.grid, grid)
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
                       footprint=footprint(calibration.effective_camera))
    if ky > 1 or kx > 1:            # the working voxels back onto the volume's grid
        vol = merge_subdivided(vol, ky, kx, kernel=settings.subdivision_kernel)
    t["mart_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    if progress is not None:
        progress("particles", 0.0)
    corr, eff, pos, intensity, size = _particles_of(vol, grid, calibration, particles)
    centroid = None
    if particles.position == "light_field" and len(eff):
        if progress is not None:
            progress("particles", 0.5)
        centroid = eff
        eff = light_field_positions(geometry.light_field, img, centroid, intensity,
                                    calibration, image_mask=image_mask)
        pos = corr.points(eff)
    t["particles_s"] = time.perf_counter() - t2
    return VolumeResult(vol, grid, corr, eff, pos, intensity, size, t,
                        particle_centroid_effective=centroid)


def _particles_of(vol: np.ndarray, grid: VolumeGrid, calibration: Calibration,
                  particles: ParticleSettings) -> tuple:
    """``(correction, effective positions, positions, intensities, sizes)`` of the particles.

    Found by :func:`plenopiv.particles.find_particles`, then depth-corrected.
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
    (:func:`plenopiv.tracking.bundle.bundle_positions` with
    :data:`~plenopiv.tracking.bundle.PARTICLE_BUNDLE`, the volume intensities sharing the
    rays that pass several particles). The voxel grid quantises a reconstructed particle:
    an in-focus one fills its lenslet's footprint and its centroid moves with the voxel
    edges; the rays do not depend on the grid. Masked pixels carry no light. A particle
    with fewer than ``min_rays`` rays keeps its seed.
    """
    _, cell = resolution_cell(calibration.effective_camera)
    img = np.asarray(image, np.float32)
    if image_mask is not None:
        img = np.where(np.asarray(image_mask, bool), np.float32(0), img)
    lit = lit_rays(lf, img, PARTICLE_BUNDLE.floor)       # the same fit, a fraction of the rays
    fit = bundle_positions(lit, img, seeds, settings=PARTICLE_BUNDLE, depth_cell=cell,
                           brightness=intensity)
    return np.where(fit.converged[:, None], fit.position, seeds)


def reconstruction_quality(volume, volume_true) -> float:
    """Q = Σ E E* / sqrt(Σ E² Σ E*²) (DESIGN.md §5)."""
    from plenopiv.reconstruction.mart import reconstruction_quality as q

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


# --------------------------------------------------------------------------------------------
# vectors and pairs
# --------------------------------------------------------------------------------------------


def piv_settings(cfg) -> PIVSettings:
    """PIV settings from a ``[piv]`` config table (:class:`plenopiv.config.PIVConfig`)."""
    try:
        return cfg.settings()
    except ValueError as exc:
        raise ConfigError(f"[piv] {exc}") from None


def correlate(result_a: VolumeResult, result_b: VolumeResult, settings=None, *, dt=None,
              workers=None, progress=None, mask=None, response=None) -> VectorResult:
    """3-D PIV between two reconstructed volumes of the same grid, in physical coordinates.

    The volumes are on the effective (air-equivalent) grid.

    ``mask``: volume mask (bool ``[z, y, x]``, True outside the flow). ``response``: a
    callable ``response(field) -> Response`` (:func:`plenopiv.piv.response.measure_response`)
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
    return VectorResult.from_field(field, result_a.correction, dt, uncertainty_method=method)


@dataclass(frozen=True)
class PairResult:
    """Everything one pair produced."""

    volume_a: VolumeResult
    volume_b: VolumeResult
    vectors: VectorResult
    timings: dict


class PairProcessor:
    """The per-pair work of one experiment and calibration, its projector built or loaded once.

    ``processor(image_a, image_b)`` reconstructs both exposures, finds their particles,
    corrects the depths and correlates them, with the experiment's settings
    (:class:`plenopiv.config.Experiment`). The weights (explicit, from the weights cache, or
    the matrix-free projector) and the image and volume masks are made on first use and kept
    for every later pair.
    """

    def __init__(self, experiment, calibration: Calibration, *,
                 weights: Weights | None = None):
        self.experiment = experiment
        self.calibration = calibration
        self._weights = weights
        self._masks = None

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
            from plenopiv.masks import image_mask, volume_mask

            exp = self.experiment
            self._masks = (image_mask(exp.mask, self.calibration.camera.sensor.shape,
                                      exp.base_dir),
                           volume_mask(exp.mask, exp.volume, exp.base_dir))
        return self._masks

    def __call__(self, image_a, image_b, *, progress: Progress = None,
                 workers=None) -> PairResult:
        """Images A and B -> two volumes -> particles -> corrections -> vectors."""
        t0 = time.perf_counter()
        exp, calibration = self.experiment, self.calibration
        weights = self.weights(progress)
        img_mask, vol_mask = self.masks()
        kw = dict(settings=exp.reconstruction, particles=exp.particles, weights=weights,
                  image_mask=img_mask)
        va = reconstruct_volume(calibration, image_a, exp.volume, **kw,
                                progress=_volume_progress(progress, "A"))
        vb = reconstruct_volume(calibration, image_b, exp.volume, **kw,
                                progress=_volume_progress(progress, "B"))
        t1 = time.perf_counter()
        if progress is not None:
            progress("piv", 0.0)
        settings = piv_settings(exp.piv)
        response = None
        if exp.piv.uncertainty == "response":
            response = _response_of(calibration, weights, va, exp, settings, workers,
                                    img_mask, vol_mask)
        vec = correlate(va, vb, settings, dt=exp.images.dt_s, workers=workers,
                        mask=vol_mask, response=response, progress=_piv_progress(progress))
        t2 = time.perf_counter()
        return PairResult(va, vb, vec, {"reconstruct_s": t1 - t0, "piv_s": t2 - t1})


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

    With the experiment's settings (:class:`plenopiv.config.Experiment`), the weights built
    once for both volumes.

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

    :func:`plenopiv.piv.response.measure_response` for this experiment, kept in the weights
    cache (``[output] weights_cache``) under a key of everything it depends on.
    """
    from plenopiv.piv import correlate_volumes
    from plenopiv.piv.response import cached_response, measure_response, response_key

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
        key = response_key(weights.key, grid.key(), experiment.reconstruction.model_dump(),
                           experiment.piv.model_dump(), n_particles,
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
    out = Path(out_dir)
    cfg = experiment.to_dict()
    paths = {}
    for tag, vol in (("A", result.volume_a), ("B", result.volume_b)):
        paths[f"volume_{tag}"] = str(vol.save(out / f"{name}_volume_{tag}.h5", config=cfg))
    if experiment.output.png:
        from plenopiv.plots import vector_slices, volume_slices

        va = result.volume_a
        paths["png_volume"] = str(volume_slices(va.volume, va.grid.x, va.grid.y, va.grid.z,
                                                out / f"{name}_volume_A.png",
                                                particles=va.particle_position_effective,
                                                title=f"pair {name}: volume A"))
        paths["png_vectors"] = str(vector_slices(result.vectors, out / f"{name}_vectors.png",
                                                 title=f"pair {name}: vectors"))
    files = result.vectors.save(out / f"{name}_vectors.h5", config=cfg, vtk=experiment.output.vtk,
                                extra_attrs={"complete": True, **(extra_attrs or {})})
    paths["vectors"] = str(files[0])
    if len(files) > 1:
        paths["vtk"] = str(files[1])
    return paths


@dataclass(frozen=True)
class ExperimentPairProcess:
    """The per-pair work of ``plenopiv run``: picklable, so dask workers can run it.

    A worker keeps one :class:`PairProcessor` per experiment and calibration file (keyed by
    their paths, sizes and modification times, :func:`worker_processor`): its first pair
    loads the experiment and the calibration and builds or loads the projector, its later
    pairs reuse them. Each call reads the pair's images, processes them and writes the
    products; the vectors file is written last, marked complete.
    """

    experiment_path: str
    calibration_path: str
    out_dir: str

    def __call__(self, job) -> dict:
        """Process one :class:`plenopiv.batch.PairJob`; returns a small summary."""
        import json

        from plenopiv.products.images import read_image

        processor = worker_processor(self.experiment_path, self.calibration_path)
        exp, cal = processor.experiment, processor.calibration
        ia, ib = read_image(job.image_a), read_image(job.image_b)
        res = processor(ia, ib)
        extra = {"image_a": str(job.image_a), "image_b": str(job.image_b)}
        if getattr(job, "identity", None) is not None:
            extra["identity"] = json.dumps(dict(job.identity), sort_keys=True)
        tracked = {}
        if exp.tracking.enabled:  # before the vectors file, which marks the pair complete
            from plenopiv.tracking.pair import track_and_save

            tracked = track_and_save(cal, ia, ib, res, exp, self.out_dir, job.name,
                                     weights=processor.weights())
        paths = save_pair(res, self.out_dir, job.name, exp, extra_attrs=extra)
        vec = res.vectors
        return {"vectors": paths["vectors"], "valid_fraction": float(np.mean(vec.valid)),
                "n_particles_a": len(res.volume_a.particle_position),
                **{k: round(v, 3) for k, v in res.timings.items()}, **tracked}


#: The :class:`PairProcessor` this process keeps, with its key (:func:`worker_processor`).
_WORKER_PROCESSOR: dict = {}
_WORKER_LOCK = threading.Lock()


def _file_identity(path: str | Path) -> tuple:
    """``(resolved path, size, modification time in ns)`` of a file."""
    p = Path(path).resolve()
    st = p.stat()
    return (str(p), st.st_size, st.st_mtime_ns)


def worker_processor(experiment_path: str | Path, calibration_path: str | Path
                     ) -> PairProcessor:
    """The :class:`PairProcessor` of this process for an experiment file and a calibration.

    Made on first use (the experiment and the calibration loaded, the projector built or read
    from the weights cache on the first pair) and kept for the later pairs of the process;
    a changed file (size or modification time) or another experiment replaces it. One is kept
    at a time, so a worker holds one projector.
    """
    key = (_file_identity(experiment_path), _file_identity(calibration_path))
    with _WORKER_LOCK:
        if _WORKER_PROCESSOR.get("key") != key:
            from plenopiv.config import load_experiment

            _WORKER_PROCESSOR.clear()
            prefer_small_pages()    # a batch worker's process is the batch's own
            exp = load_experiment(experiment_path)
            cal = experiment_calibration(exp, calibration_path)
            _WORKER_PROCESSOR.update(key=key, processor=PairProcessor(exp, cal))
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


def _camera_differences(made_for: CameraModel, used: CameraModel) -> list[str]:
    """What differs between the camera a calibration was made for and the one it is used with.

    Sensor, lattice, main-lens focal length (S_i is the calibration's to give).
    """
    def close(a, b):
        return math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-12)

    out = []
    a, b = made_for, used
    if a.sensor.shape != b.sensor.shape:
        out.append(f"sensor {a.sensor.rows} × {a.sensor.cols} px ≠ "
                   f"{b.sensor.rows} × {b.sensor.cols} px")
    if not close(a.sensor.pixel_pitch, b.sensor.pixel_pitch):
        out.append(f"pixel pitch {a.sensor.pixel_pitch * 1e6:g} µm ≠ "
                   f"{b.sensor.pixel_pitch * 1e6:g} µm")
    ma, mb = a.microlens_array, b.microlens_array
    if (ma.rows, ma.cols, ma.grid) != (mb.rows, mb.cols, mb.grid):
        out.append(f"lattice {ma.rows} × {ma.cols} {ma.grid} ≠ {mb.rows} × {mb.cols} {mb.grid}")
    for name, va, vb in (("lenslet pitch", ma.pitch, mb.pitch),
                         ("lenslet focal length", ma.focal_length, mb.focal_length),
                         ("lenslet-sensor distance", ma.sensor_distance, mb.sensor_distance)):
        if not close(va, vb):
            out.append(f"{name} {va * 1e6:g} µm ≠ {vb * 1e6:g} µm")
    if not close(a.main_lens.focal_length, b.main_lens.focal_length):
        out.append(f"main lens focal length {a.main_lens.focal_length * 1e3:g} mm ≠ "
                   f"{b.main_lens.focal_length * 1e3:g} mm")
    return out


#: The experiment camera's nominal S_i may differ from the calibrated one by this fraction;
#: beyond it the camera was refocused (or is another one) and needs its own calibration.
IMAGE_DISTANCE_TOLERANCE = 0.1


def _describe(camera: CameraModel, image_distance: float | None) -> str:
    si = "" if image_distance is None else f", S_i = {image_distance * 1e3:.5g} mm"
    mla = camera.microlens_array
    return (f"{camera.name!r} (main lens f = {camera.main_lens.focal_length * 1e3:g} mm{si}, "
            f"{mla.rows} × {mla.cols} lenslets of {mla.pitch * 1e6:g} µm, sensor "
            f"{camera.sensor.rows} × {camera.sensor.cols} px)")


def product_settings(experiment) -> dict:
    """The settings of an experiment that shape a pair's products.

    The camera, the grid, the reconstruction, particle, PIV and tracking tables, dt and the
    side products (vtk, png). Not the image patterns, the batch, the folders or the weight cache.
    """
    d = experiment.to_dict()
    return {"camera": d["camera"], "volume": d["volume"],
            "reconstruction": d["reconstruction"], "particles": d["particles"],
            "piv": d["piv"], "tracking": d.get("tracking"), "dt_s": d["images"].get("dt_s"),
            "vtk": d["output"].get("vtk"), "png": d["output"].get("png")}


def settings_identity(experiment) -> str:
    """SHA-256 of :func:`product_settings` (canonical JSON).

    Equal when, and only when, the products would be made with the same settings.
    """
    import hashlib

    from plenopiv.products.jsonio import to_json

    return hashlib.sha256(to_json(product_settings(experiment)).encode()).hexdigest()


def experiment_calibration(experiment, calibration_path) -> Calibration:
    """The calibration to use with an experiment.

    S_i and the lenslets come from the calibration product, the interfaces and back-side
    model from the experiment's camera.

    The calibration product records the camera it was made for; used with another camera
    (sensor, lattice or main-lens focal length differ, or the experiment's nominal S_i is
    more than 10 % from the calibrated one) it is a
    :class:`~plenopiv.errors.CalibrationError` naming both cameras and what differs.
    """
    cal = Calibration.load(calibration_path)
    cam = experiment.camera
    diffs = _camera_differences(cal.camera, cam)
    nominal = cam.main_lens.image_distance
    if not diffs and nominal is not None and \
            abs(nominal - cal.image_distance) > IMAGE_DISTANCE_TOLERANCE * cal.image_distance:
        diffs.append(f"calibrated S_i {cal.image_distance * 1e3:.5g} mm against the "
                     f"experiment camera's image_distance_mm = {nominal * 1e3:.5g} (more than "
                     f"{IMAGE_DISTANCE_TOLERANCE:.0%} apart: refocused?)")
    if diffs:
        raise CalibrationError(
            f"the calibration {str(calibration_path)!r} was made for camera "
            f"{_describe(cal.camera, cal.image_distance)} but the experiment's camera is "
            f"{_describe(cam, nominal)}: {'; '.join(diffs)}. Use this camera's calibration "
            "(plenopiv calibrate) or the experiment file of the calibrated camera")
    return cal.with_camera(cam)
