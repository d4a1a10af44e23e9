"""Compile a run's later numba kernels in background processes while it does other work.

A first run spends most of its time compiling numba kernels, one after another on one core.
Where a run has other work first (the demo renders before it calibrates, and calibrates before
it reconstructs), :class:`Rehearsals` starts two child processes that call the later stages'
kernels on small inputs of the run's own camera, voxels and settings (:data:`REHEARSALS`:
spot detection and PIV in one child, the reconstruction in the other), so that numba writes
them to its cache (:func:`plenopiv.cache_dir`); the run, entering a stage
(:data:`STAGE_AT_PROGRESS`), waits for that stage's rehearsal only. Children are forks where
that is safe (:func:`can_fork`), new interpreters otherwise. Nothing depends on it: a
rehearsal that fails or times out leaves the run to compile what it needs, with the same
results; none is started where the kernels are cached already, nor on one core.
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import threading
import warnings
from dataclasses import replace

import numpy as np

from plenopiv.products.locks import HEARTBEAT_THREAD

#: Edge of the rehearsal's reconstruction volume, voxels (its PIV volume holds three of the
#: first pass's windows along each axis, so that the median test has neighbours).
RECONSTRUCTION_EDGE = 16

#: Blobs of the rehearsal's volumes per 1000 voxels, and their standard deviation in voxels.
BLOBS_PER_KVOX = 2.0
BLOB_SIGMA_VOX = 1.0

#: Lenslets along each side of the calibration rehearsal's spot image, and the spots' σ, px.
SPOT_LENSLETS = 8
SPOT_SIGMA_PX = 1.2

#: Seconds a run waits for its rehearsals before it goes on without them.
DEFAULT_TIMEOUT_S = 300.0

#: The stages a child can rehearse, each a function of ``(calibration, experiment)``.
REHEARSALS = {"calibration": "rehearse_calibration",
              "reconstruction": "rehearse_reconstruction",
              "piv": "rehearse_piv"}

#: The stages of each child process by default: the calibration's spots first, as the run
#: reaches them first; the reconstruction's kernels take as long as the other two together.
DEFAULT_CHILDREN = (("calibration", "piv"), ("reconstruction",))


def rehearsal_grid(grid, shape):
    """A grid of ``grid``'s voxels about its centre, at most ``shape`` (z, y, x) voxels."""
    from plenopiv.camera.grid import VolumeGrid

    n = np.minimum(np.asarray(grid.shape), np.asarray(shape))                    # z, y, x
    centre = np.asarray(grid.origin) + 0.5 * (np.asarray(grid.shape[::-1]) - 1) * grid.voxel
    origin = centre - 0.5 * (n[::-1] - 1) * np.asarray(grid.voxel)
    return VolumeGrid(tuple(float(v) for v in origin), tuple(grid.voxel),
                      tuple(int(v) for v in n))


def rehearsal_experiment(experiment, grid):
    """``experiment`` on ``grid``, without its masks and its weights cache (nothing written)."""
    from plenopiv.config.experiment import MaskConfig

    return replace(experiment, volume=grid, mask=MaskConfig(),
                   output=experiment.output.model_copy(update={"weights_cache": ""}))


def blob_volume(shape, rng: np.random.Generator, *, shift_vox=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Gaussian blobs at random places in a ``[z, y, x]`` volume, float32, peak 1.

    :data:`BLOBS_PER_KVOX` of them, σ :data:`BLOB_SIGMA_VOX`, all moved by ``shift_vox``.
    """
    shape = tuple(int(n) for n in shape)
    n = max(4, int(BLOBS_PER_KVOX * np.prod(shape) / 1000))
    centres = rng.uniform(1.0, np.asarray(shape) - 2.0, size=(n, 3)) + np.asarray(shift_vox)
    axes = np.meshgrid(*(np.arange(k, dtype=np.float32) for k in shape), indexing="ij",
                       sparse=True)
    vol = np.zeros(shape, np.float32)
    for c in centres:
        r2 = sum((a - np.float32(ci)) ** 2 for a, ci in zip(axes, c, strict=True))
        vol += np.exp(-0.5 * r2 / BLOB_SIGMA_VOX ** 2).astype(np.float32)
    return vol


def spot_image(camera, lenslets: int = SPOT_LENSLETS) -> np.ndarray:
    """A uint16 image of ``lenslets`` x ``lenslets`` Gaussian focal spots.

    On ``camera``'s lenslet pitch and grid, σ :data:`SPOT_SIGMA_PX`, as a camera records them.
    """
    mla = camera.microlens_array
    pitch = mla.pitch / camera.sensor.pixel_pitch
    rows, cols = np.mgrid[0:lenslets, 0:lenslets].astype(float)
    if mla.grid == "hexagonal":
        cols, rows = cols + 0.5 * (rows % 2), rows * np.sqrt(3.0) / 2.0
    centres = (np.stack([rows.ravel(), cols.ravel()], axis=1) + 1.0) * pitch
    shape = tuple(int(np.ceil(pitch * (lenslets + 1))) for _ in range(2))
    r, c = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    image = np.zeros(shape)
    for cr, cc in centres:
        image += np.exp(-0.5 * ((r - cr) ** 2 + (c - cc) ** 2) / SPOT_SIGMA_PX ** 2)
    return np.round(40000.0 * image + 200.0).astype(np.uint16)


def rehearse_calibration(calibration, experiment) -> None:
    """Find and refine the spots of a small image of focal spots of the run's camera."""
    from plenopiv.calibration.spot_detection import detect_spots

    camera = calibration.camera
    detect_spots(spot_image(camera), grid=camera.microlens_array.grid)


def rehearse_reconstruction(calibration, experiment) -> None:
    """Reconstruct a tiny volume of the run's voxels with the run's settings.

    The image is a volume of Gaussian blobs projected by the run's own kind of projector, so
    the reconstruction finds particles and fits their light-field positions, and the
    tracking (where the run tracks) fits and refines their ray bundles; it is judged
    first as a run judges its images (the preprocessing's micro-image and neighbour kernels),
    and the recording check's model of micro-images is drawn once on a few pixels.
    """
    import warnings

    from plenopiv.calibration._recording_kernels import soft_discs
    from plenopiv.workflow.pair import PairProcessor
    from plenopiv.workflow.preprocess import ImagePreparation
    from plenopiv.workflow.volume import reconstruct_volume

    grid = rehearsal_grid(experiment.volume, (RECONSTRUCTION_EDGE,) * 3)
    tiny = rehearsal_experiment(experiment, grid)
    weights = PairProcessor(tiny, calibration).weights()
    rng = np.random.default_rng(0)
    shape = calibration.camera.sensor.shape
    image = weights.forward_image(blob_volume(weights.grid.shape, rng), shape)
    image *= np.float32(1000.0 / max(float(image.max()), 1e-12))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ImagePreparation(tiny, calibration).image(image)
    volume = reconstruct_volume(calibration, image, grid, settings=tiny.reconstruction,
                                particles=tiny.particles, weights=weights)
    if tiny.tracking.correct_vectors or tiny.tracking.enabled:
        # the pair's tracks: ray bundles and their forward refinement on the same image
        from plenopiv.particles.forward import _best_offset_numba
        from plenopiv.workflow.tracking import _light_field_of, track_ends

        rec = tiny.reconstruction
        track_ends(calibration, image, image, volume, volume, settings=tiny.tracking,
                   f_number=rec.f_number, min_lit=rec.min_lit, lf=_light_field_of(weights))
        # the grid search of particles near focus, which the blobs need not reach
        two = np.zeros((2, 2))
        _best_offset_numba(np.array([0, 2], np.int64), two, two, np.zeros(2), np.ones(1),
                           np.zeros((1, 3)), np.zeros(1), np.zeros(1),
                           {"object_distance": 0.1, "cell": 1e-5, "footprint": 1e-4}, 1.0)
    soft_discs((8, 8), np.array([[3.0, 4.0]]), 2.0, 1.0)


def rehearse_piv(calibration, experiment) -> None:
    """Correlate two tiny volumes of Gaussian blobs with the run's PIV settings."""
    from plenopiv.piv import correlate_volumes

    settings = experiment.piv
    first = np.asarray(settings.windows[0])
    step = np.maximum(1, np.round(first * (1.0 - settings.overlap))).astype(int)
    grid = rehearsal_grid(experiment.volume, first + 2 * step)
    rng = np.random.default_rng(0)
    a = blob_volume(grid.shape, rng)
    b = blob_volume(grid.shape, np.random.default_rng(0), shift_vox=(0.4, 1.3, -0.7))
    b += 0.05 * rng.random(grid.shape, dtype=np.float32)      # a few weak outliers
    correlate_volumes(a, b, grid, settings=settings)


def kernels_cached() -> bool:
    """Whether numba's cache holds the PIV's and the reconstruction's last kernels already.

    Reads the cache index of one kernel of each stage (numba's, for the installed source): a
    cache that holds them was filled by a run before.
    """
    try:
        from plenopiv.particles._kernels import refine_peaks as particle_peaks
        from plenopiv.piv._kernels.peaks import refine_peaks

        # an index written for another version of the source loads as empty
        return all(bool(k._cache._cache_file._load_index()) for k in (refine_peaks,
                                                                       particle_peaks))
    except Exception:               # numba's private cache API moved: assume a cold cache
        return False


#: The progress stages of a run (:func:`plenopiv.workflow.pair.process_pair`,
#: :func:`plenopiv.workflow.vortex_case.run_case`) at which it calls the kernels of a rehearsed
#: stage first: :meth:`Rehearsals.paced` waits there for that stage's rehearsal. The chain's
#: response correlates its test pairs before the pair's own PIV.
STAGE_AT_PROGRESS = {"calibrate": "calibration", "weights": "reconstruction",
                     "response": "piv", "piv": "piv"}


class _Forked:
    """A rehearsal in a forked child: the little of :class:`subprocess.Popen` used here."""

    def __init__(self, pid: int):
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self) -> int:
        if self.returncode is None:
            _, status = os.waitpid(self.pid, 0)
            self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def kill(self) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def can_fork() -> bool:
    """Whether a rehearsal may be a fork of this process (no import, no pickling).

    On Linux, while this process runs one thread and numba has not started its own: a fork
    copies only the calling thread, and a lock held by another one would stay held. The
    output locks' heartbeat (:mod:`plenopiv.products.locks`) does not count: it holds no
    lock a child uses, and a child never touches the output locks.
    """
    try:
        from numba.np.ufunc import parallel

        numba_threads = bool(parallel._is_initialized)
    except (ImportError, AttributeError):        # numba's private state moved: do not fork
        numba_threads = True
    others = [t for t in threading.enumerate()
              if t is not threading.current_thread() and t.name != HEARTBEAT_THREAD]
    return (sys.platform.startswith("linux") and hasattr(os, "fork")
            and not others and not numba_threads)


class Rehearsals:
    """The background rehearsals of one run: ``start``, do other work, wait at each stage.

    Each child reports every stage it has rehearsed (a line on a pipe); :meth:`ready`
    waits for one stage, :meth:`wait` for every child. As a context manager, any rehearsal
    still running at the end of the block is stopped (an error in the run leaves no process
    behind).
    """

    def __init__(self, processes: list, streams=(), groups=()):
        self.processes = processes
        self.groups = [tuple(g) for g in groups]
        self._done: set[str] = set()
        self._ended: set[int] = set()
        self._changed = threading.Condition()
        for i, stream in enumerate(streams):
            threading.Thread(target=self._listen, args=(i, stream), daemon=True,
                             name=f"plenopiv-rehearsal-{i}").start()

    def _listen(self, index: int, stream) -> None:
        with stream:
            for line in stream:
                with self._changed:
                    self._done.add(line.strip())
                    self._changed.notify_all()
        with self._changed:
            self._ended.add(index)
            self._changed.notify_all()

    def __enter__(self) -> Rehearsals:
        return self

    def __exit__(self, *exc) -> None:
        for p in self.processes:
            if p.poll() is None:
                p.kill()
                p.wait()

    @classmethod
    def start(cls, calibration, experiment, *, children=DEFAULT_CHILDREN,
              force: bool = False, fork: bool | None = None) -> Rehearsals:
        """Start one process per group of stages of ``children``; none where not needed.

        Not started (an empty set) on one core or where :func:`kernels_cached`, unless
        ``force``. ``fork``: fork this process (:func:`can_fork`; saves each child the
        imports) or start a new interpreter; None: fork where it can.
        """
        for stage in (s for group in children for s in group):
            if stage not in REHEARSALS:
                raise ValueError(f"stage = {stage!r}: expected one of {tuple(REHEARSALS)}")
        if not force and ((os.cpu_count() or 1) < 2 or kernels_cached()):
            return cls([])
        launch = _fork if (can_fork() if fork is None else fork) else _spawn
        # every child is started before the first listening thread (a fork copies none)
        processes, streams = zip(*(launch(group, calibration, experiment)
                                   for group in children), strict=True)
        return cls(list(processes), streams, children)

    def rehearsed(self, stage: str) -> bool:
        """Whether ``stage`` has been rehearsed (without waiting)."""
        with self._changed:
            return stage in self._done

    def ready(self, stage: str, timeout: float = DEFAULT_TIMEOUT_S) -> bool:
        """Wait until ``stage`` is rehearsed; whether it was (False: not rehearsed here).

        A child that fails or ends stops the wait for its stages; one still working on
        ``stage`` at ``timeout`` is stopped, the run then compiles what it needs itself.
        """
        holders = [i for i, g in enumerate(self.groups) if stage in g]
        if not holders:
            return False
        with self._changed:
            self._changed.wait_for(lambda: stage in self._done
                                   or all(i in self._ended for i in holders), timeout)
            if stage in self._done:
                return True
        for i in holders:
            if i not in self._ended:
                self.processes[i].kill()
        return False

    def paced(self, progress=None):
        """``progress`` that first waits, on entering a stage, for that stage's rehearsal.

        The stages are the run's progress stages of :data:`STAGE_AT_PROGRESS`; every call is
        passed on to ``progress`` (None: none).
        """
        def report(stage: str, fraction: float = 0.0) -> None:
            if stage in STAGE_AT_PROGRESS:
                self.ready(STAGE_AT_PROGRESS[stage])
            if progress is not None:
                progress(stage, fraction)
        return report

    def wait(self, timeout: float = DEFAULT_TIMEOUT_S) -> list[int | None]:
        """Wait for every rehearsal to end; their exit codes (None: stopped at ``timeout``)."""
        with self._changed:
            self._changed.wait_for(lambda: len(self._ended) == len(self.processes), timeout)
            ended = set(self._ended)
        codes = []
        for i, p in enumerate(self.processes):
            if i in ended:                      # its output closed: it is exiting
                codes.append(p.wait())
            else:
                p.kill()
                p.wait()
                codes.append(None)
        return codes


def _rehearse(stages, calibration, experiment, done) -> int:
    """Rehearse ``stages`` in turn, calling ``done(stage)`` after each; exit status 0 or 1."""
    warnings.simplefilter("ignore")
    try:
        for stage in stages:
            globals()[REHEARSALS[stage]](calibration, experiment)
            done(stage)
    except Exception:               # the run compiles what is missing itself
        return 1
    return 0


def _fork(stages, calibration, experiment):
    """A forked child rehearsing ``stages``: ``(process, stream of rehearsed stages)``."""
    read, write = os.pipe()
    with warnings.catch_warnings():
        # Python 3.12+ warns of a fork in a process it sees running several threads; here
        # they are the BLAS libraries' pools (OpenBLAS quiesces them across a fork),
        # :func:`can_fork` having ruled out Python's and numba's threads.
        warnings.simplefilter("ignore", DeprecationWarning)
        pid = os.fork()
    if pid == 0:                                        # the child: never returns
        code = 1
        try:
            os.close(read)
            null = os.open(os.devnull, os.O_RDWR)
            for fd in (0, 1, 2):
                os.dup2(null, fd)
            code = _rehearse(stages, calibration, experiment,
                             lambda stage: os.write(write, f"{stage}\n".encode()))
        finally:
            os._exit(code)
    os.close(write)
    return _Forked(pid), os.fdopen(read, "r")


def _spawn(stages, calibration, experiment):
    """A new interpreter rehearsing ``stages``: ``(process, stream of rehearsed stages)``."""
    p = subprocess.Popen([sys.executable, "-m", "plenopiv.workflow.precompile", *stages],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.DEVNULL, text=True)
    p.stdin.buffer.write(pickle.dumps((calibration, experiment)))
    p.stdin.close()
    return p, p.stdout


def _child(stages: list[str]) -> int:
    """A spawned rehearsal: exit status 0 or 1.

    The pickled calibration and experiment on stdin; the name of each rehearsed stage on
    stdout.
    """
    try:
        calibration, experiment = pickle.load(sys.stdin.buffer)
    except Exception:
        return 1

    def done(stage):
        print(stage, flush=True)
    return _rehearse(stages, calibration, experiment, done)


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1:]))
